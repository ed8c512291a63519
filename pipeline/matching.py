"""Tie points between frame images by area-based matching, predicted through the sensors'
geometry (seed 002; issue 15): interest points of one image, their ground points on the DEM,
their predicted pixels in the other image, NCC + least-squares matching
(:func:`orthowarp.adjust.match_points`), back-matching.
"""

from dataclasses import dataclass

import numpy as np

from ..adjust.matching import interest_points, match_points
from ..errors import ParamError
from ..sensor import FrameSensor
from .geometry import geolocate, project

__all__ = ["PairMatches", "match_pair"]


@dataclass
class PairMatches:
    """Matches of one image pair.

    Attributes
    ----------
    left, right : ndarray, shape (k, 2)
        (col, row) of the accepted points in each image.
    sigma : ndarray, shape (k, 2)
        Least-squares sigmas (px) of the right positions.
    predicted : ndarray, shape (k, 2)
        Where the orientation predicted them in the right image.
    score : ndarray, shape (k,)
    candidates : int
        Interest points whose prediction fell inside the right image.
    back_error : ndarray, shape (k,)
        Distance (px) between each left point and the back-match of its right position.
    """

    left: np.ndarray
    right: np.ndarray
    sigma: np.ndarray
    predicted: np.ndarray
    score: np.ndarray
    candidates: int
    back_error: np.ndarray


def match_pair(left, right, left_sensor, right_sensor, dem, *, zones=(4, 3), per_zone=2, window=21, radius=8,
               min_score=0.7, max_back_error=0.2, refraction=True, device=None):
    """Match interest points of ``left`` in ``right``, predicted through the sensors and the DEM.

    Parameters
    ----------
    left, right : array_like, shape (rows, cols)
        The two images (one band) of the sensors' sizes.
    left_sensor, right_sensor : FrameSensor
        Approximate orientations (GNSS/INS or omega-phi-kappa).
    dem : Dem, str or float
    zones, per_zone, window, radius, min_score :
        As :func:`~orthowarp.adjust.matching.interest_points` and
        :func:`~orthowarp.adjust.matching.match_points`; ``radius`` must cover the
        orientation's error in pixels.
    max_back_error : float, optional
        Largest distance (px) between a left point and the back-match of its right position.
    refraction : bool, optional
    device : str, optional

    Returns
    -------
    PairMatches
    """
    for name, s, img in (("left_sensor", left_sensor, left), ("right_sensor", right_sensor, right)):
        if not isinstance(s, FrameSensor):
            raise ParamError(f"{name} must be a FrameSensor, got {type(s).__name__}")
        shape = np.shape(img)
        if len(shape) != 2 or (shape[1], shape[0]) != tuple(s.image_size):
            raise ParamError(f"{name}'s image must be (rows, cols) = ({s.image_size[1]}, {s.image_size[0]}), "
                             f"got shape {shape}")
    pts, _ = interest_points(left, zones=zones, per_zone=per_zone, window=window)
    empty = PairMatches(*(np.zeros((0, 2)),) * 4, np.zeros(0), 0, np.zeros(0))
    if not len(pts):
        return empty
    crs = left_sensor.frame_crs
    ground = geolocate(left_sensor, pts, dem=dem, crs=crs, refraction=refraction, device=device)
    pred = project(right_sensor, ground, crs=crs, refraction=refraction, device=device)
    w, h = right_sensor.image_size
    inside = np.all(np.isfinite(pred), axis=1) & (pred[:, 0] > window) & (pred[:, 0] < w - window) & (
        pred[:, 1] > window) & (pred[:, 1] < h - window)
    pts, pred = pts[inside], pred[inside]
    if not len(pts):
        return empty
    fwd = match_points(left, right, pts, pred, window=window, radius=radius, min_score=min_score, device=device)
    back = match_points(right, left, np.nan_to_num(fwd.xy, nan=-1e3), pts, window=window, radius=2,
                        min_score=min_score, device=device)
    err = np.hypot(*(back.xy - pts).T)
    with np.errstate(invalid="ignore"):
        ok = fwd.ok & back.ok & (err <= max_back_error)
    return PairMatches(left=pts[ok], right=fwd.xy[ok], sigma=fwd.sigma[ok], predicted=pred[ok], score=fwd.score[ok],
                       candidates=int(inside.sum()), back_error=err[ok])
