"""Collinearity observation equations of frame images, map-Cartesian mode (seed 002 eqs. 4-6).

Pure functions of arrays (float64 NumPy), vectorised over observations:

- the camera -> object rotation ``R = Rx(omega) Ry(phi) Rz(kappa)`` (DESIGN.md, PATB) and its
  derivatives by the three angles;
- a ground point X seen from the projection centre X0: camera-frame vector
  ``Xc = R^T (X - X0)``, OpenCV-normalised coordinates ``u = -Xc/Zc, v = Yc/Zc`` (the camera
  looks along -z), Brown distortion, pixel (col, row);
- the analytic Jacobians of the pixel by the six pose parameters (X0, Y0, Z0 in m; omega, phi,
  kappa in radians) and by the point (m).

Camera parameters per observation, array (m, 10): f (mm), x0, y0 (mm, principal point from the
image centre, y up), k1, k2, k3, p1, p2 (OpenCV-normalised), and the pixel pitch px, py (mm);
image size (m, 2) in pixels.
"""

import numpy as np

from ..brown import distort, normalized_to_pixel

__all__ = ["rotation", "project", "jacobians", "CAMERA_COLUMNS"]

CAMERA_COLUMNS = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "px", "py")


def rotation(angles):
    """R = Rx(omega) Ry(phi) Rz(kappa) and its derivatives, element by element.

    Parameters
    ----------
    angles : ndarray, shape (n, 3)
        omega, phi, kappa (rad).

    Returns
    -------
    r : ndarray, shape (n, 3, 3)
    dr : ndarray, shape (n, 3, 3, 3)
        dr[:, k] = dR / d(angle k).
    """
    a = np.asarray(angles, dtype=np.float64)
    so, co = np.sin(a[:, 0]), np.cos(a[:, 0])
    sp, cp = np.sin(a[:, 1]), np.cos(a[:, 1])
    sk, ck = np.sin(a[:, 2]), np.cos(a[:, 2])
    r = np.empty((len(a), 3, 3))
    r[:, 0, 0], r[:, 0, 1], r[:, 0, 2] = cp * ck, -cp * sk, sp
    r[:, 1, 0], r[:, 1, 1], r[:, 1, 2] = co * sk + so * sp * ck, co * ck - so * sp * sk, -so * cp
    r[:, 2, 0], r[:, 2, 1], r[:, 2, 2] = so * sk - co * sp * ck, so * ck + co * sp * sk, co * cp
    dr = np.zeros((len(a), 3, 3, 3))
    # d/d omega = Gx R (Gx the generator of x): rows (0, -R2, R1)
    dr[:, 0, 1], dr[:, 0, 2] = -r[:, 2], r[:, 1]
    # d/d phi = Rx (Gy Ry) Rz
    dr[:, 1, 0, 0], dr[:, 1, 0, 1], dr[:, 1, 0, 2] = -sp * ck, sp * sk, cp
    dr[:, 1, 1, 0], dr[:, 1, 1, 1], dr[:, 1, 1, 2] = so * cp * ck, -so * cp * sk, so * sp
    dr[:, 1, 2, 0], dr[:, 1, 2, 1], dr[:, 1, 2, 2] = -co * cp * ck, co * cp * sk, -co * sp
    # d/d kappa = R Gz: columns (R1, -R0, 0)
    dr[:, 2, :, 0], dr[:, 2, :, 1] = r[:, :, 1], -r[:, :, 0]
    return r, dr


def _normalised(cam, xc):
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


def _distort(cam, uv):
    """Distorted (ud, vd) (m, 2) and d(ud, vd)/d(u, v) (m, 2, 2) (Brown, OpenCV normalised)."""
    return distort(uv, cam[:, 3], cam[:, 4], cam[:, 5], cam[:, 6], cam[:, 7])


def _to_pixel(cam, size, uvd):
    return normalized_to_pixel(uvd, cam[:, 0], (cam[:, 1], cam[:, 2]), (cam[:, 8], cam[:, 9]), (size[:, 0], size[:, 1]))


def project(poses, points, cam, size):
    """Pixels (m, 2) of points (m, 3) seen from poses (m, 6) (X0, Y0, Z0 m; omega, phi, kappa
    rad) by cameras (m, 10) of image sizes (m, 2); NaN for points behind the camera."""
    r, _ = rotation(poses[:, 3:])
    xc = np.einsum("nji,nj->ni", r, points - poses[:, :3])
    uv, _ = _normalised(cam, xc)
    pix = _to_pixel(cam, size, _distort(cam, uv)[0])
    pix[xc[:, 2] >= 0] = np.nan
    return pix


def jacobians(poses, points, cam, size):
    """Pixels (m, 2) and their Jacobians by the pose (m, 2, 6) and by the point (m, 2, 3).

    The pose Jacobian's angle columns are per radian.
    """
    r, dr = rotation(poses[:, 3:])
    d = points - poses[:, :3]
    xc = np.einsum("nji,nj->ni", r, d)
    uv, duv = _normalised(cam, xc)
    uvd, dd = _distort(cam, uv)
    pix = _to_pixel(cam, size, uvd)
    scale = np.stack([cam[:, 0] / cam[:, 8], cam[:, 0] / cam[:, 9]], -1)  # d pixel / d (ud, vd)
    chain = scale[:, :, None] * np.einsum("nij,njk->nik", dd, duv)  # d pixel / d Xc (m, 2, 3)
    rt = np.transpose(r, (0, 2, 1))
    j_point = chain @ rt  # dXc/dX = R^T
    j_pose = np.empty((len(d), 2, 6))
    j_pose[:, :, :3] = -j_point
    for k in range(3):
        dxc = np.einsum("nji,nj->ni", dr[:, k], d)  # d(R^T d)/d angle = (dR/d angle)^T d
        j_pose[:, :, 3 + k] = np.einsum("nij,nj->ni", chain, dxc)
    return pix, j_pose, j_point


CALIBRATION = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2")


def camera_jacobian(poses, points, cam, size, which):
    """Jacobian (m, 2, q) of the pixels by the camera parameters named in ``which`` (a subset
    of :data:`CALIBRATION`; f, x0, y0 in mm, the Brown coefficients as defined on OpenCV
    normalised coordinates). The normalised coordinates do not depend on them: only the
    distortion and the scaling to pixels do."""
    r, _ = rotation(poses[:, 3:])
    xc = np.einsum("nji,nj->ni", r, points - poses[:, :3])
    uv, _ = _normalised(cam, xc)
    uvd, _ = _distort(cam, uv)
    u, v = uv[:, 0], uv[:, 1]
    r2 = u * u + v * v
    fx, fy = cam[:, 0] / cam[:, 8], cam[:, 0] / cam[:, 9]
    cols = {"f": (uvd[:, 0] / cam[:, 8], uvd[:, 1] / cam[:, 9]),
            "x0": (1.0 / cam[:, 8], 0.0 * u), "y0": (0.0 * u, -1.0 / cam[:, 9]),
            "k1": (fx * u * r2, fy * v * r2), "k2": (fx * u * r2**2, fy * v * r2**2),
            "k3": (fx * u * r2**3, fy * v * r2**3),
            "p1": (fx * 2 * u * v, fy * (r2 + 2 * v * v)), "p2": (fx * (r2 + 2 * u * u), fy * 2 * u * v)}
    out = np.empty((len(poses), 2, len(which)))
    for k, name in enumerate(which):
        out[:, 0, k], out[:, 1, k] = cols[name]
    return out
