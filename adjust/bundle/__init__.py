"""Bundle block adjustment of frame images ([P2]), map-Cartesian mode.

Unknowns: six pose parameters per image (X0, Y0, Z0 in m; omega, phi, kappa in radians inside,
degrees at the interface) and three coordinates per tie and control point (control points with
sigma 0 are constants). Observations: image coordinates (collinearity, [P2] eqs. 4-6,
weights 1/sigma^2), control coordinates, GNSS projection centres and INS attitudes as weighted
direct observations. Check points never enter; they are intersected afterwards with the
adjusted poses.

Solution: Levenberg-Marquardt on the normal equations partitioned into 6x6 image blocks U,
3x3 point blocks V and the image-point blocks W ([P2] eq. 10); the point blocks are
eliminated (Schur complement ``S = U - W V^-1 W^T``, the reduced camera system, formed as one
sparse product), S is factorised sparse (SuperLU) and the points back-substituted. Statistics ([P2] eq. 11 and the usual
photogrammetric set): sigma0, covariances ``sigma0^2 Q`` of every pose (6x6) and point (3x3) from
solves with the factorisation (no dense inverse), residuals, redundancy numbers, Baarda's
w-test with optional iterative rejection, an optional Huber loss, high-correlation warnings,
RMSE per axis at control and check points.

Gross blunders (hundreds to tens of thousands of pixels): initial tie points come from a
consensus of ray pairs and resections are trimmed, so one blunder does not spoil the start;
with snooping or the robust estimation, an iteratively reweighted (Huber, cut off beyond
``ROBUST_CUT`` scales) adjustment comes first, gross blunders are set aside, and least squares
runs on the rest; set-aside observations are tested again with their predicted residuals.
Bad input is refused before iterating, with what is wrong (images with too few observations,
groups of images without a datum, points behind their camera at the start, parallel rays);
a run that fails (iteration limit, singular, diverged, too many blunders) returns a result
with ``success`` False, a status and a message, never a numpy error.

The modules follow the steps of an adjustment (the public names are the ones below; the
modules' own names are internal):

- :mod:`.checks`: the arguments validated up front, the block's structure and datum, the
  start (parallel rays, points behind their camera), diagnoses of singular systems;
- :mod:`.problem`: the parameter layout, the observations and priors, the cost ``v^T P v``;
- :mod:`.initial`: initial poses (GNSS/INS, space resection) and points;
- :mod:`.intersection`: :func:`intersect`, points from their rays with the poses held;
- :mod:`.normal`: the Jacobians into normal-equation blocks, the reduced system's sparsity,
  its Schur complement and factorisation;
- :mod:`.solve`: :func:`bundle_adjust`, the Levenberg-Marquardt loop, the robust start and
  data snooping;
- :mod:`.statistics`: sigma0, cofactor blocks, redundancy numbers, w-tests;
- :mod:`.result`: :class:`AdjustResult` and how it is filled;
- :mod:`.batched`: batched small solves.
"""

# resect and the constants are not in __all__: importable from here, as before the package
from .initial import resect  # noqa: F401
from .intersection import intersect
from .problem import POSE_NAMES  # noqa: F401
from .result import AdjustResult
from .solve import GROSS_FACTOR, ROBUST_CUT, bundle_adjust  # noqa: F401
from .statistics import JOINT_LIMIT  # noqa: F401

__all__ = ["bundle_adjust", "AdjustResult", "intersect"]
