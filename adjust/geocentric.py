"""Geocentric blocks (GNSS/INS poses in latitude, longitude, ellipsoidal height, roll, pitch,
yaw; points in latitude, longitude, height): adjusted rigorously in a local east-north-up
frame at the block's centre, which is ECEF rotated and shifted (exact: no map projection, the
Earth's curvature stays in the coordinates).

:func:`to_local` turns such a block into a map-Cartesian one in that frame (poses as
R_enu<-cam = Rx(omega) Ry(phi) Rz(kappa), near-vertical there, so no singularity);
:func:`from_local` turns the adjustment's result back (poses as lat, lon, h, roll, pitch,
yaw with docs/design.md's NED navigation frame and standard mount; points as lat, lon, h).
Sigmas of GNSS positions and control points are read as east, north, up (m); INS sigmas as
the attitude angles' (deg), applied to omega, phi, kappa of the local frame; the result's pose
sigmas are east, north, up (m) and the rotations about the local axes (deg).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from .. import geodesy
from ..pose import MOUNT, Pose

if TYPE_CHECKING:  # annotations only
    from .block import Block
    from .bundle.result import AdjustResult

__all__ = ["to_local", "from_local"]


class LocalFrame:
    """East-north-up frame at an origin (lat, lon, h in deg, m)."""

    def __init__(self, lat: float, lon: float, h: float) -> None:
        self.lat, self.lon, self.h = float(lat), float(lon), float(h)
        self.origin = geodesy.geodetic_to_ecef(lat, lon, h)
        self.r = geodesy.enu_to_ecef_matrix(lat, lon).T  # R_enu<-ecef

    def from_lla(self, lla: ArrayLike) -> np.ndarray:
        """Points in this frame.

        Parameters
        ----------
        lla : array_like, shape (k, 3) or (3,)
            Latitude, longitude (deg), ellipsoidal height (m).

        Returns
        -------
        ndarray, shape (k, 3)
            East, north, up (m).
        """
        lla = np.atleast_2d(lla)
        x = geodesy.geodetic_to_ecef(lla[:, 0], lla[:, 1], lla[:, 2])
        return (x - self.origin) @ self.r.T

    def to_lla(self, enu: ArrayLike) -> np.ndarray:
        """Points in this frame as geodetic coordinates (the inverse of :meth:`from_lla`).

        Parameters
        ----------
        enu : array_like, shape (k, 3) or (3,)
            East, north, up (m).

        Returns
        -------
        ndarray, shape (k, 3)
            Latitude, longitude (deg), ellipsoidal height (m).
        """
        x = np.atleast_2d(enu) @ self.r + self.origin
        lat, lon, h = geodesy.ecef_to_geodetic(x)
        return np.stack([lat, lon, h], -1)

    def pose_to_local(self, lat: float, lon: float, h: float, roll: float, pitch: float, yaw: float) -> np.ndarray:
        """A GNSS/INS pose as a pose in this frame.

        Parameters
        ----------
        lat, lon, h : float
            The navigation reference point: latitude, longitude (deg), ellipsoidal height (m).
        roll, pitch, yaw : float
            Attitude (deg; docs/design.md's GNSS/INS convention, standard mount).

        Returns
        -------
        ndarray, shape (6,)
            East, north, up (m), omega, phi, kappa (deg) in this frame.
        """
        p = Pose.from_ins(lat, lon, h, roll, pitch, yaw)
        c = (p.center - self.origin) @ self.r.T
        return np.r_[c, geodesy.opk_angles(self.r @ p.rotation)]

    def pose_from_local(self, pose: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`pose_to_local`.

        Parameters
        ----------
        pose : ndarray, shape (6,)
            East, north, up (m), omega, phi, kappa (deg) in this frame.

        Returns
        -------
        ndarray, shape (6,)
            Latitude, longitude (deg), height (m), roll, pitch, yaw (deg).
        """
        r_ecef_cam = self.r.T @ geodesy.opk_matrix(np.radians(pose[3:6]))[0][0]
        lla = self.to_lla(pose[:3])[0]
        r_nav_body = geodesy.ned_to_ecef_matrix(lla[0], lla[1]).T @ r_ecef_cam @ MOUNT.T
        return np.r_[lla, geodesy.rpy_angles(r_nav_body)]


def to_local(block: Block) -> tuple[Block, LocalFrame]:
    """A geocentric block in the local ENU frame of its centre (see the module doc).

    Parameters
    ----------
    block : Block
        In ``mode="geocentric"``.

    Returns
    -------
    local : Block
        The block, map-Cartesian in the frame (m, deg).
    frame : LocalFrame
        The frame: east-north-up at the mean of the initial positions (else of the GNSS
        positions, else of the points).
    """
    from .block import Block

    b = block
    known = np.all(np.isfinite(b.poses), axis=1)
    src = b.poses[known, :3] if np.any(known) else b.gnss_xyz[np.all(np.isfinite(b.gnss_xyz), axis=1)]
    if len(src) == 0:
        src = b.xyz[np.all(np.isfinite(b.xyz), axis=1)]
    centre = src.mean(axis=0)
    frame = LocalFrame(*centre)
    poses = np.full((b.n_images, 6), np.nan)
    for k in np.flatnonzero(known):
        poses[k] = frame.pose_to_local(*b.poses[k])
    gnss = np.full((b.n_images, 3), np.nan)
    g = np.all(np.isfinite(b.gnss_xyz), axis=1)
    gnss[g] = frame.from_lla(b.gnss_xyz[g])
    ins = np.full((b.n_images, 3), np.nan)
    for k in np.flatnonzero(np.all(np.isfinite(b.ins_opk), axis=1)):
        where = b.poses[k, :3] if known[k] else b.gnss_xyz[k]
        if np.all(np.isfinite(where)):
            ins[k] = frame.pose_to_local(*where, *b.ins_opk[k])[3:]
    xyz = np.full((b.n_points, 3), np.nan)
    ok = np.all(np.isfinite(b.xyz), axis=1)
    xyz[ok] = frame.from_lla(b.xyz[ok])
    local = Block(crs=f"ENU at ({frame.lat:.8f}, {frame.lon:.8f}, {frame.h:.3f})", cameras=b.cameras,
                  image_ids=b.image_ids, image_camera=b.image_camera, poses=poses, point_ids=b.point_ids,
                  roles=b.roles, xyz=xyz, xyz_sigma=b.xyz_sigma, obs_image=b.obs_image, obs_point=b.obs_point,
                  obs_xy=b.obs_xy, obs_sigma=b.obs_sigma, gnss_xyz=gnss, gnss_sigma=b.gnss_sigma, ins_opk=ins,
                  ins_sigma=np.where(np.isfinite(ins), b.ins_sigma, np.nan), name=b.name)
    return local, frame


def from_local(result: AdjustResult, frame: LocalFrame) -> AdjustResult:
    """The adjustment result of a local block with poses (lat, lon, h, roll, pitch, yaw) and
    points (lat, lon, h); sigmas, residuals and RMSEs stay in the local frame (m, deg).

    Parameters
    ----------
    result : AdjustResult
        Of the block :func:`to_local` gave; changed in place.
    frame : LocalFrame

    Returns
    -------
    AdjustResult
        ``result``, with ``local_frame`` set.
    """
    result.poses = {k: tuple(frame.pose_from_local(np.asarray(v))) for k, v in result.poses.items()}
    result.points = {k: tuple(frame.to_lla(np.asarray(v))[0]) if np.all(np.isfinite(v)) else v
                     for k, v in result.points.items()}
    result.local_frame = frame
    return result
