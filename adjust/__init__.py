"""SciPy adjustment stage: bundle block adjustment of frame images (seed 002).

- :class:`Block`: a block as arrays; :func:`read_block` / :func:`write_block` (JSON, see
  :mod:`orthowarp.pipeline.blockio`);
- :func:`bundle_adjust` -> :class:`AdjustResult`;
- :mod:`~orthowarp.adjust.collinearity`: the observation equations and their Jacobians;
- :func:`synthetic_block`: blocks with known truth (:func:`film_camera`: seed 002's kind of camera);
- :func:`monoplot_covariance`, :func:`intersection_covariance`: ground points' precision by
  error propagation (seed 004; :mod:`~orthowarp.adjust.precision`).
"""

from .block import ROLES, Block
from .bundle import AdjustResult, bundle_adjust, intersect
from .precision import PrecisionResult, intersection_covariance, monoplot_covariance
from .synthetic import CONTROL_LAYOUTS, film_camera, synthetic_block

__all__ = ["Block", "ROLES", "AdjustResult", "bundle_adjust", "intersect", "synthetic_block", "film_camera",
           "CONTROL_LAYOUTS", "read_block", "write_block", "PrecisionResult", "monoplot_covariance",
           "intersection_covariance"]


def read_block(path, *, drop_outside=False):
    """Read a block file (JSON; see :func:`orthowarp.pipeline.blockio.read_block`)."""
    from ..pipeline.blockio import read_block as _read

    return _read(path, drop_outside=drop_outside)


def write_block(block, path):
    """Write a block file (JSON), atomically."""
    from ..pipeline.blockio import write_block as _write

    return _write(block, path)
