"""SciPy adjustment stage: bundle block adjustment of frame images ([P2]).

- :class:`Block`: a block as arrays (its files: :func:`orthowarp.read_block` /
  :func:`orthowarp.write_block`, :mod:`orthowarp.pipeline.formats.block`; this package touches no file);
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
  error propagation ([P4]; :mod:`~orthowarp.adjust.precision`);
- :func:`estimate_bias`, :func:`leave_one_out`: an RPC image's bias compensation from ground
  control, :func:`fit_rpc`: RPC00B coefficients fitted to a sensor's 3-D grid
  (:mod:`~orthowarp.adjust.rpc`).
"""

# The names below are imported when first used (PEP 562), so that importing one module of this
# package (``orthowarp.adjust.precision`` for the ortho's accuracy rasters, say) does not load
# the bundle adjustment and SciPy's sparse solvers with it.
_LAZY = {
    "ROLES": ".block",
    "Block": ".block",
    "LookAngleResult": ".lookangles",
    "preadjust_look_angles": ".lookangles",
    "MatchResult": ".matching",
    "interest_points": ".matching",
    "match_points": ".matching",
    "ScenePoints": ".scene_points",
    "EO_GROUPS": ".spot_bundle",
    "SceneBundleResult": ".spot_bundle",
    "adjust_scenes": ".spot_bundle",
    "intersect_scene_points": ".spot_bundle",
    "AdjustResult": ".bundle",
    "bundle_adjust": ".bundle",
    "intersect": ".bundle",
    "PrecisionResult": ".precision",
    "input_covariance": ".precision",
    "intersection_covariance": ".precision",
    "monoplot_covariance": ".precision",
    "CONTROL_LAYOUTS": ".synthetic",
    "film_camera": ".synthetic",
    "synthetic_block": ".synthetic",
    "BiasResult": ".rpc",
    "RpcFitResult": ".rpc",
    "estimate_bias": ".rpc",
    "leave_one_out": ".rpc",
    "fit_rpc": ".rpc",
}

__all__ = ["Block", "ROLES", "AdjustResult", "bundle_adjust", "intersect", "synthetic_block", "film_camera",
           "CONTROL_LAYOUTS", "PrecisionResult", "ScenePoints", "LookAngleResult", "preadjust_look_angles",
           "EO_GROUPS", "SceneBundleResult", "adjust_scenes", "intersect_scene_points", "MatchResult", "match_points", "interest_points", "monoplot_covariance",
           "intersection_covariance", "input_covariance", "BiasResult", "RpcFitResult", "estimate_bias",
           "leave_one_out", "fit_rpc"]


def __getattr__(name):
    import importlib

    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
