"""Collinearity equations of frame images ([P2] eqs. 4-6): the host model of
:class:`~orthowarp.sensor.FrameSensor` and of the bundle adjustment (:mod:`orthowarp.adjust`).

Pure functions of arrays (float64 NumPy), vectorised over observations:

- the camera -> object rotation ``R = Rx(omega) Ry(phi) Rz(kappa)`` (docs/design.md, PATB) and its
  derivatives by the three angles (:func:`orthowarp.geodesy.opk_matrix`, here ``rotation``);
- a ground point X seen from the projection centre X0: camera-frame vector
  ``Xc = R^T (X - X0)``, OpenCV-normalised coordinates ``u = -Xc/Zc, v = Yc/Zc`` (the camera
  looks along -z), Brown distortion, pixel (col, row);
- the analytic Jacobians of the pixel by the six pose parameters (X0, Y0, Z0 in m; omega, phi,
  kappa in radians) and by the point (m).

Camera parameters per observation, array (m, 10): f (mm), x0, y0 (mm, principal point from the
image centre, y up), k1, k2, k3, p1, p2 (OpenCV-normalised), and the pixel pitch px, py (mm);
image size (m, 2) in pixels.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .brown import distort, normalized_to_pixel
from .geodesy import opk_matrix as rotation

if TYPE_CHECKING:  # annotations only
    from collections.abc import Sequence

__all__ = ["rotation", "project", "jacobians", "camera_jacobian", "camera_frame_to_pixel", "camera_jacobian_from_frame",
           "CAMERA_COLUMNS", "CALIBRATION"]

CAMERA_COLUMNS = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "px", "py")


def _normalised(xc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) (m, 2) and the camera-frame vector's Jacobian d(u, v)/d(Xc) (m, 2, 3)."""
    x, y, z = xc[:, 0], xc[:, 1], xc[:, 2]
    iz = 1.0 / z
    uv = np.stack([-x * iz, y * iz], -1)
    d = np.zeros((len(xc), 2, 3))
    d[:, 0, 0] = -iz
    d[:, 0, 2] = x * iz * iz
    d[:, 1, 1] = iz
    d[:, 1, 2] = -y * iz * iz
    return uv, d


def camera_frame_to_pixel(xc: np.ndarray, cam: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame vectors (m, 3) -> pixels (m, 2) and d pixel / d Xc (m, 2, 3).

    The normalised coordinates, Brown distortion and scaling to pixels of one observation
    row of ``cam`` (m, 10) and ``size`` (m, 2) each; points behind the camera (Zc >= 0) are
    not masked here (see :func:`project`).

    Parameters
    ----------
    xc : ndarray, shape (m, 3)
        Camera-frame vectors Xc (m; any length: only the direction matters).
    cam : ndarray, shape (m, 10)
        Camera parameters per observation (:data:`CAMERA_COLUMNS`: f, x0, y0 in mm, k1, k2, k3,
        p1, p2, px, py in mm).
    size : ndarray, shape (m, 2)
        Image (width, height) per observation (pixels).

    Returns
    -------
    pixels : ndarray, shape (m, 2)
        Pixel (col, row).
    d_xc : ndarray, shape (m, 2, 3)
        d pixel / d Xc (pixels per m).
    """
    uv, duv = _normalised(xc)
    uvd, dd = distort(uv, cam[:, 3], cam[:, 4], cam[:, 5], cam[:, 6], cam[:, 7])
    pix = normalized_to_pixel(uvd, cam[:, 0], (cam[:, 1], cam[:, 2]), (cam[:, 8], cam[:, 9]), (size[:, 0], size[:, 1]))
    scale = np.stack([cam[:, 0] / cam[:, 8], cam[:, 0] / cam[:, 9]], -1)  # d pixel / d (ud, vd)
    return pix, scale[:, :, None] * np.einsum("nij,njk->nik", dd, duv)


def _camera_frame(poses: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """R (m, 3, 3), dR (m, 3, 3, 3), X - X0 (m, 3) and Xc = R^T (X - X0) (m, 3)."""
    r, dr = rotation(poses[:, 3:])
    d = points - poses[:, :3]
    return r, dr, d, np.einsum("nji,nj->ni", r, d)


def project(poses: np.ndarray, points: np.ndarray, cam: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Pixels (m, 2) of points (m, 3) seen from poses (m, 6) (X0, Y0, Z0 m; omega, phi, kappa
    rad) by cameras (m, 10) of image sizes (m, 2); NaN for points behind the camera.

    Parameters
    ----------
    poses : ndarray, shape (m, 6)
        X0, Y0, Z0 (m, object frame) and omega, phi, kappa (rad) per observation.
    points : ndarray, shape (m, 3)
        Object-frame points X, Y, Z (m).
    cam : ndarray, shape (m, 10)
        Camera parameters per observation (:data:`CAMERA_COLUMNS`).
    size : ndarray, shape (m, 2)
        Image (width, height) per observation (pixels).

    Returns
    -------
    ndarray, shape (m, 2)
        Pixel (col, row); NaN rows for points behind the camera.
    """
    *_, xc = _camera_frame(poses, points)
    pix, _ = camera_frame_to_pixel(xc, cam, size)
    pix[xc[:, 2] >= 0] = np.nan
    return pix


def jacobians(poses: np.ndarray, points: np.ndarray, cam: np.ndarray,
              size: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (m, 2) and their Jacobians by the pose (m, 2, 6) and by the point (m, 2, 3).

    The pose Jacobian's angle columns are per radian.

    Parameters
    ----------
    poses, points, cam, size : ndarray
        As for :func:`project`: (m, 6) (m and rad), (m, 3) (m), (m, 10) and (m, 2) (pixels).

    Returns
    -------
    pixels : ndarray, shape (m, 2)
        Pixel (col, row), not masked behind the camera.
    j_pose : ndarray, shape (m, 2, 6)
        d pixel / d (X0, Y0, Z0, omega, phi, kappa): pixels per m, per radian.
    j_point : ndarray, shape (m, 2, 3)
        d pixel / d (X, Y, Z) (pixels per m).
    """
    r, dr, d, xc = _camera_frame(poses, points)
    pix, chain = camera_frame_to_pixel(xc, cam, size)
    rt = np.transpose(r, (0, 2, 1))
    j_point = chain @ rt  # dXc/dX = R^T
    j_pose = np.empty((len(d), 2, 6))
    j_pose[:, :, :3] = -j_point
    for k in range(3):
        dxc = np.einsum("nji,nj->ni", dr[:, k], d)  # d(R^T d)/d angle = (dR/d angle)^T d
        j_pose[:, :, 3 + k] = np.einsum("nij,nj->ni", chain, dxc)
    return pix, j_pose, j_point


CALIBRATION = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2")


def camera_jacobian(poses: np.ndarray, points: np.ndarray, cam: np.ndarray, size: np.ndarray,
                    which: Sequence[str]) -> np.ndarray:
    """Jacobian (m, 2, q) of the pixels by the camera parameters named in ``which`` (a subset
    of :data:`CALIBRATION`; f, x0, y0 in mm, the Brown coefficients as defined on OpenCV
    normalised coordinates).

    Parameters
    ----------
    poses, points, cam, size : ndarray
        As for :func:`project`: (m, 6) (m and rad), (m, 3) (m), (m, 10) and (m, 2) (pixels).
    which : sequence of str, length q
        Names from :data:`CALIBRATION`, in the order of the Jacobian's columns.

    Returns
    -------
    ndarray, shape (m, 2, q)
        d pixel / d parameter: pixels per mm for f, x0, y0, per unit of each Brown coefficient.
    """
    *_, xc = _camera_frame(poses, points)
    return camera_jacobian_from_frame(xc, cam, size, which)


def camera_jacobian_from_frame(xc: np.ndarray, cam: np.ndarray, size: np.ndarray, which: Sequence[str]) -> np.ndarray:
    """:func:`camera_jacobian` of camera-frame vectors Xc (m, 3). The normalised coordinates
    do not depend on the camera parameters: only the distortion and the scaling to pixels do.

    Parameters
    ----------
    xc : ndarray, shape (m, 3)
        Camera-frame vectors Xc = R^T (X - X0) (m).
    cam, size : ndarray
        As for :func:`project`: (m, 10) and (m, 2) (pixels).
    which : sequence of str, length q
        Names from :data:`CALIBRATION`, in the order of the Jacobian's columns.

    Returns
    -------
    ndarray, shape (m, 2, q)
        As :func:`camera_jacobian`.
    """
    uv, _ = _normalised(xc)
    uvd, _ = distort(uv, cam[:, 3], cam[:, 4], cam[:, 5], cam[:, 6], cam[:, 7])
    u, v = uv[:, 0], uv[:, 1]
    r2 = u * u + v * v
    fx, fy = cam[:, 0] / cam[:, 8], cam[:, 0] / cam[:, 9]
    cols = {"f": (uvd[:, 0] / cam[:, 8], uvd[:, 1] / cam[:, 9]),
            "x0": (1.0 / cam[:, 8], 0.0 * u), "y0": (0.0 * u, -1.0 / cam[:, 9]),
            "k1": (fx * u * r2, fy * v * r2), "k2": (fx * u * r2**2, fy * v * r2**2),
            "k3": (fx * u * r2**3, fy * v * r2**3),
            "p1": (fx * 2 * u * v, fy * (r2 + 2 * v * v)), "p2": (fx * (r2 + 2 * u * u), fy * 2 * u * v)}
    out = np.empty((len(xc), 2, len(which)))
    for k, name in enumerate(which):
        out[:, 0, k], out[:, 1, k] = cols[name]
    return out
