"""RPC images in the pipeline: RPC00B coefficients fitted to any sensor through its kernels
(:func:`fit_sensor_rpc`), and an RPC image's sensor from its files with the bias compensation
estimated from ground control (:func:`rpc_image_sensor`, what ``orthowarp ortho --rpc`` runs).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..adjust.rpc import BiasResult, RpcFitResult, estimate_bias, fit_rpc, leave_one_out
from ..errors import ParamError
from ..rpc import BIAS_MODELS, RationalSensor
from ..sensor import SensorModel
from .formats.rpc import GroundControl, read_gcps, rpc_sensor
from .geometry import geolocate

if TYPE_CHECKING:
    from warp.context import Device

__all__ = ["fit_sensor_rpc", "sensor_grid", "rpc_image_sensor", "RpcImage", "REGULARIZATIONS"]


def sensor_grid(sensor: SensorModel, *, height_range: tuple[float, float], shape: tuple[int, int, int] = (21, 21, 7),
                offset: float = 0.0, refraction: bool = True, device: str | Device | None = None,
                ) -> tuple[np.ndarray, np.ndarray]:
    """A terrain-independent 3-D grid of a sensor: image rows and columns evenly over the image
    (the border included), each geolocated by the sensor's kernels on surfaces of constant
    ellipsoidal height evenly over ``height_range``.

    Parameters
    ----------
    sensor : SensorModel
        A geocentric sensor (geo triples lon, lat, ellipsoidal h).
    height_range : (float, float)
        Lowest and highest height (m).
    shape : (int, int, int), optional
        Columns, rows and heights of the grid.
    offset : float, optional
        Shift of the columns, rows and heights by this fraction of a cell (0.5: the centres of
        the cells of the grid with offset 0, for independent checks; the last ones dropped).
    refraction : bool, optional
        Geolocate with atmospheric refraction (what the sensor's images show).
    device : str, optional
        Warp device.

    Returns
    -------
    pixels : ndarray, shape (N, 2)
        (col, row) of the points.
    ground : ndarray, shape (N, 3)
        Their lon, lat (deg), ellipsoidal h (m); rows that meet no ground dropped.

    Raises
    ------
    ParamError
        A sensor whose geo triples are not geocentric, a bad range or shape.
    """
    if not sensor.geocentric:
        raise ParamError("RPCs are fitted to geocentric sensors (geo triples of longitude, latitude, ellipsoidal "
                         "height)")
    lo, hi = sorted(float(h) for h in height_range)
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise ParamError(f"height_range must be two different finite heights, got {height_range!r}")
    nc, nr, nh = (int(n) for n in shape)
    if min(nc, nr) < 2 or nh < 4:
        raise ParamError(f"shape must be at least 2 columns, 2 rows and 4 heights, got {shape!r}")
    w, h = sensor.image_size

    def axis(n: int, size: float) -> np.ndarray:
        v = (np.arange(n) + offset) * size / (n - 1)
        return v[v <= size]

    cols, rows, heights = axis(nc, w), axis(nr, h), lo + axis(nh, hi - lo)
    cc, rr = np.meshgrid(cols, rows)
    pix = np.stack([cc.ravel(), rr.ravel()], 1)
    all_pix, all_ground = [], []
    for z in heights:
        g = geolocate(sensor, pix, dem=float(z), refraction=refraction, device=device)
        ok = np.all(np.isfinite(g), axis=1)
        all_pix.append(pix[ok])
        all_ground.append(g[ok])
    return np.concatenate(all_pix), np.concatenate(all_ground)


#: The Tikhonov lambdas :func:`fit_sensor_rpc` tries (see :func:`orthowarp.adjust.rpc.fit_rpc`).
REGULARIZATIONS = (0.0, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3)


def fit_sensor_rpc(sensor: SensorModel, *, height_range: tuple[float, float], shape: tuple[int, int, int] = (21, 21, 7),
                   refraction: bool = True, device: str | Device | None = None, iterations: int = 3,
                   regularization: float | None = None) -> RpcFitResult:
    """RPC00B coefficients of a sensor (a SPOT-5 :class:`~orthowarp.pushbroom.PushbroomScene`,
    say), fitted terrain-independently (:func:`orthowarp.adjust.rpc.fit_rpc`) to a 3-D grid
    of its geolocation (:func:`sensor_grid`), with the fit's error on that grid and on an
    independent one.

    The regularisation is chosen, unless given, among :data:`REGULARIZATIONS` as the one
    whose RPCs deviate least (largest error) at the centres of the grid's cells, where poles
    of loosely fixed denominators would show; the reported check is on a third grid (a
    quarter of a cell off the nodes).

    Parameters
    ----------
    sensor : SensorModel
        A geocentric sensor.
    height_range : (float, float)
        The heights (m, ellipsoidal) the RPCs must serve: the terrain's, with a margin.
    shape : (int, int, int), optional
        Columns, rows and heights of the fit's grid.
    refraction : bool, optional
        The sensor's geolocation with atmospheric refraction (the RPCs then hold it).
    device : str, optional
        Warp device.
    iterations : int, optional
        Reweighted solves of the fit.
    regularization : float, optional
        Tikhonov's lambda; default: chosen (see above).

    Returns
    -------
    RpcFitResult
        Its ``check_rms`` (col, row) and ``check_max`` (px): the fitted RPCs' projections of
        the independent grid's ground points against the sensor's pixels.
    """
    grid = dict(height_range=height_range, shape=shape, refraction=refraction, device=device)
    pix, ground = sensor_grid(sensor, **grid)

    def worst(fit: RpcFitResult, points: tuple[np.ndarray, np.ndarray]) -> float:
        err = np.linalg.norm(fit.rpc.pixels(points[1]) - points[0], axis=1)
        return float(np.max(err)) if np.all(np.isfinite(err)) else np.inf

    if regularization is None:
        centres = sensor_grid(sensor, offset=0.5, **grid)
        fits = [f for f in (fit_rpc(pix, ground, iterations=iterations, regularization=lam)
                            for lam in REGULARIZATIONS) if f.success]
        if not fits:
            return fit_rpc(pix, ground, iterations=iterations)
        fit = min(fits, key=lambda f: worst(f, centres))
    else:
        fit = fit_rpc(pix, ground, iterations=iterations, regularization=regularization)
    if fit.success:
        cpix, cground = sensor_grid(sensor, offset=0.25, **grid)
        res = fit.rpc.pixels(cground) - cpix
        fit.check_rms = np.sqrt(np.mean(res * res, axis=0))
        fit.check_max = float(np.max(np.linalg.norm(res, axis=1)))
    return fit


@dataclass
class RpcImage:
    """An RPC image's sensor from :func:`rpc_image_sensor`, with its ground control.

    Attributes
    ----------
    sensor : RationalSensor
        Compensated where ground control was given.
    control : GroundControl or None
    bias : BiasResult or None
        The estimate (None without ground control).
    check_before, check_after : ndarray, shape (N, 2), or None
        Leave-one-out check residuals (px) of the control points without and with the
        compensation (see :func:`orthowarp.adjust.rpc.leave_one_out`).
    """

    sensor: RationalSensor
    control: GroundControl | None = None
    bias: BiasResult | None = None
    check_before: np.ndarray | None = None
    check_after: np.ndarray | None = None

    def summary(self) -> dict[str, Any]:
        """The compensation's figures: model, points, estimates, sigma0 and the RMS length
        (px) of the leave-one-out check residuals before and after (points whose check is
        NaN left out); empty without ground control.

        Returns
        -------
        dict
        """
        if self.bias is None:
            return {}

        def rms(v: np.ndarray) -> float:
            ok = np.all(np.isfinite(v), axis=1)
            return float(np.sqrt(np.mean(np.sum(v[ok] ** 2, axis=1)))) if ok.any() else float("nan")

        return dict(model=self.bias.model, points=len(self.control.ids), estimates=self.bias.estimates,
                    sigma0=self.bias.sigma0, check_rms_before_px=rms(self.check_before),
                    check_rms_after_px=rms(self.check_after))


def rpc_image_sensor(image: str | os.PathLike, *, rpc: str | os.PathLike | None = None,
                     gcps: str | os.PathLike | None = None, bias: str = "shift",
                     pixel_sigma: float = 1.0) -> RpcImage:
    """An RPC image's sensor from its files: the RPCs of its metadata or of an RPC file
    (:func:`~orthowarp.pipeline.formats.rpc.rpc_sensor`), compensated by the bias that ground
    control points estimate (:func:`~orthowarp.adjust.rpc.estimate_bias`), with the control
    points' leave-one-out check residuals before and after.

    Parameters
    ----------
    image : str or os.PathLike
    rpc : str or os.PathLike, optional
        An .RPB, _RPC.TXT or orthority RPC parameter file; default: the image's metadata.
    gcps : str or os.PathLike, optional
        Orthority's GCP GeoJSON (the points of this image are used).
    bias : {"shift", "affine"}, optional
        The compensation's model (with ``gcps``).
    pixel_sigma : float, optional
        Standard deviation of the points' image measurements (px).

    Returns
    -------
    RpcImage

    Raises
    ------
    ParamError
        Unusable files, an unknown model, or a compensation the points cannot fix (the
        message says why).
    RasterIOError
        A file cannot be read.
    """
    if bias not in BIAS_MODELS:
        raise ParamError(f"bias must be one of {sorted(BIAS_MODELS)}, got {bias!r}")
    sensor = rpc_sensor(image, rpc)
    if gcps is None:
        return RpcImage(sensor)
    control = read_gcps(gcps, image=image)
    result = estimate_bias(sensor, control.pixels, control.ground, model=bias, pixel_sigma=pixel_sigma)
    if not result.success:
        raise ParamError(f"'{os.fspath(gcps)}': {result.message}")
    before = leave_one_out(sensor, control.pixels, control.ground, model=None)
    after = leave_one_out(sensor, control.pixels, control.ground, model=bias, pixel_sigma=pixel_sigma)
    return RpcImage(result.sensor, control, result, before, after)
