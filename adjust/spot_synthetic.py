"""Simulated SPOT-like stereo pairs with truth, for the pushbroom adjustment's tests and bench
(the setting of [P1]: two scenes of one area from different orbits and mirror angles,
ground control from a GPS survey, image measurements of a few tenths of a pixel).

- :func:`stereo_pair`: two synthetic scenes whose centres see the same ground point.
- :func:`perturbed`: a scene with look-angle and exterior-orientation errors added (the truth
  that the nominal metadata misses).
- :func:`simulate_points`: points in the overlap measured in both true scenes, with noise.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .. import geodesy
from ..pushbroom import PushbroomScene, synthetic_scene
from .lookangles import corrected_scene
from .scene_points import ScenePoints

__all__ = ["stereo_pair", "perturbed", "simulate_points", "LAYOUTS"]

LAYOUTS = ("H-0", "H-20", "G-A", "G-B")
"""Point distributions of [P1]'s Tables 1-2 (47 points: H-0 47 control; H-20 27 control, 20
check; G-A 23 control, 24 check; G-B 24 control, 23 check):

- H-0: every point is control;
- H-20: 20 check points drawn at random among the points (half the points below 40), the rest
  control, both spread over the scene;
- G-A: control only in one half of the detector line: the points with the smallest columns of
  the first scene (23 of 47) are control, the rest check points. [P1] explains G-A's large
  check errors by exactly this: its control does not spread over the whole line, and look
  angles belong to the detectors, so half of the line gets adjusted look angles and the other
  half extrapolated ones;
- G-B: control only in one half of the lines: the points with the smallest rows of the first
  scene (24 of 47) are control; the control spans the whole detector line. [P1] draws G-B only
  (its Figure 4); this is our reading: grouped like G-A, but along the other image axis, which
  its results (check errors like H-20's) and its text (only G-A leaves part of the line without
  control) call for.

Other ``n`` scale the G-A and G-B control counts (23/47 and 24/47 of the points)."""

GROUPED_CONTROL = {"G-A": (0, 23), "G-B": (1, 24)}  # image axis (0 col, 1 row), control points of 47


def stereo_pair(*, width: int = 3000, height: int = 3000, gsd: float = 10.0,
                view_angles: tuple[float, float] = (-12.0, 12.0), lat: float = 44.0,
                lon: float = 5.0) -> tuple[PushbroomScene, PushbroomScene]:
    """Two synthetic scenes (:func:`~orthowarp.pushbroom.synthetic_scene`, with the polynomials
    of their exterior orientation fitted) whose centre pixels see one ground point at h = 0:
    the second orbit is shifted until its centre meets the first's.

    Parameters
    ----------
    width, height : int, optional
        Scene size (px).
    gsd : float, optional
        Ground sample distance (m).
    view_angles : (float, float), optional
        The two scenes' mirror angles (deg).
    lat, lon : float, optional
        The first scene's centre (deg).

    Returns
    -------
    (PushbroomScene, PushbroomScene)
    """
    a = synthetic_scene(width=width, height=height, gsd=gsd, view_angle=view_angles[0], lat=lat, lon=lon)
    centre = np.array([[0.5 * width, 0.5 * height]])
    target = a.geolocate_ellipsoid(centre)[0]
    la, lo = lat, lon
    for _ in range(6):
        b = synthetic_scene(width=width, height=height, gsd=gsd, view_angle=view_angles[1], lat=la, lon=lo)
        got = b.geolocate_ellipsoid(centre)[0]
        lo, la = lo + (target[0] - got[0]), la + (target[1] - got[1])
    b = synthetic_scene(width=width, height=height, gsd=gsd, view_angle=view_angles[1], lat=la, lon=lo)
    return tuple(s.with_polynomials(s.fit_polynomials()[0]) for s in (a, b))


def perturbed(scene: PushbroomScene, *, look: ArrayLike | None = None,
              eo: ArrayLike | None = None) -> PushbroomScene:
    """The scene with errors.

    Parameters
    ----------
    scene : PushbroomScene
    look : array_like, shape (2, k), optional
        Look-angle corrections (rad, polynomials in the normalised detector number, as
        :func:`~orthowarp.adjust.lookangles.corrected_scene`).
    eo : array_like, shape (3, 3, 3), optional
        Added to the exterior-orientation coefficients (m, m/s, rad per power of t).

    Returns
    -------
    PushbroomScene
    """
    out = scene if look is None else corrected_scene(scene, look)
    if eo is not None:
        out = out.with_polynomials(out.polynomials + np.asarray(eo, dtype=np.float64))
    return out


def simulate_points(truth: dict[str, PushbroomScene], *, n: int = 47, layout: str = "H-20",
                    ground_sigma: tuple[float, float, float] = (0.06, 0.06, 1.0), pixel_sigma: float = 0.25,
                    heights: tuple[float, float] = (0.0, 600.0), seed: int = 0, noise: bool = True,
                    margin: float = 30.0) -> tuple[ScenePoints, np.ndarray]:
    """Points in the overlap of the true scenes, measured in both.

    Parameters
    ----------
    truth : dict of str -> PushbroomScene
        The true scenes (two); the first one's pixels are drawn, their ground points (at
        uniform random heights) projected into the second.
    n : int, optional
    layout : {"H-0", "H-20", "G-A", "G-B"}, optional
        See :data:`LAYOUTS` (G-A: control in one half of the detector line; G-B: in one half
        of the lines).
    ground_sigma : (float, float, float), optional
        Control coordinates' noise east, north, up (m): [P1]'s GPS survey.
    pixel_sigma : float, optional
        Image measurement noise (px).
    heights : (float, float), optional
        Range of the points' ellipsoidal heights (m).
    seed : int, optional
    noise : bool, optional
        False: exact observations.
    margin : float, optional
        Pixels left at the scenes' borders.

    Returns
    -------
    points : ScenePoints
    true_llh : ndarray, shape (n, 3)
    """
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    rng = np.random.default_rng(seed)
    (ia, a), (ib, b) = list(truth.items())[:2]
    llh, pa, pb = [], [], []
    while len(llh) < n:
        pix = np.array([[rng.uniform(margin, a.width - margin), rng.uniform(margin, a.height - margin)]])
        g = a.geolocate_ellipsoid(pix, rng.uniform(*heights))[0]
        x = geodesy.geodetic_to_ecef(g[1], g[0], g[2])[None]
        q = b.project_ecef(x, tol=1e-9)[0]
        if np.all(np.isfinite(q)) and margin < q[0] < b.width - margin and margin < q[1] < b.height - margin:
            llh.append(g), pa.append(pix[0]), pb.append(q)
    llh, pa, pb = np.array(llh), np.array(pa), np.array(pb)
    if layout == "H-0":
        roles = ["control"] * n
    elif layout == "H-20":
        roles = ["control"] * n
        for i in rng.choice(n, 20 if n >= 40 else n // 2, replace=False):
            roles[i] = "check"
    else:  # grouped: the control points are those nearest one end of an image axis
        axis, of_47 = GROUPED_CONTROL[layout]
        n_control = min(max(int(round(n * of_47 / 47)), 1), n - 1) if n > 1 else n
        first = set(np.argsort(pa[:, axis], kind="stable")[:n_control].tolist())
        roles = ["control" if i in first else "check" for i in range(n)]
    given = llh.copy()
    obs_a, obs_b = pa.copy(), pb.copy()
    if noise:
        enu = rng.normal(0.0, 1.0, (n, 3)) * ground_sigma
        x = geodesy.geodetic_to_ecef(llh[:, 1], llh[:, 0], llh[:, 2])
        x = x + np.matmul(geodesy.enu_to_ecef_matrix(llh[:, 1], llh[:, 0]), enu[:, :, None])[:, :, 0]
        lat, lon, h = geodesy.ecef_to_geodetic(x)
        given = np.stack([lon, lat, h], -1)
        obs_a = obs_a + rng.normal(0.0, pixel_sigma, obs_a.shape)
        obs_b = obs_b + rng.normal(0.0, pixel_sigma, obs_b.shape)
    sig = np.array([ground_sigma if r == "control" else (np.nan,) * 3 for r in roles], dtype=np.float64)
    pts = ScenePoints(scene_ids=[ia, ib], point_ids=[f"P{k:02d}" for k in range(n)], roles=roles, llh=given,
                      llh_sigma=sig, obs_scene=np.repeat([0, 1], n), obs_point=np.tile(np.arange(n), 2),
                      obs_xy=np.concatenate([obs_a, obs_b]), obs_sigma=np.full(2 * n, float(pixel_sigma)),
                      name=f"simulated {layout}")
    return pts, llh
