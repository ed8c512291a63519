"""Host-side (NumPy float64) geodesy on WGS84 and elementary rotations.

The kernels in :mod:`orthowarp.kernels.geodesy` implement the same formulas on the device;
both are checked against pyproj in the tests. Angles are degrees at this interface.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only
    from numpy.typing import ArrayLike

__all__ = [
    "WGS84_A",
    "WGS84_F",
    "WGS84_B",
    "WGS84_E2",
    "geodetic_to_ecef",
    "ecef_to_geodetic",
    "ned_to_ecef_matrix",
    "enu_to_ecef_matrix",
    "geodetic_up",
    "rx",
    "ry",
    "rz",
    "opk_matrix",
    "rpy_angles",
    "rotvec_matrix",
    "opk_angles",
    "r1",
    "r2",
    "r3",
]

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def geodetic_to_ecef(lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> np.ndarray:
    """Geodetic latitude, longitude (deg) and ellipsoidal height (m) -> ECEF x, y, z (m).

    Parameters
    ----------
    lat, lon, h : array_like
        Broadcastable arrays (or scalars), degrees and metres (WGS84).

    Returns
    -------
    ndarray, shape (..., 3)
        ECEF x, y, z (m), float64; ``...`` the broadcast shape of the arguments.
    """
    lat = np.radians(np.asarray(lat, dtype=np.float64))
    lon = np.radians(np.asarray(lon, dtype=np.float64))
    h = np.asarray(h, dtype=np.float64)
    s = np.sin(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
    c = np.cos(lat)
    return np.stack(
        np.broadcast_arrays((n + h) * c * np.cos(lon), (n + h) * c * np.sin(lon), (n * (1.0 - WGS84_E2) + h) * s),
        axis=-1,
    )


def ecef_to_geodetic(xyz: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (..., 3) (m) -> latitude, longitude (deg), ellipsoidal height (m), each (...,).

    Same formulas as the kernel (see :func:`orthowarp.kernels.geodesy.ecef_to_geodetic`):
    Bowring's first guess and one fixed-point step.

    Parameters
    ----------
    xyz : array_like, shape (..., 3)
        ECEF x, y, z (m).

    Returns
    -------
    lat, lon : ndarray, shape (...,)
        Geodetic latitude and longitude (deg, WGS84), float64 (NumPy scalars for one point of
        shape (3,)).
    h : ndarray, shape (...,)
        Ellipsoidal height (m).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    r = np.hypot(x, y)
    ep2 = WGS84_E2 / (1.0 - WGS84_E2)
    den = np.hypot(r * WGS84_B, z * WGS84_A)
    cu, su = r * WGS84_B / den, z * WGS84_A / den
    num = z + ep2 * WGS84_B * su**3
    dnm = r - WGS84_E2 * WGS84_A * cu**3
    norm = np.hypot(num, dnm)
    s, c = num / norm, dnm / norm
    w = np.sqrt(1.0 - WGS84_E2 * s * s)
    n = WGS84_A / w
    h = r * c + z * s - WGS84_A * w
    dnm = r * (1.0 - WGS84_E2 * n / (n + h))
    norm = np.hypot(z, dnm)
    s, c = z / norm, dnm / norm
    h = r * c + z * s - WGS84_A * np.sqrt(1.0 - WGS84_E2 * s * s)
    return np.degrees(np.arctan2(z, dnm)), np.degrees(np.arctan2(y, x)), h


def ned_to_ecef_matrix(lat: float, lon: float) -> np.ndarray:
    """R_ecef<-ned (3, 3) at latitude, longitude (deg): columns north, east, down.

    Parameters
    ----------
    lat, lon : float
        Geodetic latitude and longitude (deg).

    Returns
    -------
    ndarray, shape (3, 3)
        Maps NED vectors at (lat, lon) to ECEF vectors.
    """
    m = enu_to_ecef_matrix(lat, lon)  # (the same axes: north, east and minus up)
    return np.stack([m[..., 1], m[..., 0], -m[..., 2]], -1)


def geodetic_up(lat: ArrayLike, lon: ArrayLike) -> np.ndarray:
    """Unit ellipsoid normal (local vertical, ECEF) (..., 3) at latitude, longitude (deg,
    arrays of one shape or scalars).

    Parameters
    ----------
    lat, lon : array_like, shape (...,)
        Geodetic latitude and longitude (deg).

    Returns
    -------
    ndarray, shape (..., 3)
        Unit ECEF vectors (dimensionless).
    """
    la, lo = np.radians(lat), np.radians(lon)
    return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la) * np.ones_like(lo)], -1)


def enu_to_ecef_matrix(lat: ArrayLike, lon: ArrayLike) -> np.ndarray:
    """R_ecef<-enu (..., 3, 3) at latitude, longitude (deg): columns east, north, up ([P3] eq. 9).

    Parameters
    ----------
    lat, lon : array_like, shape (...,)
        Geodetic latitude and longitude (deg), arrays of one shape or scalars.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        Maps ENU vectors at (lat, lon) to ECEF vectors.
    """
    la, lo = np.radians(lat), np.radians(lon)
    sl, cl, so, co = np.sin(la), np.cos(la), np.sin(lo), np.cos(lo)
    east = np.stack([-so, co, np.zeros_like(co)], -1)
    north = np.stack([-sl * co, -sl * so, cl * np.ones_like(co)], -1)
    return np.stack([east, north, geodetic_up(lat, lon)], -1)


def rx(angle: float) -> np.ndarray:
    """Active rotation (3, 3) by angle (deg) about x: rotates vectors counter-clockwise.

    Parameters
    ----------
    angle : float
        Rotation angle (deg), counter-clockwise seen from the positive x axis.

    Returns
    -------
    ndarray, shape (3, 3)
    """
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(angle: float) -> np.ndarray:
    """Active rotation (3, 3) by angle (deg) about y.

    Parameters
    ----------
    angle : float
        Rotation angle (deg), counter-clockwise seen from the positive y axis.

    Returns
    -------
    ndarray, shape (3, 3)
    """
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(angle: float) -> np.ndarray:
    """Active rotation (3, 3) by angle (deg) about z.

    Parameters
    ----------
    angle : float
        Rotation angle (deg), counter-clockwise seen from the positive z axis.

    Returns
    -------
    ndarray, shape (3, 3)
    """
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def opk_matrix(angles: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """R = Rx(omega) Ry(phi) Rz(kappa) (PATB: camera -> object) and its derivatives, for many
    angle triples; the one place this product is written (:meth:`Pose.from_opk`, the bundle
    adjustment and :class:`~orthowarp.sensor.FrameSensor` use it).

    Parameters
    ----------
    angles : array_like, shape (n, 3)
        omega, phi, kappa (rad).

    Returns
    -------
    r : ndarray, shape (n, 3, 3)
        R_object<-camera of each triple.
    dr : ndarray, shape (n, 3, 3, 3)
        dr[:, k] = dR / d(angle k) (per radian).
    """
    a = np.asarray(angles, dtype=np.float64).reshape(-1, 3)
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


def rotvec_matrix(rvec: ArrayLike) -> np.ndarray:
    """The rotation matrix (3, 3) of a rotation vector (3,) (rad: axis times angle), by
    Rodrigues' formula ``R = I + (sin t / t) K + ((1 - cos t) / t^2) K^2`` with K the cross-product
    matrix of the vector and t its length (series below 1e-4 rad, exact to float64 there).

    Parameters
    ----------
    rvec : array_like, shape (3,)
        Rotation vector (rad): the unit axis times the angle.

    Returns
    -------
    ndarray, shape (3, 3)
        The active rotation about that axis by that angle.
    """
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    t2 = float(r @ r)
    k = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if t2 < 1e-8:
        a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = np.sqrt(t2)
        a, b = np.sin(t) / t, (1.0 - np.cos(t)) / t2
    return np.eye(3) + a * k + b * (k @ k)


def rpy_angles(r_nav_body: ArrayLike) -> tuple[float, float, float]:
    """(roll, pitch, yaw) (deg) of ``R_nav<-body = Rz(yaw) Ry(pitch) Rx(roll)`` (3, 3): the
    inverse of that product (docs/design.md's GNSS/INS convention), pitch within +-90 degrees.

    Parameters
    ----------
    r_nav_body : array_like, shape (3, 3)
        A rotation matrix R_nav<-body.

    Returns
    -------
    roll, pitch, yaw : float
        Angles (deg, Python floats); pitch within [-90, 90].
    """
    r = np.asarray(r_nav_body, dtype=np.float64)
    return tuple(float(a) for a in np.degrees([np.arctan2(r[2, 1], r[2, 2]), -np.arcsin(np.clip(r[2, 0], -1.0, 1.0)),
                                               np.arctan2(r[1, 0], r[0, 0])]))


def opk_angles(r: np.ndarray) -> tuple[float, float, float]:
    """(omega, phi, kappa) (deg, Python floats) of ``R = Rx(omega) Ry(phi) Rz(kappa)`` (3, 3): the
    inverse of :func:`opk_matrix`, phi within +-90 degrees.

    Parameters
    ----------
    r : ndarray, shape (3, 3)
        A rotation matrix R_object<-camera.

    Returns
    -------
    omega, phi, kappa : float
        Angles (deg, Python floats); phi within [-90, 90].
    """
    phi = np.arcsin(np.clip(r[0, 2], -1.0, 1.0))
    angles = np.degrees([np.arctan2(-r[1, 2], r[2, 2]), phi, np.arctan2(-r[0, 1], r[0, 0])])
    return tuple(float(a) for a in angles)


def r1(angle: float) -> np.ndarray:
    """[P3]'s elementary rotation R1 (3, 3): a passive (frame) rotation, ``R1(a) = rx(-a)``.

    Parameters
    ----------
    angle : float
        Rotation angle (deg).

    Returns
    -------
    ndarray, shape (3, 3)
    """
    return rx(-angle)


def r2(angle: float) -> np.ndarray:
    """[P3]'s elementary rotation R2 (3, 3): ``R2(a) = ry(-a)``.

    Parameters
    ----------
    angle : float
        Rotation angle (deg).

    Returns
    -------
    ndarray, shape (3, 3)
    """
    return ry(-angle)


def r3(angle: float) -> np.ndarray:
    """[P3]'s elementary rotation R3 (3, 3): ``R3(a) = rz(-a)``.

    Parameters
    ----------
    angle : float
        Rotation angle (deg).

    Returns
    -------
    ndarray, shape (3, 3)
    """
    return rz(-angle)
