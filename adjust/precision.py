"""Precision of ground points by error propagation ([P4]: C_f = A C_l A^T).

A ground point is a function of the orientation and the measurements: X = X(l). Linearised,
its covariance is ``C_X = A C_l A^T`` with ``A = dX/dl``. The point is defined implicitly by
conditions ``F(X, l) = 0`` written with the bundle adjustment's collinearity equations
(:mod:`orthowarp.collinearity`, whose distortion and pixel mapping are
:class:`~orthowarp.camera.FrameCamera`'s own, :mod:`orthowarp.brown`), so ``A = -(F_X^+) F_l``:

- **monoplotting** (one image and a DEM): the point's pixel is the measured one (two
  conditions) and its height is the DEM's at its position, ``Z - DEM(X, Y) - e_h = 0`` (the
  DEM's local slope from its bilinear surface; ``e_h`` the DEM height error);
- **intersection** (two or more images): the least-squares point of the rays, ``A = -(F_X^T
  F_X)^-1 F_X^T F_l``.

The inputs l per image: the pose, the camera parameters named in ``camera_params`` (f, x0, y0
in mm; k1, k2, k3, p1, p2 on OpenCV-normalised coordinates), the measured pixel (col, row); for
monoplotting also the DEM height. Images are taken as independent of one another (block
covariances between poses: pass a full ``pose_cov`` of the stacked poses to
:func:`intersection_covariance`).

Poses:

- photogrammetric (omega-phi-kappa in a projected CRS, treated as Cartesian): the pose inputs
  are X0, Y0, Z0 (m) and omega, phi, kappa (deg); points are X, Y, Z in that CRS and their
  covariance is in its axes;
- GNSS/INS (:meth:`~orthowarp.Pose.from_ins`): the pose inputs are the reference point's
  offsets east, north, up (m) and roll, pitch, yaw (deg), as a GNSS/INS specification states
  them, optionally followed by the boresight angles (deg) and the lever arm's components (m)
  as :meth:`~orthowarp.Pose.from_ins` takes them (9 or 12 inputs); points are (longitude,
  latitude, height) as :func:`orthowarp.geolocate` returns them.
  The equations are written in an east-north-up frame at the (first) pose's nadir (exactly:
  ECEF rotated and shifted, :mod:`orthowarp.adjust.geocentric`), the pose inputs mapped into
  it by their Jacobian (boresight and lever arm included), and the points' covariance is in
  east, north, up (m).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from ..errors import ParamError
from .. import collinearity as col

if TYPE_CHECKING:  # annotations only
    from ..camera import FrameCamera
    from ..pose import Pose
    from .geocentric import LocalFrame

__all__ = ["PrecisionResult", "monoplot_covariance", "intersection_covariance", "input_covariance"]

CAMERA_PARAMS = col.CALIBRATION  # f, x0, y0, k1, k2, k3, p1, p2


@dataclass
class PrecisionResult:
    """Ground points and their precision.

    Attributes
    ----------
    points : ndarray (n, 3)
        X, Y, Z (m) in the poses' CRS.
    cov : ndarray (n, 3, 3)
        Their covariances (m^2).
    sigma : ndarray (n, 3)
        Standard deviations of X, Y, Z (m).
    sigma_xy : ndarray (n,)
        sqrt((sigma_X^2 + sigma_Y^2) / 2) (m), the mean horizontal standard deviation.
    """

    points: np.ndarray
    cov: np.ndarray

    @property
    def sigma(self) -> np.ndarray:
        """Standard deviations (n, 3) of X, Y, Z (m)."""
        return np.sqrt(np.maximum(np.diagonal(self.cov, axis1=1, axis2=2), 0.0))

    @property
    def sigma_xy(self) -> np.ndarray:
        """sqrt((sigma_X^2 + sigma_Y^2) / 2) (n,) (m)."""
        s = self.sigma
        return np.sqrt(0.5 * (s[:, 0] ** 2 + s[:, 1] ** 2))


def _camera_row(camera: FrameCamera) -> np.ndarray:
    """The camera's parameter row (10,) for :mod:`orthowarp.collinearity`."""
    return np.array([camera.focal_length, *camera.principal_point, camera.k1, camera.k2, camera.k3, camera.p1,
                     camera.p2, *camera.pixel_size], dtype=np.float64)


def _pose_row(pose: Pose) -> np.ndarray:
    """A photogrammetric pose's row (6,): X0, Y0, Z0 (m), omega, phi, kappa (rad)."""
    if pose.mode != "map":
        raise ParamError("precision is computed for photogrammetric (omega-phi-kappa) poses; got a "
                         f"{pose.mode} pose")
    p = pose.params
    return np.array([p["x"], p["y"], p["z"], np.radians(p["omega"]), np.radians(p["phi"]),
                     np.radians(p["kappa"])])


class _Frame:
    """Where the equations are written: the map CRS of photogrammetric poses (identity), or an
    east-north-up frame at the first GNSS/INS pose's nadir."""

    def __init__(self, poses: Sequence[Pose], local: LocalFrame | None = None) -> None:
        modes = {p.mode for p in poses}
        if len(modes) != 1:
            raise ParamError(f"the poses must be all photogrammetric or all GNSS/INS, got {sorted(modes)}")
        self.local = None
        if modes == {"geocentric"}:
            from .geocentric import LocalFrame

            lat, lon, _ = poses[0].center_geodetic
            self.local = local if local is not None else LocalFrame(lat, lon, 0.0)
        elif modes != {"map"}:
            raise ParamError(f"precision is computed for photogrammetric or GNSS/INS poses, got {sorted(modes)}")

    def points(self, points: np.ndarray) -> np.ndarray:
        """Points (n, 3) of the poses' kind -> the frame's coordinates."""
        if self.local is None:
            return points
        return self.local.from_lla(np.stack([points[:, 1], points[:, 0], points[:, 2]], -1))

    def _row(self, pose: Pose) -> np.ndarray:
        from .. import geodesy

        c = (pose.center - self.local.origin) @ self.local.r.T
        return np.r_[c, np.radians(geodesy.opk_angles(self.local.r @ pose.rotation))]

    def pose(self, pose: Pose, inputs: int = 6) -> tuple[np.ndarray, np.ndarray]:
        """The pose's row in the frame (X0, Y0, Z0 m, omega, phi, kappa rad) and the Jacobian
        (6, inputs) of that row (angles in deg) by the pose's first ``inputs`` inputs (see the
        module's description): the identity for photogrammetric poses, numerical (central
        differences) for GNSS/INS ones, through :meth:`Pose.from_ins` (:func:`moved_pose`)."""
        if self.local is None:
            return _pose_row(pose), np.eye(6)
        jac = np.empty((6, inputs))
        for k in range(inputs):
            d = INPUT_STEPS[k]
            diff = self._row(moved_pose(pose, k, d)) - self._row(moved_pose(pose, k, -d))
            # angles per degree, as the equations' columns are (a step across +-180 deg wrapped)
            diff[3:] = (np.degrees(diff[3:]) + 180.0) % 360.0 - 180.0
            jac[:, k] = diff / (2 * d)
        return self._row(pose), jac


# central-difference steps of the pose inputs: position (m), attitude (deg), boresight (deg),
# lever arm (m)
INPUT_STEPS = (1e-3, 1e-3, 1e-3, 1e-5, 1e-5, 1e-5, 1e-5, 1e-5, 1e-5, 1e-3, 1e-3, 1e-3)


def cov_size(c: ArrayLike) -> int:
    """The side of a square matrix argument, for the checks.

    Parameters
    ----------
    c : array_like

    Returns
    -------
    int
        Its first dimension when 2-D, else -1.
    """
    return np.shape(c)[0] if np.ndim(c) == 2 else -1


def pose_inputs(pose: Pose, size: int) -> int:
    """Check that a pose covariance of ``size`` x ``size`` fits the pose.

    Parameters
    ----------
    pose : Pose
    size : int
        6 for photogrammetric poses; 6, 9 (with boresight) or 12 (with boresight and lever
        arm) for GNSS/INS poses.

    Returns
    -------
    int
        ``size``.

    Raises
    ------
    ParamError
        Any other size.
    """
    allowed = (6,) if pose.mode == "map" else (6, 9, 12)
    if size not in allowed:
        kind = "a photogrammetric" if pose.mode == "map" else "a GNSS/INS"
        raise ParamError(f"pose_cov of {kind} pose must be {' or '.join(f'{a} x {a}' for a in allowed)}, "
                         f"got {size} x {size}")
    return size


def moved_pose(pose: Pose, k: int, d: float) -> Pose:
    """The pose with one of its inputs moved.

    Parameters
    ----------
    pose : Pose
    k : int
        The input (see the module's description): 0-2 X0, Y0, Z0 or east, north, up (m);
        3-5 omega, phi, kappa or roll, pitch, yaw (deg); for GNSS/INS poses also 6-8 the
        boresight angles (deg) and 9-11 the lever arm (m).
    d : float
        The step, in the input's unit.

    Returns
    -------
    Pose
    """
    from ..pose import Pose

    p = pose.params
    if pose.mode == "map":
        v = np.array([p["x"], p["y"], p["z"], p["omega"], p["phi"], p["kappa"]], dtype=np.float64)
        v[k] += d
        return Pose.from_opk(*v, crs=pose.crs)
    if pose.mode != "geocentric":
        raise ParamError(f"precision is computed for photogrammetric or GNSS/INS poses, got a {pose.mode} pose")
    from .geocentric import LocalFrame

    lla = np.array([p["lat"], p["lon"], p["h"]], dtype=np.float64)
    att = np.array([p["roll"], p["pitch"], p["yaw"]], dtype=np.float64)
    boresight = np.array(p["boresight"], dtype=np.float64)
    lever = np.array(p["lever_arm"], dtype=np.float64)
    if k < 3:  # along the reference point's own east, north, up
        off = np.zeros(3)
        off[k] = d
        lla = LocalFrame(*lla).to_lla(off)[0]
    elif k < 6:
        att[k - 3] += d
    elif k < 9:
        boresight[k - 6] += d
    else:
        lever[k - 9] += d
    return Pose.from_ins(*lla, *att, boresight=tuple(boresight), lever_arm=tuple(lever))


def input_covariance(pose: Pose, frame_cov: ArrayLike, *, local: LocalFrame | None = None) -> np.ndarray:
    """The covariance of a pose's inputs (see the module's description) from that of its row
    in an adjustment's frame: ``J^-1 C J^-T`` with ``J`` the row's derivative by the inputs.

    Parameters
    ----------
    pose : Pose
    frame_cov : array_like, shape (6, 6)
        Covariance of the pose's row: X0, Y0, Z0 (m) and omega, phi, kappa (deg) of a
        photogrammetric pose in its CRS, or for a GNSS/INS pose of its row in the
        east-north-up frame ``local``.
    local : LocalFrame, optional
        The adjustment's frame (:class:`~orthowarp.adjust.geocentric.LocalFrame`, as
        :attr:`AdjustResult.local_frame <orthowarp.adjust.AdjustResult>`); needed for GNSS/INS
        poses.

    Returns
    -------
    ndarray, shape (6, 6)
        The inputs' covariance (m, deg; photogrammetric poses: ``frame_cov`` as given).
    """
    c = square_matrix("frame_cov", frame_cov, 6)
    if pose.mode == "map":
        return c
    if local is None:
        raise ParamError("a GNSS/INS pose's covariance needs the adjustment's local frame")
    _, jac = _Frame([pose], local=local).pose(pose)
    inv = np.linalg.inv(jac)
    out = inv @ c @ inv.T
    return 0.5 * (out + out.T)


def square_matrix(name: str, value: ArrayLike, n: int) -> np.ndarray:
    """``value`` as a symmetric positive semi-definite (n, n) matrix; ParamError else."""
    try:
        c = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be a {n} x {n} matrix of numbers: {e}") from e
    if c.shape != (n, n):
        raise ParamError(f"{name} must be a {n} x {n} matrix, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        i, j = (int(k) for k in np.argwhere(~np.isfinite(c))[0])
        raise ParamError(f"{name} must hold finite numbers, got {c[i, j]} at [{i}, {j}] (a variance overflows "
                         "float64 where its sigma is beyond ~1e154)")
    if not np.allclose(c, c.T, rtol=1e-9, atol=1e-15) or np.linalg.eigvalsh(0.5 * (c + c.T)).min() < -1e-12 * max(
            1.0, np.abs(c).max()):
        raise ParamError(f"{name} must be symmetric positive semi-definite")
    return c


def _image_terms(camera: FrameCamera, pose_row: np.ndarray, points: np.ndarray,
                 camera_params: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Per point: the collinearity Jacobians by the point (n, 2, 3) and by the image's inputs
    (n, 2, 6 + q + 2): pose (X0, Y0, Z0 m, angles per degree), camera parameters, measured
    pixel. ``pose_row``: X0, Y0, Z0, omega, phi, kappa (rad) in the points' frame."""
    n = len(points)
    cam = np.broadcast_to(_camera_row(camera), (n, 10))
    size = np.broadcast_to(np.asarray(camera.image_size, dtype=np.float64), (n, 2))
    poses = np.broadcast_to(pose_row, (n, 6))
    _, j_pose, j_point = col.jacobians(poses, points, cam, size)
    j_pose = j_pose.copy()
    j_pose[:, :, 3:] *= np.pi / 180.0  # per degree, as the poses and their sigmas are stated
    blocks = [j_pose]
    if camera_params:
        blocks.append(col.camera_jacobian(poses, points, cam, size, list(camera_params)))
    blocks.append(np.broadcast_to(-np.eye(2), (n, 2, 2)))  # F = project(X) - measured pixel
    return j_point, np.concatenate(blocks, axis=2)


def _input_cov(pose_cov: np.ndarray, camera_cov: np.ndarray | None, pixel_cov: np.ndarray, q: int) -> np.ndarray:
    """The block-diagonal covariance (6 + q + 2,) * 2 of one image's inputs."""
    m = 6 + q + 2
    c = np.zeros((m, m))
    c[:6, :6] = pose_cov
    if q:
        c[6:6 + q, 6:6 + q] = camera_cov
    c[6 + q:, 6 + q:] = pixel_cov
    return c


def monoplot_covariance(camera: FrameCamera, pose: Pose, points: ArrayLike, slopes: ArrayLike, *,
                        pose_cov: ArrayLike, pixel_sigma: float = 0.5, camera_cov: ArrayLike | None = None,
                        camera_params: Sequence[str] = (), dem_sigma: float = 0.0) -> PrecisionResult:
    """Covariance of ground points geolocated from one image on a DEM.

    Parameters
    ----------
    camera : FrameCamera
    pose : Pose
        Photogrammetric (omega-phi-kappa) or GNSS/INS pose.
    points : array_like (n, 3)
        The ground points (X, Y, Z m in the pose's CRS; longitude, latitude, height for GNSS/INS
        poses), e.g. from :func:`orthowarp.geolocate`.
    slopes : array_like (n, 2)
        The DEM's slopes there (its bilinear surface): dZ/dX, dZ/dY, or for GNSS/INS poses
        dh/d(east), dh/d(north).
    pose_cov : array_like (6, 6), or for GNSS/INS poses also (9, 9) or (12, 12)
        Covariance of the pose's inputs (see the module's description: X0, Y0, Z0 or east,
        north, up in m; omega, phi, kappa or roll, pitch, yaw in deg; for GNSS/INS poses then
        the boresight angles (deg) and the lever arm (m), see :meth:`Pose.from_ins`).
    pixel_sigma : float, optional
        Standard deviation of the measured pixel, each axis (px).
    camera_cov : array_like (q, q), optional
        Covariance of the camera parameters ``camera_params`` (units as in the module's
        description).
    camera_params : sequence of str, optional
        Names from ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2").
    dem_sigma : float, optional
        Standard deviation of the DEM's heights (m).

    Returns
    -------
    PrecisionResult
    """
    pts, slopes, q, pose_cov, camera_cov = _check(points, pose_cov, camera_cov, camera_params, slopes=slopes,
                                                  pose_size=pose_inputs(pose, cov_size(pose_cov)))
    if not (np.isfinite(pixel_sigma) and pixel_sigma >= 0 and np.isfinite(dem_sigma) and dem_sigma >= 0):
        raise ParamError(f"pixel_sigma and dem_sigma must be finite and >= 0, got {pixel_sigma}, {dem_sigma}")
    n = len(pts)
    frame = _Frame([pose])
    row, jac = frame.pose(pose, len(pose_cov))
    pose_cov = jac @ pose_cov @ jac.T
    j_point, j_in = _image_terms(camera, row, frame.points(pts), camera_params)
    m = j_in.shape[2]
    f_x = np.zeros((n, 3, 3))
    f_x[:, :2] = j_point
    f_x[:, 2] = np.stack([-slopes[:, 0], -slopes[:, 1], np.ones(n)], -1)  # Z - DEM(X, Y) - e_h
    f_l = np.zeros((n, 3, m + 1))
    f_l[:, :2, :m] = j_in
    f_l[:, 2, m] = -1.0
    c_in = np.zeros((m + 1, m + 1))
    c_in[:m, :m] = _input_cov(pose_cov, camera_cov, pixel_sigma**2 * np.eye(2), q)
    c_in[m, m] = dem_sigma**2
    a = -np.linalg.solve(f_x, f_l)  # dX/dl (n, 3, m + 1)
    return PrecisionResult(pts, a @ c_in @ np.transpose(a, (0, 2, 1)))


def intersection_covariance(cameras: Sequence[FrameCamera], poses: Sequence[Pose], points: ArrayLike, *,
                            pose_cov: ArrayLike, pixel_sigma: float = 0.5, camera_cov: ArrayLike | None = None,
                            camera_params: Sequence[str] = ()) -> PrecisionResult:
    """Covariance of ground points intersected from two or more images (least squares).

    Parameters
    ----------
    cameras : sequence of FrameCamera, one per image (the same object for a shared camera:
        its parameters are then one set of inputs)
    poses : sequence of Pose
        Photogrammetric or GNSS/INS poses (all of one kind), one per image (k images).
    points : array_like (n, 3)
        The intersected ground points.
    pose_cov : array_like (p, p) or (pk, pk)
        Each pose's covariance (the same for all), or that of the stacked poses (correlated
        poses, e.g. from an adjustment); p = 6, or for GNSS/INS poses also 9 or 12 (see
        :func:`monoplot_covariance`). A (6k, 6k) matrix is read as the stacked poses'.
    pixel_sigma : float, optional
    camera_cov, camera_params :
        As for :func:`monoplot_covariance`, per distinct camera.

    Returns
    -------
    PrecisionResult
    """
    if len(cameras) != len(poses) or len(poses) < 2:
        raise ParamError(f"intersection needs two or more images with one camera each; got {len(poses)} poses "
                         f"and {len(cameras)} cameras")
    k = len(poses)
    size = cov_size(pose_cov)
    shared = size in (6, 9, 12) and size != 6 * k  # one covariance for every pose, or the stacked poses'
    p = pose_inputs(poses[0], size if shared else size // k if size % k == 0 else -1)
    pts, _, q, pose_cov, camera_cov = _check(points, pose_cov, camera_cov, camera_params,
                                             pose_size=p if shared else p * k)
    distinct = []
    for c in cameras:
        if not any(c is d for d in distinct):
            distinct.append(c)
    n_in = 6 * k + q * len(distinct) + 2 * k
    c_in = np.zeros((n_in, n_in))
    c_pose = np.kron(np.eye(k), pose_cov) if shared else pose_cov  # (p k, p k) of the inputs
    for d in range(len(distinct)):
        if q:
            c_in[6 * k + q * d:6 * k + q * (d + 1), 6 * k + q * d:6 * k + q * (d + 1)] = camera_cov
    c_in[6 * k + q * len(distinct):, 6 * k + q * len(distinct):] = pixel_sigma**2 * np.eye(2 * k)
    n = len(pts)
    frame = _Frame(poses)
    local = frame.points(pts)
    pose_rows, big = [], np.zeros((6 * k, p * k))
    for i, pose in enumerate(poses):  # each pose's row in the frame, its inputs mapped there
        row, jac = frame.pose(pose, p)
        pose_rows.append(row)
        big[6 * i:6 * i + 6, p * i:p * i + p] = jac
    c_in[:6 * k, :6 * k] = big @ c_pose @ big.T
    f_x = np.zeros((n, 2 * k, 3))
    f_l = np.zeros((n, 2 * k, n_in))
    for i, (camera, pose) in enumerate(zip(cameras, poses)):
        j_point, j_in = _image_terms(camera, pose_rows[i], local, camera_params)
        rows = slice(2 * i, 2 * i + 2)
        f_x[:, rows] = j_point
        f_l[:, rows, 6 * i:6 * i + 6] = j_in[:, :, :6]
        d = next(t for t, c in enumerate(distinct) if c is camera)
        if q:
            f_l[:, rows, 6 * k + q * d:6 * k + q * (d + 1)] = j_in[:, :, 6:6 + q]
        px = 6 * k + q * len(distinct) + 2 * i
        f_l[:, rows, px:px + 2] = j_in[:, :, 6 + q:]
    ft = np.transpose(f_x, (0, 2, 1))
    a = -np.linalg.solve(ft @ f_x, ft @ f_l)  # (n, 3, n_in)
    return PrecisionResult(pts, a @ c_in @ np.transpose(a, (0, 2, 1)))


def _check(points: ArrayLike, pose_cov: ArrayLike, camera_cov: ArrayLike | None, camera_params: Sequence[str],
           slopes: ArrayLike | None = None,
           pose_size: int = 6) -> tuple[np.ndarray, np.ndarray | None, int, np.ndarray, np.ndarray | None]:
    """The arguments of the propagations, checked (ParamError) and as arrays: points (n, 3),
    slopes (n, 2) or None, q, pose_cov, camera_cov."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ParamError(f"points must be a finite (n, 3) array, got shape {pts.shape}")
    bad = [p for p in camera_params if p not in CAMERA_PARAMS]
    if bad or len(set(camera_params)) != len(camera_params):
        raise ParamError(f"camera_params must be distinct names from {CAMERA_PARAMS}, got {list(camera_params)}")
    q = len(camera_params)
    pose_cov = square_matrix("pose_cov", pose_cov, pose_size)
    if q:
        if camera_cov is None:
            raise ParamError("camera_params given without camera_cov")
        camera_cov = square_matrix("camera_cov", camera_cov, q)
    elif camera_cov is not None:
        raise ParamError("camera_cov given without camera_params")
    if slopes is not None:
        slopes = np.asarray(slopes, dtype=np.float64)
        if slopes.shape != (len(pts), 2) or not np.all(np.isfinite(slopes)):
            raise ParamError(f"slopes must be a finite ({len(pts)}, 2) array, got shape {slopes.shape}")
    return pts, slopes, q, pose_cov, camera_cov
