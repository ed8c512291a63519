"""The frame camera's formulas on the host (float64 NumPy), written once.

Brown-Conrady distortion on OpenCV-normalised coordinates with its Jacobian, and the mapping
between normalised coordinates and pixels (docs/design.md: pixel (col, row) from the top-left
corner, camera x right, y up, the principal point's offset from the image centre in mm, y up).
:class:`~orthowarp.camera.FrameCamera` uses them with its scalars, the bundle adjustment
(:mod:`orthowarp.collinearity`) with per-observation arrays: every argument
broadcasts. The device twins are in :mod:`orthowarp.kernels.camera`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only
    from collections.abc import Sequence

    from numpy.typing import ArrayLike

__all__ = ["distort", "normalized_to_pixel", "pixel_to_normalized"]


def distort(uv: ArrayLike, k1: float | np.ndarray, k2: float | np.ndarray, k3: float | np.ndarray,
            p1: float | np.ndarray, p2: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted -> distorted normalised coordinates and the Jacobian.

    Parameters
    ----------
    uv : array_like, shape (..., 2)
        Undistorted OpenCV-normalised (u, v).
    k1, k2, k3, p1, p2 : float or ndarray broadcasting with ``uv[..., 0]``
        Radial and decentring coefficients (OpenCV's convention).

    Returns
    -------
    uvd : ndarray, shape (..., 2)
        Distorted normalised (ud, vd).
    jacobian : ndarray, shape (..., 2, 2)
        d(ud, vd) / d(u, v).
    """
    uv = np.asarray(uv, dtype=np.float64)
    u, v = uv[..., 0], uv[..., 1]
    r2 = u * u + v * v
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2 * k2 + 3 * r2 * k3)  # d rad / d r2
    uvd = np.stack([u * rad + 2 * p1 * u * v + p2 * (r2 + 2 * u * u),
                    v * rad + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v], axis=-1)
    j01 = 2 * u * v * drad + 2 * p1 * u + 2 * p2 * v
    jac = np.stack([np.stack([rad + 2 * u * u * drad + 2 * p1 * v + 6 * p2 * u, j01], -1),
                    np.stack([j01, rad + 2 * v * v * drad + 6 * p1 * v + 2 * p2 * u], -1)], -2)
    return uvd, jac


def normalized_to_pixel(uv: ArrayLike, focal_length: float | np.ndarray,
                        principal_point: Sequence[float | np.ndarray], pixel_size: Sequence[float | np.ndarray],
                        image_size: Sequence[float | np.ndarray]) -> np.ndarray:
    """Distorted normalised (u, v) (..., 2) -> pixel (col, row) (..., 2).

    ``focal_length`` (mm), ``principal_point`` (x0, y0) (mm, from the image centre, y up),
    ``pixel_size`` (px, py) (mm) and ``image_size`` (width, height) (pixels): each a pair (or
    a scalar for the focal length) of floats or of arrays broadcasting with ``uv[..., 0]``.

    Parameters
    ----------
    uv : array_like, shape (..., 2)
        Distorted OpenCV-normalised (u, v).
    focal_length : float or ndarray
        Focal length (mm).
    principal_point : pair of float or ndarray
        (x0, y0) (mm), offset of the principal point from the image centre, x right, y up.
    pixel_size : pair of float or ndarray
        Pixel pitch (px, py) (mm).
    image_size : pair of float or ndarray
        (width, height) (pixels).

    Returns
    -------
    ndarray, shape (..., 2)
        Pixel (col, row), origin at the top-left corner of the top-left pixel.
    """
    uv = np.asarray(uv, dtype=np.float64)
    x = uv[..., 0] * focal_length
    y = -uv[..., 1] * focal_length
    return np.stack([(x + principal_point[0]) / pixel_size[0] + 0.5 * image_size[0],
                     0.5 * image_size[1] - (y + principal_point[1]) / pixel_size[1]], axis=-1)


def pixel_to_normalized(pixels: ArrayLike, focal_length: float | np.ndarray,
                        principal_point: Sequence[float | np.ndarray], pixel_size: Sequence[float | np.ndarray],
                        image_size: Sequence[float | np.ndarray]) -> np.ndarray:
    """Pixel (col, row) (..., 2) -> distorted normalised (u, v) (..., 2); arguments as for
    :func:`normalized_to_pixel`.

    Parameters
    ----------
    pixels : array_like, shape (..., 2)
        Pixel (col, row), origin at the top-left corner of the top-left pixel.
    focal_length : float or ndarray
        Focal length (mm).
    principal_point : pair of float or ndarray
        (x0, y0) (mm), offset of the principal point from the image centre, x right, y up.
    pixel_size : pair of float or ndarray
        Pixel pitch (px, py) (mm).
    image_size : pair of float or ndarray
        (width, height) (pixels).

    Returns
    -------
    ndarray, shape (..., 2)
        Distorted OpenCV-normalised (u, v).
    """
    p = np.asarray(pixels, dtype=np.float64)
    x = (p[..., 0] - 0.5 * image_size[0]) * pixel_size[0] - principal_point[0]
    y = (0.5 * image_size[1] - p[..., 1]) * pixel_size[1] - principal_point[1]
    return np.stack([x / focal_length, -y / focal_length], axis=-1)
