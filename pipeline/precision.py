"""Predicted-accuracy rasters of orthoimages: the precision of each ground position by error
propagation (:mod:`orthowarp.adjust.precision`, [P4]) on a grid aligned with the ortho.

For every ``step`` x ``step`` cell of the ortho's grid, the ground point at the cell's centre
(its height from the DEM, the DEM's slope from its bilinear surface) is projected into the
image; where the image sees it, its covariance from one image on the DEM ([P4]'s
monoplotting) is turned into the output CRS and written as three float32 bands: sigma x,
sigma y (along the output CRS's axes, in its axis unit: m for a projected CRS in metres, deg
for a longitude/latitude one) and sigma up (m); NaN where the image does not see the point.
The bands carry their descriptions and units (:func:`band_descriptions`). The raster's pixels
are ``step`` ortho pixels, with the ortho's origin.

"Not seen" includes ground hidden by its own slope: where the DEM's tangent plane at the point
faces away from the camera (:func:`facing`), the ray passes under the terrain just in front of
the point; the monoplot's equations still solve there, for ground the image does not show,
with sigmas that explode toward the grazing ray (the plane containing the ray, where the
equations are singular). Such cells are NaN. On the seen side of a grazing ray the large
sigmas are right: the horizontal sigma grows as 1 / sin(the angle between the ray and the
terrain plane), e.g. 134 m north at 0.7 deg on a steep slope at the far edge of an aerial frame.

For frame images the whole computation runs on the device
(:func:`frame_window_sigmas`, :mod:`orthowarp.kernels.precision`): the cells' ground points
from the ortho's coarse-grid geometry, the projection's derivatives by Warp's automatic
differentiation of the kernels' own projection (refraction included), the covariance per cell.
The pose's and camera's input covariance enters once per image (:func:`raw_covariance`).

:func:`scene_monoplot_covariance` is the same propagation for a pushbroom scene, whose
projection has no closed form: its derivatives are taken through the kernels'
own projection (:func:`orthowarp.project`, the chain the ortho runs) by central differences.
"""

from __future__ import annotations

import functools
import os
import time
from typing import TYPE_CHECKING

import numpy as np
from affine import Affine
from pyproj import CRS, Transformer

from ..adjust.precision import INPUT_STEPS, PrecisionResult, cov_size, moved_pose, pose_inputs, square_matrix
from ..errors import ParamError
from ..geodesy import WGS84_A, WGS84_E2
from ..kernels.precision import hidden_facets_kernel
from .dem import as_dem
from .raster.io import write_raster
from .tiles import Tile

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import ArrayLike

    from ..camera import FrameCamera
    from ..pose import Pose
    from ..pushbroom import PushbroomScene
    from ..sensor import SensorModel
    from .dem import Dem
    from .geometry import SensorGeometry

__all__ = ["accuracy_raster", "scene_accuracy_raster", "sensor_accuracy_raster", "accuracy_path",
           "mosaic_accuracy_raster", "frame_window_sigmas",
           "raw_covariance", "scene_cell_sigmas", "scene_monoplot_covariance", "SCENE_INPUTS", "band_descriptions",
           "facing"]

# a pushbroom scene's orientation inputs, constant over the scene: the orbit's offset in the
# orbital frame (m), the attitude's offsets (deg) and the look angles' offsets (deg)
SCENE_INPUTS = ("across", "along", "radial", "roll", "pitch", "yaw", "psi_x", "psi_y")
_SCENE_STEPS = np.array([1.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4])  # central-difference steps


def perturbed_scene(scene: PushbroomScene, offsets: ArrayLike) -> PushbroomScene:
    """The scene with its orientation offset by ``offsets`` (8,), in the order and units of
    :data:`SCENE_INPUTS`: every ephemeris position moved by (across, along, radial) m along the
    orbital frame's axes at that sample (X2 = v x radial, Y2, Z2 radial), the yaw, pitch and
    roll samples and every detector's psi_x, psi_y shifted (deg)."""
    d = np.asarray(offsets, float)
    if scene.polynomials is not None:
        raise ParamError("the precision of a scene whose orientation is given by polynomials is not supported")
    frame = scene.orbital_frame(scene.eph_position, scene.eph_velocity)  # (n, 3, 3): columns X2, Y2, Z2
    yaw, pitch, roll = np.radians(d[[5, 4, 3]])
    return scene.replace(eph_position=scene.eph_position + frame @ d[:3],
                         att_angles=scene.att_angles + [yaw, pitch, roll],
                         psi_x=scene.psi_x + np.radians(d[6]), psi_y=scene.psi_y + np.radians(d[7]))


def enu_shifted(points: ArrayLike, axis: int, metres: float) -> np.ndarray:
    """Geodetic points (n, 3: longitude, latitude deg, height m) moved ``metres`` along their
    local east (axis 0), north (1) or up (2), to first order (through the ellipsoid's radii of
    curvature at the point; the error, metres^2 / R, is below a micrometre at 1 m)."""
    lon, lat, h = (np.asarray(points, float)[:, k] for k in range(3))
    s = np.sin(np.radians(lat))
    w = np.sqrt(1.0 - WGS84_E2 * s * s)
    out = np.stack([lon, lat, h], -1)
    if axis == 0:
        out[:, 0] += np.degrees(metres / ((WGS84_A / w + h) * np.cos(np.radians(lat))))
    elif axis == 1:
        out[:, 1] += np.degrees(metres / (WGS84_A * (1.0 - WGS84_E2) / w**3 + h))
    else:
        out[:, 2] += metres
    return out


def scene_monoplot_covariance(scene: PushbroomScene, points: ArrayLike, slopes: ArrayLike, *,
                              orientation_cov: ArrayLike, pixel_sigma: float = 0.5, dem_sigma: float = 0.0,
                              refraction: bool = True, device: str | None = None) -> PrecisionResult:
    """Covariance of ground points geolocated from one pushbroom scene on a DEM.

    The conditions are those of :func:`~orthowarp.adjust.precision.monoplot_covariance`: the
    point's pixel is the measured one, its height the DEM's (``u - s_e e - s_n n - e_h = 0``
    in the point's east-north-up frame); their derivatives by central differences through
    :func:`orthowarp.project` (1 m along east, north and up; 1 m and 1e-4 deg of the inputs).

    Parameters
    ----------
    scene : PushbroomScene
    points : array_like (n, 3)
        Longitude, latitude (deg), ellipsoidal height (m), e.g. from :func:`orthowarp.geolocate`.
    slopes : array_like (n, 2)
        The DEM's slopes there: dh/d(east), dh/d(north).
    orientation_cov : array_like (8, 8)
        Covariance of the orientation's offsets, constant over the scene, in the order and
        units of :data:`SCENE_INPUTS`: the orbit across and along the track and radially (m),
        roll, pitch, yaw (deg), the look angles psi_x, psi_y (deg).
    pixel_sigma : float, optional
        Standard deviation of the measured pixel, each axis (px).
    dem_sigma : float, optional
        Standard deviation of the DEM's heights (m).
    refraction : bool, optional
    device : str, optional
        Warp device of the projections.

    Returns
    -------
    PrecisionResult
        Covariances (n, 3, 3) in each point's own east, north, up frame (m).
    """
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.isfinite(pts).all():
        raise ParamError(f"points must be finite (n, 3) longitude, latitude, height, got shape {pts.shape}")
    slopes = np.asarray(slopes, float)
    if slopes.shape != (len(pts), 2) or not np.isfinite(slopes).all():
        raise ParamError(f"slopes must be finite, shape ({len(pts)}, 2), got {slopes.shape}")
    cov_l = square_matrix("orientation_cov", orientation_cov, len(SCENE_INPUTS))
    if not (np.isfinite(pixel_sigma) and pixel_sigma >= 0 and np.isfinite(dem_sigma) and dem_sigma >= 0):
        raise ParamError(f"pixel_sigma and dem_sigma must be finite and >= 0, got {pixel_sigma}, {dem_sigma}")
    cov, _ = _scene_monoplot(scene, pts, slopes, cov_l, pixel_sigma, dem_sigma, refraction, device)
    return PrecisionResult(pts, cov)


def _scene_monoplot(scene, pts, slopes, cov_l, pixel_sigma, dem_sigma, refraction, device):
    """:func:`scene_monoplot_covariance`'s covariances (n, 3, 3) and its ``F_X`` (n, 3, 3:
    rows d(col, row)/d(east, north, up) and the height condition), inputs checked."""
    from .geometry import project

    n, m = len(pts), len(SCENE_INPUTS)

    def pixels(sc, lon_lat_h):
        return project(sc, lon_lat_h, refraction=refraction, device=device)

    if not np.isfinite(pixels(scene, pts)).all():
        raise ParamError("every point must lie on the scene (some project outside it or behind it)")
    f_x = np.zeros((n, 3, 3))
    for a in range(3):
        plus, minus = (pixels(scene, enu_shifted(pts, a, sign)) for sign in (1.0, -1.0))
        f_x[:, :2, a] = 0.5 * (plus - minus)
    f_x[:, 2] = np.stack([-slopes[:, 0], -slopes[:, 1], np.ones(n)], -1)
    f_l = np.zeros((n, 3, m + 3))
    for k in range(m):
        step = np.zeros(m)
        step[k] = _SCENE_STEPS[k]
        plus, minus = (pixels(perturbed_scene(scene, s * step), pts) for s in (1.0, -1.0))
        f_l[:, :2, k] = (plus - minus) / (2 * _SCENE_STEPS[k])
    f_l[:, :2, m:m + 2] = -np.eye(2)  # the measured pixel
    f_l[:, 2, m + 2] = -1.0  # the DEM's height error
    c_in = np.zeros((m + 3, m + 3))
    c_in[:m, :m] = cov_l
    c_in[m:m + 2, m:m + 2] = pixel_sigma**2 * np.eye(2)
    c_in[m + 2, m + 2] = dem_sigma**2
    a = -np.linalg.solve(f_x, f_l)
    return a @ c_in @ np.transpose(a, (0, 2, 1)), f_x


def _cell_grid(transform, shape, step):
    """The accuracy raster's grid (``step`` ortho pixels a cell): its transform and (rows,
    cols)."""
    if not isinstance(step, (int, np.integer)) or step < 1:
        raise ParamError(f"step must be an integer >= 1, got {step!r}")
    return transform @ Affine.scale(int(step)), (-(-shape[0] // int(step)), -(-shape[1] // int(step)))


def _cell_centres(grid, rows, cols, at=None):
    """The centres (x, y) in the ortho's CRS of the cells ``at`` (flat indices, row-major;
    default all) of an accuracy grid."""
    i, j = np.divmod(np.arange(rows * cols) if at is None else np.asarray(at), cols)
    ox, oy = grid @ (j + 0.5, i + 0.5)
    return np.asarray(ox, dtype=np.float64), np.asarray(oy, dtype=np.float64)


def _terrain_points(dem, crs, ox, oy, frame_crs):
    """Points (n, 3) on the terrain under (ox, oy) of ``crs`` and the terrain's slopes (n, 2):
    x, y, h in the frame's map CRS ``frame_crs``, or longitude, latitude, ellipsoidal height
    where it is None; slopes per metre along x, y, or east, north."""
    geo = frame_crs is None
    to_frame = Transformer.from_crs(crs, "EPSG:4326" if geo else frame_crs, always_xy=True)
    px, py = (np.asarray(v, dtype=np.float64) for v in to_frame.transform(ox, oy))
    terrain = as_dem(dem).for_frame(frame_crs)
    h = terrain.sample(px, py)
    if terrain.is_constant:
        slopes = np.zeros((len(px), 2))
    else:  # the bilinear surface's slope (per metre east and north for lon/lat grids)
        d = 0.1 * min(abs(terrain.transform.a), abs(terrain.transform.e))
        sx = sy = 2 * d
        if geo:  # degrees -> metres through the ellipsoid's radii of curvature (as the kernels)
            sl = np.sin(np.radians(py))
            w2 = 1.0 - WGS84_E2 * sl * sl
            sx = sx * np.radians(1.0) * (WGS84_A / np.sqrt(w2) + h) * np.cos(np.radians(py))
            sy = sy * np.radians(1.0) * (WGS84_A * (1.0 - WGS84_E2) / w2**1.5 + h)
        slopes = np.stack([(terrain.sample(px + d, py) - terrain.sample(px - d, py)) / sx,
                           (terrain.sample(px, py + d) - terrain.sample(px, py - d)) / sy], -1)
    return np.stack([px, py, h], -1), slopes


MEASURES = ("sigma", "ce90")  # the accuracy rasters' bands: sigma x, y, up; or CE90, LE90
LE90 = 1.6448536269514722  # LE90 / sigma: the standard normal's 95 % quantile


@functools.lru_cache(maxsize=4)  # 0.5 s to compute; read-only
def ce90_table(n: int = 129) -> np.ndarray:
    """CE90 / sigma_major (n,) at sigma_minor / sigma_major = 0, 1/(n-1), ..., 1: the radius
    holding 90 % of a horizontal normal error, from the exact probability over the circle,
    P(R) = 1/(2 pi s1 s2) integral over theta of (1 - exp(-a R^2 / 2)) / a, a = cos^2 / s1^2 +
    sin^2 / s2^2, solved for P = 0.9 (1.6449 for a line, 2.1460 for a circle). Linear
    interpolation between the 129 entries is within 1e-5 of the exact value."""
    from scipy.integrate import quad
    from scipy.optimize import brentq

    def p(r, q):
        def f(t):
            a = np.cos(t) ** 2 + np.sin(t) ** 2 / q**2
            return (1.0 - np.exp(-a * r * r / 2.0)) / a

        return 4.0 * quad(f, 0.0, np.pi / 2, limit=200, epsabs=1e-13, epsrel=1e-12)[0] / (2.0 * np.pi * q)

    out = np.empty(n)
    out[0] = LE90  # a line: the two-sided 90 % of one normal
    for i in range(1, n):
        q = i / (n - 1)
        out[i] = brentq(lambda r: p(r, q) - 0.9, 1.0, 3.0, xtol=1e-13)
    out.flags.writeable = False
    return out


def _measure(measure):
    if measure not in MEASURES:
        raise ParamError(f"measure must be one of {MEASURES}, got {measure!r}")
    return measure


def _sigmas(cov, jac, measure="sigma"):
    """(3, n) float32: sigma x, y of the horizontal covariance taken through ``jac`` (n, 2, 2)
    and sigma up; or, for ``measure="ce90"``, CE90 of the horizontal covariance (m, in the
    covariance's own east/north), LE90 and NaN."""
    if measure == "ce90":
        h = cov[:, :2, :2]
        mean = 0.5 * (h[:, 0, 0] + h[:, 1, 1])
        d = np.sqrt(np.maximum(0.25 * (h[:, 0, 0] - h[:, 1, 1]) ** 2 + h[:, 0, 1] * h[:, 1, 0], 0.0))
        major, minor = np.sqrt(np.maximum(mean + d, 0.0)), np.sqrt(np.maximum(mean - d, 0.0))
        table = ce90_table()
        ratio = np.divide(minor, major, out=np.ones_like(major), where=major > 0)
        ce = major * np.interp(ratio, np.linspace(0.0, 1.0, len(table)), table)
        return np.stack([ce, LE90 * np.sqrt(np.maximum(cov[:, 2, 2], 0.0)), np.full(len(cov), np.nan)]).astype(
            np.float32)
    horizontal = jac @ cov[:, :2, :2] @ np.transpose(jac, (0, 2, 1))
    return np.stack([np.sqrt(np.maximum(horizontal[:, 0, 0], 0.0)), np.sqrt(np.maximum(horizontal[:, 1, 1], 0.0)),
                     np.sqrt(np.maximum(cov[:, 2, 2], 0.0))]).astype(np.float32)


RAW_CAMERA = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2")  # the kernels' raw camera parameters, in order


def raw_covariance(camera: FrameCamera, pose: Pose, *, pose_cov: ArrayLike, camera_cov: ArrayLike | None = None,
                   camera_params: Sequence[str] = ()) -> np.ndarray:
    """Covariance (20, 20) of the raw parameters the accuracy kernels differentiate by
    (:data:`orthowarp.kernels.precision.RAW`: projection centre, rotation matrix row-major,
    camera), ``M C_in M^T``, with ``M`` the derivative of the pose's centre and rotation by its
    inputs (central differences through the pose's own construction,
    :func:`~orthowarp.adjust.precision.moved_pose`) and of the camera by its parameters (the
    identity); inputs and units as for :func:`~orthowarp.adjust.precision.monoplot_covariance`."""
    pose_cov = square_matrix("pose_cov", pose_cov, pose_inputs(pose, cov_size(pose_cov)))
    p = len(pose_cov)
    q = len(camera_params)
    bad = [n for n in camera_params if n not in RAW_CAMERA]
    if bad or len(set(camera_params)) != q:
        raise ParamError(f"camera_params must be distinct names from {RAW_CAMERA}, got {list(camera_params)}")
    c_in = np.zeros((p + q, p + q))
    c_in[:p, :p] = pose_cov
    if q:
        c_in[p:, p:] = square_matrix("camera_cov", camera_cov, q)
    m = np.zeros((20, p + q))
    for k in range(p):
        d = INPUT_STEPS[k]
        hi, lo = moved_pose(pose, k, d), moved_pose(pose, k, -d)
        m[:3, k] = (np.asarray(hi.center, float) - np.asarray(lo.center, float)) / (2 * d)
        m[3:12, k] = (np.asarray(hi.rotation, float) - np.asarray(lo.rotation, float)).ravel() / (2 * d)
    for i, name in enumerate(camera_params):
        m[12 + RAW_CAMERA.index(name), p + i] = 1.0
    return m @ c_in @ m.T


def facing(to_sensor: ArrayLike, slopes: ArrayLike) -> np.ndarray:
    """Whether the terrain's tangent plane at ground points faces the sensor, ``n . v > 0``:
    ``n = (-s_e, -s_n, 1)`` its upward normal (``slopes`` (n, 2): rise per metre east, north),
    ``v`` (n, 3: east, north, up) the ray's direction at the point toward the sensor. The ray
    ``X0 + t v`` stands ``t n . v`` above that plane, so where ``n . v < 0`` the terrain just in
    front of the point rises above the ray: its own slope hides the point from the sensor
    (the monoplot's equations still have a solution there, for ground the image does not
    see). At ``n . v = 0`` the ray grazes the terrain and the monoplot's conditions are
    singular: on the seen side the horizontal sigma grows without bound, as
    1 / sin(the angle between the ray and the terrain plane)."""
    v = np.asarray(to_sensor, float)
    s = np.asarray(slopes, float)
    return v[:, 2] - s[:, 0] * v[:, 0] - s[:, 1] * v[:, 1] > 0.0


def _write_accuracy(dst, out, grid, crs, measure):
    """Write an accuracy raster (bands, rows, cols; NaN: not seen) on ``grid`` in ``crs``, its
    bands described (:func:`band_descriptions`)."""
    descriptions, units = band_descriptions(crs, measure)
    write_raster(dst, out, transform=grid, crs=crs.to_wkt(), nodata=np.nan, descriptions=descriptions, units=units)


_UNIT_ABBREV = {"metre": "m", "meter": "m", "degree": "deg", "US survey foot": "ftUS", "foot": "ft"}


def band_descriptions(crs: CRS | str, measure: str = "sigma") -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(descriptions, units) of an accuracy raster's bands, one string each, for rasterio's
    ``descriptions`` and ``units``: ``measure="sigma"``: sigma x and sigma y along the output
    CRS's own axes, in its axis unit (m for UTM; deg for a longitude/latitude CRS), and sigma
    up (m); ``"ce90"``: CE90 and LE90 (m on the ground)."""
    if _measure(measure) == "ce90":
        return (("CE90: radius holding 90% of the horizontal error (m)", "LE90: 90% vertical error, 1.6449 sigma up (m)"),
                ("m", "m"))
    axes = CRS(crs).axis_info
    x = next((a for a in axes if a.direction.lower() in ("east", "west")), axes[0] if axes else None)
    y = next((a for a in axes if a.direction.lower() in ("north", "south")), axes[1] if len(axes) > 1 else None)
    names, units = [], []
    for label, a in (("x", x), ("y", y)):
        u = _UNIT_ABBREV.get(a.unit_name, a.unit_name) if a is not None else "m"
        names.append(f"sigma {label}: {a.name.lower()} ({u})" if a is not None else f"sigma {label} ({u})")
        units.append(u)
    return (*names, "sigma up (m)"), (*units, "m")


def _check_sigmas(pixel_sigma, dem_sigma):
    if not (np.isfinite(pixel_sigma) and pixel_sigma >= 0 and np.isfinite(dem_sigma) and dem_sigma >= 0):
        raise ParamError(f"pixel_sigma and dem_sigma must be finite and >= 0, got {pixel_sigma}, {dem_sigma}")


def frame_window_sigmas(geometry: SensorGeometry, crs: CRS, cells: Affine, window: tuple[int, int, int, int],
                        c_raw: np.ndarray, *, pixel_sigma: float = 0.5, dem_sigma: float = 0.0, measure: str = "sigma",
                        nodes: int = 32, chunk: int | None = None, timings: dict | None = None) -> np.ndarray:
    """Predicted sigma x, y (the axes of ``crs``, in its unit) and up (m) of the ground under a window of
    accuracy cells seen by one frame image, on the geometry's device
    (:mod:`orthowarp.kernels.precision`).

    Parameters
    ----------
    geometry : SensorGeometry
        The frame image's geometry (sensor, DEM, refraction, device), as the ortho uses it.
    crs : pyproj.CRS
    cells : affine.Affine
        The accuracy grid's transform (north up: no rotation terms).
    window : Tile or (row0, col0, rows, cols)
        The cells to compute.
    c_raw : ndarray (20, 20)
        :func:`raw_covariance` of the image.
    pixel_sigma, dem_sigma : float
        As for :func:`~orthowarp.adjust.precision.monoplot_covariance`.
    measure : {"sigma", "ce90"}, optional
        What the rows hold: sigma x, y (the axes of ``crs``, in its unit) and up (m); or CE90 (the radius
        holding 90 % of the horizontal error, m on the ground), LE90 (1.6449 sigma up) and NaN.
    nodes : int, optional
        Cells between the exact (PROJ) nodes of the cells' positions; between them the
        positions are interpolated bilinearly, as the ortho's coarse grid (over 32 cells of
        16 pixels of 10 cm, ~50 m, a map projection departs from bilinear by < 0.1 mm).
    chunk : int, optional
        Cells per launch (bounds the device memory: ~0.5 kB a cell); default 2^21 on a GPU,
        2^18 on the CPU.
    timings : dict, optional
        Filled with seconds per step (nodes, buffers, cells, projection, gradients,
        covariance, read-back), the device synchronised after each: for benchmarks.

    Returns
    -------
    ndarray (3, rows, cols) float32
        NaN where the image does not see the cell's ground point: off the image or the DEM, or
        on terrain whose slope faces away from the camera (:func:`facing`).
    """
    import warp as wp

    from ..kernels import precision as kp
    from .._device import to_host
    from .ortho.tiles import coarse_grid, coarse_struct

    if cells.b != 0 or cells.d != 0:
        raise ParamError(f"the accuracy grid must be north up (no rotation terms), got {tuple(cells)[:6]}")
    _check_sigmas(pixel_sigma, dem_sigma)
    table = ce90_table() if _measure(measure) == "ce90" else np.zeros(0)
    window = Tile(*map(int, window))
    rows, cols = window.shape
    device = geometry.device
    clock = [time.perf_counter()]

    def tick(step):  # with ``timings``: seconds per step, the device synchronised
        if timings is not None:
            wp.synchronize_device(device)
            now = time.perf_counter()
            timings[step] = timings.get(step, 0.0) + now - clock[0]
            clock[0] = now

    to_frame = Transformer.from_crs(crs, geometry.horizontal_crs, always_xy=True)
    grid = coarse_struct(coarse_grid(cells, to_frame, *window, step=nodes), geometry.geocentric, device,
                         step=nodes)
    tick("nodes")
    arg, refr = geometry.sensor_structs()
    dem = geometry.dem_struct()
    width, height = map(float, geometry.image_size)
    n_all = rows * cols
    if chunk is None:
        chunk = 1 << 21 if device.is_cuda else 1 << 18
    m = max(1, min(int(chunk), n_all))
    out = wp.empty((3, n_all), dtype=wp.float32, device=device)
    c_raw = wp.array(np.ascontiguousarray(c_raw, dtype=np.float64), dtype=wp.float64, device=device)
    table = wp.array(table, dtype=wp.float64, device=device)

    def written(dtype, grad=False):  # every entry written by a kernel before it is read
        return wp.empty(m, dtype=dtype, device=device, requires_grad=grad)

    def zeros(dtype, grad=False):
        return wp.zeros(m, dtype=dtype, device=device, requires_grad=grad)

    x, h, basis, slope = written(wp.vec3d, True), written(wp.float64), written(wp.mat33d), written(wp.vec2d)
    to_out, pix = written(wp.mat22d), written(wp.vec2d, True)
    d_r, d_k = zeros(wp.mat33d, True), zeros(kp.vec8d, True)  # the zero offsets the gradients are by
    # each reverse pass accumulates into its own zeroed gradient buffers: by the point, the
    # rotation and the camera, for the column (0) and the row (1)
    grads = [(zeros(wp.vec3d), zeros(wp.mat33d), zeros(kp.vec8d)) for _ in range(2)]
    seeds = [wp.full(m, value=wp.vec2d(*e), dtype=wp.vec2d, device=device) for e in np.eye(2)]
    tick("buffers")
    for start in range(0, n_all, m):
        n = min(m, n_all - start)
        wp.launch(kp.cell_points_kernel, dim=n, device=device,
                  inputs=[dem, grid, start, cols, 1.0 / nodes, 1.0 / (nodes * cells.a), 1.0 / (nodes * cells.e)],
                  outputs=[x, h, basis, slope, to_out])
        tick("cells")
        inputs = [arg.cam, arg.pose, refr, x, h, d_r, d_k]
        wp.launch(kp.pixel_ad_kernel, dim=n, device=device, inputs=inputs, outputs=[pix])
        tick("projection")
        for seed, g in zip(seeds, grads):  # reverse passes: d col, then d row
            if start:
                for a in g:
                    a.zero_()
            x.grad, d_r.grad, d_k.grad = g
            pix.grad.assign(seed)
            _reverse_launch(kp.pixel_ad_kernel, n, device, inputs, [pix])
        tick("gradients")
        (gx0, gr0, gk0), (gx1, gr1, gk1) = grads
        wp.launch(kp.accuracy_kernel, dim=n, device=device,
                  inputs=[pix, gx0, gx1, gr0, gr1, gk0, gk1, basis, slope, to_out, c_raw,
                          float(pixel_sigma) ** 2, float(dem_sigma) ** 2, width, height, table, start],
                  outputs=[out])
        wp.launch(hidden_facets_kernel, dim=n, device=device,
                  inputs=[arg.pose, x, grads[0][0], grads[1][0], basis, slope, start], outputs=[out])
        tick("covariance")
    sig = to_host(out).reshape(3, rows, cols)  # (a pinned buffer's allocation costs more than it saves)
    tick("read-back")
    return sig


def scene_cell_sigmas(scene: PushbroomScene, dem: Dem, crs: CRS, ox: np.ndarray, oy: np.ndarray, *,
                      orientation_cov: ArrayLike, pixel_sigma: float = 0.5, dem_sigma: float = 0.0,
                      refraction: bool = True, measure: str = "sigma", device: str | None = None) -> np.ndarray:
    """Predicted sigma x, y (the axes of ``crs``, in its unit) and up (m), (3, n) float32, of the ground
    under the points (ox, oy) of ``crs`` seen by a pushbroom scene (NaN where it does not see
    them: off the scene or the DEM, or hidden by their own slope, :func:`facing`), by :func:`scene_monoplot_covariance` at each point; or CE90, LE90 and NaN (see
    :func:`frame_window_sigmas`)."""
    _measure(measure)
    from .geometry import project

    square_matrix("orientation_cov", orientation_cov, len(SCENE_INPUTS))
    pts, slopes = _terrain_points(dem, crs, ox, oy, None)
    ok = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(slopes), axis=1)
    if ok.any():  # on the scene
        pix = project(scene, pts[ok], refraction=refraction, device=device)
        inside = np.all(np.isfinite(pix), axis=1) & (pix[:, 0] >= 0) & (pix[:, 0] <= scene.width) & (
            pix[:, 1] >= 0) & (pix[:, 1] <= scene.height)
        ok[np.flatnonzero(ok)[~inside]] = False
    out = np.full((3, len(ox)), np.nan, np.float32)
    if ok.any():
        _check_sigmas(pixel_sigma, dem_sigma)
        cov, f_x = _scene_monoplot(scene, pts[ok], slopes[ok], square_matrix("orientation_cov", orientation_cov,
                                                                             len(SCENE_INPUTS)),
                                   pixel_sigma, dem_sigma, refraction, device)
        # the line of sight: the pixel's null direction in east, north, up, toward the (orbiting) sensor
        v = np.cross(f_x[:, 0], f_x[:, 1])
        v *= np.where(v[:, 2] < 0.0, -1.0, 1.0)[:, None]
        seen = facing(v, slopes[ok])  # ground whose own slope hides it from the scene: NaN
        cov = cov[seen]
        ok[np.flatnonzero(ok)[~seen]] = False
        # east/north (m) -> the output CRS's x, y: J by central differences
        to_out = Transformer.from_crs("EPSG:4326", crs, always_xy=True)

        def out_xy(q):
            return np.stack(to_out.transform(q[:, 0], q[:, 1]), -1)

        p = pts[ok]
        jac = np.stack([out_xy(enu_shifted(p, a, 1.0)) - out_xy(enu_shifted(p, a, -1.0)) for a in (0, 1)], -1) / 2.0
        out[:, ok] = _sigmas(cov, jac, measure)
    return out


def _reverse_launch(kernel, dim, device, inputs, outputs):
    """The reverse (adjoint) pass of one launch of ``kernel``, accumulating into the ``grad``
    arrays of its array arguments (and of the arrays inside its struct arguments), from the
    ``grad`` arrays of its outputs: what ``wp.Tape.backward`` does for a recorded launch,
    without a tape. Warp keeps one tape for the whole process, which records every launch of
    every thread while it is active: kernels launched meanwhile by another thread (another
    image's ortho in a batch) would be recorded and run backwards too."""
    import warp as wp

    adjoints = wp.Tape()  # never entered: only its mapping of arguments to their adjoints
    wp.launch(kernel, dim=dim, device=device, inputs=inputs, outputs=outputs,
              adj_inputs=[adjoints.get_adjoint(a) for a in inputs],
              adj_outputs=[adjoints.get_adjoint(a) for a in outputs], adjoint=True)


def accuracy_raster(dst: str | os.PathLike, camera: FrameCamera, pose: Pose, dem: Dem | str | os.PathLike | float,
                    crs: CRS, transform: Affine, shape: tuple[int, int], *, pose_cov: ArrayLike, pixel_sigma: float = 0.5,
                    camera_cov: ArrayLike | None = None, camera_params: Sequence[str] = (), dem_sigma: float = 0.0,
                    step: int = 16, measure: str = "sigma", refraction: bool = True,
                    geoid: Dem | str | os.PathLike | None = None, same_vertical_datum: bool = False,
                    device: str | None = None) -> np.ndarray:
    """Write the predicted accuracy of an ortho of one frame image, computed on ``device``
    (:func:`frame_window_sigmas`).

    Parameters
    ----------
    dst : str or os.PathLike
        The raster (GeoTIFF, written atomically).
    camera : FrameCamera
    pose : Pose
        A photogrammetric (omega-phi-kappa) or GNSS/INS pose (see
        :mod:`orthowarp.adjust.precision` for the inputs ``pose_cov`` states).
    dem : Dem, str or float
        The terrain (any CRS): a Dem, a DEM file or a constant height (m).
    crs : pyproj.CRS
        The ortho's CRS.
    transform : affine.Affine
    shape : (int, int)
        The ortho's grid (rows, cols).
    pose_cov, pixel_sigma, camera_cov, camera_params, dem_sigma :
        As for :func:`~orthowarp.adjust.precision.monoplot_covariance`.
    step : int, optional
        Ortho pixels per accuracy pixel, each way.
    measure : {"sigma", "ce90"}, optional
        Three bands sigma x, y (the axes of ``crs``, in its axis unit) and up (m), or two bands
        CE90 and LE90 (m; see :func:`frame_window_sigmas`); each band's description and unit
        are set (:func:`band_descriptions`).
    refraction, geoid, same_vertical_datum, device :
        The ortho's geometry options (:class:`~orthowarp.pipeline.geometry.SensorGeometry`).

    Returns
    -------
    ndarray (bands, rows, cols) float32
        What was written; NaN where the image does not see the cell's centre (including
        ground hidden by its own slope).
    """
    from ..sensor import FrameSensor
    from .geometry import SensorGeometry

    grid, (rows, cols) = _cell_grid(transform, shape, step)
    bands = 2 if _measure(measure) == "ce90" else 3
    c_raw = raw_covariance(camera, pose, pose_cov=pose_cov, camera_cov=camera_cov, camera_params=camera_params)
    geom = SensorGeometry(FrameSensor(camera, pose), dem, refraction=refraction, device=device, geoid=geoid,
                          same_vertical_datum=same_vertical_datum)
    out = frame_window_sigmas(geom, crs, grid, (0, 0, rows, cols), c_raw, pixel_sigma=pixel_sigma,
                              dem_sigma=dem_sigma, measure=measure)[:bands]
    _write_accuracy(dst, out, grid, crs, measure)
    return out


def scene_accuracy_raster(dst: str | os.PathLike, scene: PushbroomScene, dem: Dem | str | os.PathLike | float, crs: CRS,
                          transform: Affine, shape: tuple[int, int], *, orientation_cov: ArrayLike,
                          pixel_sigma: float = 0.5, dem_sigma: float = 0.0, step: int = 16, measure: str = "sigma",
                          refraction: bool = True, device: str | None = None) -> np.ndarray:
    """Write the predicted accuracy of an ortho of one pushbroom scene: as
    :func:`accuracy_raster`, with :func:`scene_monoplot_covariance` (``orientation_cov``: (8,
    8) in the order and units of :data:`SCENE_INPUTS`) at each cell's centre.

    Returns
    -------
    ndarray (bands, rows, cols) float32
        What was written: sigma x, y (the output CRS's axes, in its unit) and up (m), or CE90
        and LE90 (m).
    """
    grid, (rows, cols) = _cell_grid(transform, shape, step)
    ox, oy = _cell_centres(grid, rows, cols)
    bands = 2 if _measure(measure) == "ce90" else 3
    out = scene_cell_sigmas(scene, dem, crs, ox, oy, orientation_cov=orientation_cov, pixel_sigma=pixel_sigma,
                            dem_sigma=dem_sigma, refraction=refraction, measure=measure,
                            device=device).reshape(3, rows, cols)[:bands]
    _write_accuracy(dst, out, grid, crs, measure)
    return out


def sensor_accuracy_raster(dst: str | os.PathLike, sensor: SensorModel, dem: Dem | str | os.PathLike | float,
                           crs: CRS, transform: Affine, shape: tuple[int, int], *, pose_cov: np.ndarray | None = None,
                           orientation_cov: np.ndarray | None = None, pixel_sigma: float = 0.5, dem_sigma: float = 0.0,
                           step: int = 16, measure: str = "sigma", refraction: bool = True,
                           geoid: Dem | str | os.PathLike | None = None, same_vertical_datum: bool = False,
                           device: str | None = None) -> np.ndarray:
    """Write the predicted accuracy of an ortho of any sensor: :func:`accuracy_raster` for a
    frame image (``FrameSensor``), :func:`scene_accuracy_raster` for a pushbroom scene.

    Parameters
    ----------
    dst : str or os.PathLike
        The raster (GeoTIFF, written atomically).
    sensor : SensorModel
        A ``FrameSensor`` or a ``PushbroomScene``.
    dem, crs, transform, shape, step, measure, pixel_sigma, dem_sigma, refraction, device :
        As for :func:`accuracy_raster` (the ortho's grid: ``crs``, ``transform``, ``shape``
        (rows, cols)).
    pose_cov : array_like (k, k)
        A frame's pose covariance (m, deg; see :func:`accuracy_raster`); needed for frames.
    orientation_cov : array_like (8, 8)
        A scene's orientation covariance, in the order and units of :data:`SCENE_INPUTS`;
        needed for scenes.
    geoid, same_vertical_datum :
        Frames only, as for :func:`accuracy_raster` (a scene's heights are ellipsoidal).

    Returns
    -------
    ndarray (bands, rows, cols) float32
        What was written (see :func:`accuracy_raster`).

    Raises
    ------
    ParamError
        The covariance the sensor needs is missing, or the sensor is of another kind.
    """
    from ..sensor import SensorModel

    if not isinstance(sensor, SensorModel):
        raise ParamError(f"sensor must be a FrameSensor or a PushbroomScene, got {type(sensor).__name__}")
    if sensor.line_timed:
        if orientation_cov is None:
            raise ParamError("The accuracy of a pushbroom scene needs orientation_cov (8 x 8)")
        return scene_accuracy_raster(dst, sensor, dem, crs, transform, shape, orientation_cov=orientation_cov,
                                     pixel_sigma=pixel_sigma, dem_sigma=dem_sigma, measure=measure, step=step,
                                     refraction=refraction, device=device)
    if getattr(sensor, "pose", None) is None:  # neither line times nor a pose (RPCs): nothing to propagate
        raise ParamError(f"The accuracy of {sensor.kind} images is not supported (no orientation to propagate)")
    if pose_cov is None:
        raise ParamError("The accuracy of a frame image needs pose_cov")
    return accuracy_raster(dst, sensor.camera, sensor.pose, dem, crs, transform, shape, pose_cov=pose_cov,
                           pixel_sigma=pixel_sigma, dem_sigma=dem_sigma, measure=measure, step=step,
                           refraction=refraction, geoid=geoid, same_vertical_datum=same_vertical_datum,
                           device=device)


def accuracy_path(dst: str | os.PathLike) -> str:
    """The accuracy raster's name beside an output: ``<image>_ACCURACY.tif`` for
    ``<image>_ORTHO.tif``, ``<name>_ACCURACY.tif`` for any other ``<name>.<ext>``.

    Parameters
    ----------
    dst : str or os.PathLike
        The ortho's or mosaic's path.

    Returns
    -------
    str
    """
    dst = os.fspath(dst)
    base = dst[:-len("_ORTHO.tif")] if dst.endswith("_ORTHO.tif") else os.path.splitext(dst)[0]
    return base + "_ACCURACY.tif"


def mosaic_accuracy_raster(dst: str | os.PathLike, images: Sequence, index: str | os.PathLike,
                           dem: Dem | str | os.PathLike | float, crs: CRS, transform: Affine, shape: tuple[int, int], *,
                           pose_cov: ArrayLike | None = None, orientation_cov: ArrayLike | None = None,
                           pixel_sigma: float = 0.5, dem_sigma: float = 0.0, step: int = 16, measure: str = "sigma",
                           refraction: bool = True, geoid: Dem | str | os.PathLike | None = None,
                           same_vertical_datum: bool = False, device: str | None = None) -> np.ndarray:
    """Write the predicted accuracy of a mosaic: each cell from the image the mosaic took the
    cell's centre from (its source-index raster), as :func:`accuracy_raster` /
    :func:`scene_accuracy_raster` for that image.

    Parameters
    ----------
    dst : str or os.PathLike
    images : sequence
        The mosaic's images in index order: their sensors (``FrameSensor``,
        ``PushbroomScene``), or (src, sensor) items as :func:`~orthowarp.pipeline.mosaic.mosaic`
        takes them.
    index : str or os.PathLike
        The mosaic's source-index raster (uint16, the image's position; 65535 for none).
    dem, crs, transform, shape, step :
        As for :func:`accuracy_raster` (the mosaic's grid).
    pose_cov : array_like (6, 6)
        Frames' pose covariance (as for :func:`accuracy_raster`); needed with frames.
    orientation_cov : array_like (8, 8)
        Scenes' orientation covariance (:data:`SCENE_INPUTS`); needed with scenes.
    pixel_sigma, dem_sigma, measure, refraction, geoid, same_vertical_datum, device :
        As above (``geoid``, ``same_vertical_datum``: frames only).

    Returns
    -------
    ndarray (bands, rows, cols) float32
        What was written.
    """
    import rasterio

    from ..sensor import SensorModel
    from .geometry import SensorGeometry
    from .raster.io import pending_path
    from .mosaic import NO_SOURCE

    grid, (rows, cols) = _cell_grid(transform, shape, step)
    bands = 2 if _measure(measure) == "ce90" else 3
    try:
        with rasterio.open(pending_path(index)) as ds:  # maybe not yet published (outputs_together)
            if (ds.height, ds.width) != tuple(shape):
                raise ParamError(f"Index '{index}' is {ds.height} x {ds.width} pixels, the mosaic {shape[0]} x {shape[1]}")
            # the pixel at each cell's centre (a cell of step x step pixels; the last may be short)
            r = np.minimum(np.arange(rows) * int(step) + int(step) // 2, shape[0] - 1)
            c = np.minimum(np.arange(cols) * int(step) + int(step) // 2, shape[1] - 1)
            if shape[0] * shape[1] <= 64 << 20:  # at most 128 MB: read whole
                src = ds.read(1)[np.ix_(r, c)].ravel()
            else:  # one row of pixels per row of cells
                src = np.concatenate([ds.read(1, window=((int(i), int(i) + 1), (0, shape[1])))[0, c] for i in r])
    except rasterio.errors.RasterioIOError as e:
        raise ParamError(f"Could not read index '{index}': {e}") from e
    out = np.full((3, rows * cols), np.nan, np.float32)
    for k in np.unique(src):
        if k == NO_SOURCE:
            continue
        if k >= len(images):
            raise ParamError(f"Index '{index}' names image {k}; {len(images)} images were given")
        at = np.flatnonzero(src == k)
        item = images[k]
        sensor = item if isinstance(item, SensorModel) else item[1]
        if not isinstance(sensor, SensorModel):
            raise ParamError(f"images[{k}] must be a sensor or (source, sensor), got {type(sensor).__name__}")
        if sensor.line_timed:
            if orientation_cov is None:
                raise ParamError("mosaic_accuracy_raster: a pushbroom scene needs orientation_cov")
            ox, oy = _cell_centres(grid, rows, cols, at)
            out[:, at] = scene_cell_sigmas(sensor, dem, crs, ox, oy, orientation_cov=orientation_cov,
                                           pixel_sigma=pixel_sigma, dem_sigma=dem_sigma, refraction=refraction,
                                           measure=measure, device=device)
        else:
            if getattr(sensor, "pose", None) is None:  # (RPCs)
                raise ParamError(f"mosaic_accuracy_raster: the accuracy of {sensor.kind} images is not supported")
            if pose_cov is None:
                raise ParamError("mosaic_accuracy_raster: frame images need pose_cov")
            # the image's cells: its window of the grid on the device, then those it supplies
            i, j = np.divmod(at, cols)
            win = Tile(int(i.min()), int(j.min()), int(i.max() - i.min() + 1), int(j.max() - j.min() + 1))
            geom = SensorGeometry(sensor, dem, refraction=refraction, device=device, geoid=geoid,
                                  same_vertical_datum=same_vertical_datum)
            sig = frame_window_sigmas(geom, crs, grid, win, raw_covariance(sensor.camera, sensor.pose,
                                                                           pose_cov=pose_cov),
                                      pixel_sigma=pixel_sigma, dem_sigma=dem_sigma, measure=measure)
            out[:, at] = sig[:, i - win.row, j - win.col]
    out = out.reshape(3, rows, cols)[:bands]
    _write_accuracy(dst, out, grid, crs, measure)
    return out
