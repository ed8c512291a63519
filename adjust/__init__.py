"""SciPy adjustment stage: bundle block adjustment of frame images ([P2]).

- :class:`Block`: a block as arrays (its files: :func:`orthowarp.read_block` /
  :func:`orthowarp.write_block`, :mod:`orthowarp.pipeline.blockio`; this package touches no file);
- :func:`bundle_adjust` -> :class:`AdjustResult`;
- the observation equations and their Jacobians: :mod:`orthowarp.collinearity` (the frame sensor's own);
- :class:`ScenePoints` (points measured in pushbroom scenes; files: :func:`orthowarp.read_scene_points`)
  and :func:`preadjust_look_angles`: [P1]'s look-angle pre-adjustment of SPOT-5 level-1A
  scenes (:mod:`~orthowarp.adjust.lookangles`); :func:`adjust_scenes`: its bundle adjustment
  of exterior-orientation coefficient groups over a stereo pair (:mod:`~orthowarp.adjust.spot_bundle`;
  simulated pairs: :mod:`~orthowarp.adjust.spot_synthetic`);
- :func:`match_points`: area-based matching (NCC search, then least-squares matching) of
  points between two images on a Warp device (:mod:`~orthowarp.adjust.matching`);
- :func:`synthetic_block`: blocks with known truth (:func:`film_camera`: [P2]'s kind of camera);
- :func:`monoplot_covariance`, :func:`intersection_covariance`: ground points' precision by
  error propagation ([P4]; :mod:`~orthowarp.adjust.precision`).
"""

from .block import ROLES, Block
from .lookangles import LookAngleResult, preadjust_look_angles
from .matching import MatchResult, interest_points, match_points
from .scene_points import ScenePoints
from .spot_bundle import EO_GROUPS, SceneBundleResult, adjust_scenes, intersect_scene_points
from .bundle import AdjustResult, bundle_adjust, intersect
from .precision import PrecisionResult, input_covariance, intersection_covariance, monoplot_covariance
from .synthetic import CONTROL_LAYOUTS, film_camera, synthetic_block

__all__ = ["Block", "ROLES", "AdjustResult", "bundle_adjust", "intersect", "synthetic_block", "film_camera",
           "CONTROL_LAYOUTS", "PrecisionResult", "ScenePoints", "LookAngleResult", "preadjust_look_angles",
           "EO_GROUPS", "SceneBundleResult", "adjust_scenes", "intersect_scene_points", "MatchResult", "match_points", "interest_points", "monoplot_covariance",
           "intersection_covariance", "input_covariance"]

