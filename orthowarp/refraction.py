"""Atmospheric refraction: a layered standard atmosphere traced with Snell's law.

The atmosphere is the U.S. Standard Atmosphere 1976 (pressure and temperature by geopotential
layers up to 86 km, vacuum above), and its refractivity the dry-air Smith-Weintraub/Essen form
``N = 77.6 P / T`` (P in hPa, T in K; n = 1 + 1e-6 N), as in [P3]'s eq. 13 sense of a
refractive index per layer. Layers are 50 m thick below 20 km ([P3] uses 1 km), 250 m to
50 km and 1 km above. Inside a layer the index is constant and the ray straight; across
spherical layer boundaries Snell's law makes ``n r sin(z)`` invariant (Bouguer), so the central
angle a ray sweeps is the sum over layers of ``acos(b / r_top) - acos(b / r_bottom)`` with the
layer's impact parameter ``b = n_C r_C sin(theta_C) / n``.

The quantity the kernels use is ``delta(theta, h)``: the angle at the sensor between the
apparent ray (nadir angle theta) and the straight chord to the point where the traced ray
reaches ellipsoidal height h. The ASPRS closed form (Manual of Photogrammetry) is provided as a
cross-check.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from ._device import upload
from .errors import GeometryError, ParamError
from .kernels.refraction import RefractionTable

if TYPE_CHECKING:  # annotations only
    from numpy.typing import ArrayLike

__all__ = [
    "standard_atmosphere",
    "refractive_index",
    "trace_delta",
    "asprs_delta",
    "saastamoinen_delta",
    "RefractionModel",
]

EARTH_RADIUS = 6371000.0  # mean radius of the spherical shells (m)
_R0 = 6356766.0  # radius used by the 1976 standard atmosphere for geopotential height (m)
_G0M_R = 9.80665 * 0.0289644 / 8.3144598  # g0 M / R* (K/m)
# (base geopotential height m, base temperature K, lapse rate K/m) of the 1976 layers
_LAYERS = [(0.0, 288.15, -0.0065), (11000.0, 216.65, 0.0), (20000.0, 216.65, 0.001),
           (32000.0, 228.65, 0.0028), (47000.0, 270.65, 0.0), (51000.0, 270.65, -0.0028),
           (71000.0, 214.65, -0.002)]
_TOP = 86000.0  # geometric altitude above which the index is taken as 1
LOWEST_LAYER = -2000.0  # m: the layered atmosphere's floor (below the lowest land, -430 m)


def _layer_base_pressures() -> np.ndarray:
    p = [101325.0]
    for (hb, tb, lr), (hn, _, _) in zip(_LAYERS[:-1], _LAYERS[1:]):
        dh = hn - hb
        if lr == 0.0:
            p.append(p[-1] * np.exp(-_G0M_R * dh / tb))
        else:
            p.append(p[-1] * (tb / (tb + lr * dh)) ** (_G0M_R / lr))
    return np.array(p)


_PB = _layer_base_pressures()
_HB = np.array([la[0] for la in _LAYERS])
_TB = np.array([la[1] for la in _LAYERS])
_LR = np.array([la[2] for la in _LAYERS])


def standard_atmosphere(z: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Pressure (Pa) and temperature (K) of the U.S. Standard Atmosphere 1976.

    Parameters
    ----------
    z : array_like
        Geometric altitude above sea level (m); the lowest layer extends below 0.

    Returns
    -------
    pressure : ndarray, shape of ``z``
        Pa.
    temperature : ndarray, shape of ``z``
        K.
    """
    z = np.asarray(z, dtype=np.float64)
    hgp = _R0 * z / (_R0 + z)
    k = np.clip(np.searchsorted(_HB, hgp, side="right") - 1, 0, len(_LAYERS) - 1)
    base, tb, lr = _HB[k], _TB[k], _LR[k]
    t = tb + lr * (hgp - base)
    with np.errstate(divide="ignore", invalid="ignore"):
        p_grad = _PB[k] * (tb / t) ** (_G0M_R / np.where(lr == 0.0, 1.0, lr))
    p_iso = _PB[k] * np.exp(-_G0M_R * (hgp - base) / tb)
    return np.where(lr == 0.0, p_iso, p_grad), t


def refractive_index(z: ArrayLike) -> np.ndarray:
    """Refractive index n of dry air at geometric altitude z (m), 1 above 86 km.

    Parameters
    ----------
    z : array_like
        Geometric altitude above sea level (m).

    Returns
    -------
    ndarray, shape of ``z``
        n = 1 + 77.6e-6 P / T (P in hPa, T in K) of the standard atmosphere, dimensionless.
    """
    p, t = standard_atmosphere(z)
    n = 1.0 + 77.6e-6 * (p / 100.0) / t
    return np.where(np.asarray(z) >= _TOP, 1.0, n)


def _boundaries(top: float) -> np.ndarray:
    """Layer boundaries (descending, m) from ``top`` down to -2 km."""
    b = np.concatenate([np.arange(LOWEST_LAYER, 20000.0, 50.0), np.arange(20000.0, 50000.0, 250.0),
                        np.arange(50000.0, _TOP, 1000.0), [_TOP]])
    b = b[b < top]
    return np.concatenate([[top], b[::-1]])


def trace_delta(theta: ArrayLike, sensor_height: float, ground_height: ArrayLike, *,
                radius: float = EARTH_RADIUS) -> np.ndarray:
    """Refraction angle delta (rad) by tracing through spherical layers.

    Parameters
    ----------
    theta : array_like
        Apparent nadir angle of the ray at the sensor (rad), shape (T,) or broadcastable with
        ``ground_height``.
    sensor_height : float
        Sensor height above the sphere (m).
    ground_height : array_like
        Height (m) where the ray is stopped, < sensor_height.
    radius : float, optional
        Radius of the spherical shells (m).

    Returns
    -------
    ndarray, the broadcast shape of ``theta`` and ``ground_height``
        delta = theta - (nadir angle of the chord from the sensor to the stopped point), rad;
        NaN where the ray never descends to ``ground_height``.

    Raises
    ------
    ParamError
        A ground height is not below the sensor.
    """
    theta, hg = np.broadcast_arrays(np.asarray(theta, dtype=np.float64),
                                    np.asarray(ground_height, dtype=np.float64))
    hs = float(sensor_height)
    if np.any(hg >= hs):
        raise ParamError("ground_height must be below sensor_height")
    rc = radius + hs
    p = (refractive_index(hs) * rc * np.sin(theta)).ravel()  # Bouguer invariant n r sin z
    flat_hg = hg.ravel()
    bnd = _boundaries(hs)
    bnd = bnd[: max(int(np.count_nonzero(bnd > flat_hg.min())) + 1, 2)] if flat_hg.size else bnd[:2]
    top, bot = bnd[:-1], bnd[1:]
    n_layers = len(top)
    # per ray: the layers it crosses whole (those from the top whose bottom is at or above its
    # stop), then the part of the next one above its stop, if that layer's top is above it
    whole = np.searchsorted(-bot, -flat_hg, side="right")
    part = np.minimum(whole, n_layers - 1)
    has_part = (whole < n_layers) & (top[part] > flat_hg)
    # the index of a layer the ray crosses whole is the layer's; of the layer where it stops,
    # that of the part above the stop: one value per layer and one per ray
    n_whole = refractive_index(0.5 * (top + bot))
    n_stop = refractive_index(0.5 * (top[part] + flat_hg))  # (used where the ray has that part)
    # a whole layer's angle depends on the ray's invariant only: computed once per distinct
    # invariant (a table's rays share theirs across its heights), each ray's sum of its whole
    # layers then a running sum's entry. The sums run layer by layer within chunks of layers,
    # chunk by chunk, as a sum over layers x rays arrays of bounded size would, so that each
    # value is that sum's to the last bit.
    pu, ray_p = np.unique(p, return_inverse=True)
    ray_p = ray_p.ravel()
    chunk = max(1, (1 << 20) // max(p.size, 1))
    phi = np.zeros_like(p)
    with np.errstate(invalid="ignore"):
        b_part = p / n_stop
        seg_part = np.arccos(b_part / (radius + top[part])) - np.arccos(b_part / (radius + flat_hg))
        for i in range(0, n_layers, chunk):
            t, b0 = top[i:i + chunk, None], bot[i:i + chunk, None]
            b = pu / n_whole[i:i + chunk, None]
            running = np.cumsum(np.arccos(b / (radius + t)) - np.arccos(b / (radius + b0)), axis=0)
            k = np.clip(whole - i, 0, len(t))  # the ray's whole layers in this chunk
            add = np.where(k > 0, running[np.maximum(k - 1, 0), ray_p], 0.0)
            here = has_part & (whole >= i) & (whole < i + chunk)
            add = np.where(here, np.where(k > 0, add + seg_part, seg_part), add)
            phi += add
        rg = radius + flat_hg
        chord = np.arctan2(rg * np.sin(phi), rc - rg * np.cos(phi))
    return theta - chord.reshape(theta.shape)


def asprs_delta(theta: ArrayLike, sensor_height: ArrayLike, ground_height: ArrayLike = 0.0) -> np.ndarray:
    """ASPRS closed form of the refraction angle (rad): ``K tan(theta)``.

    ``K = 2410 H / (H^2 - 6 H + 250) - 2410 h^2 / ((h^2 - 6 h + 250) H)`` microradians with
    H and h in km (Manual of Photogrammetry); valid for aircraft heights.

    Parameters
    ----------
    theta : array_like
        Apparent nadir angle of the ray at the sensor (rad).
    sensor_height : array_like
        Sensor height H (m) above sea level.
    ground_height : array_like, optional
        Ground height h (m) above sea level.

    Returns
    -------
    ndarray, the broadcast shape of the arguments
        Refraction angle delta (rad).
    """
    big_h = np.asarray(sensor_height, dtype=np.float64) / 1000.0
    h = np.asarray(ground_height, dtype=np.float64) / 1000.0
    k = 2410.0 * big_h / (big_h**2 - 6.0 * big_h + 250.0) - 2410.0 * h**2 / ((h**2 - 6.0 * h + 250.0) * big_h)
    return 1e-6 * k * np.tan(theta)


def saastamoinen_delta(theta: ArrayLike, sensor_height: ArrayLike, ground_height: ArrayLike = 0.0) -> np.ndarray:
    """Saastamoinen's (1972) closed form of the refraction angle (rad) for aerial photographs.

    ``13 (H - h) (1 - 0.02 (2 H + h)) tan(theta)`` microradians with H and h in km.

    Parameters
    ----------
    theta : array_like
        Apparent nadir angle of the ray at the sensor (rad).
    sensor_height : array_like
        Sensor height H (m) above sea level.
    ground_height : array_like, optional
        Ground height h (m) above sea level.

    Returns
    -------
    ndarray, the broadcast shape of the arguments
        Refraction angle delta (rad).
    """
    big_h = np.asarray(sensor_height, dtype=np.float64) / 1000.0
    h = np.asarray(ground_height, dtype=np.float64) / 1000.0
    return 13e-6 * (big_h - h) * (1.0 - 0.02 * (2.0 * big_h + h)) * np.tan(theta)


def _table_nodes(lo: float, hi: float, theta_max: float) -> tuple[np.ndarray, np.ndarray]:
    """:class:`RefractionModel`'s nodes: apparent nadir angles (N_THETA,) from 0 to
    ``theta_max`` degrees, in rad, and ground heights (N_H,) from ``lo`` to ``hi`` m."""
    return (np.radians(np.linspace(0.0, theta_max, RefractionModel.N_THETA)),
            np.linspace(lo, hi, RefractionModel.N_H))


@functools.lru_cache(maxsize=256)
def _q_table(sensor_height: float, lo: float, hi: float, theta_max: float) -> np.ndarray:
    """:class:`RefractionModel`'s table q (N_THETA, N_H), read-only, made once per process for
    each set of its arguments (a mosaic builds an image's geometry several times: for its
    grid, its reduced window and each worker's tiles; its probes' table too)."""
    theta, heights = _table_nodes(lo, hi, theta_max)
    th = np.maximum(theta, 1e-3)[:, None]
    q = trace_delta(th, sensor_height, heights[None, :]) / np.tan(th)
    q.setflags(write=False)
    return q


class RefractionModel:
    """Per-image refraction table for the kernels.

    Parameters
    ----------
    sensor_height : float
        Ellipsoidal height (m) of the sensor.
    h_min, h_max : float
        Range of ground heights (m) the table must cover.
    theta_max : float, optional
        Largest apparent nadir angle tabulated (deg); larger angles use its value of
        ``delta / tan(theta)``.
    enabled : bool, optional
        False gives a table that the kernels read as "no refraction".

    Attributes
    ----------
    theta : ndarray, shape (N_THETA,)
        Tabulated apparent nadir angles (rad), evenly spaced from 0 to ``theta_max``.
    heights : ndarray, shape (N_H,)
        Tabulated ground heights (m), evenly spaced from ``h_min`` - 10 m to ``h_max`` + 10 m (or
        to 1 m below the sensor if that is lower).
    q : ndarray, shape (N_THETA, N_H)
        ``delta / tan(theta)`` at each node (zero when not ``enabled``).

    Raises
    ------
    GeometryError
        Refraction is enabled and the sensor is below the atmosphere's floor (-2 km).
    """

    N_THETA = 181
    N_H = 17

    def __init__(self, sensor_height: float, h_min: float, h_max: float, *, theta_max: float = 89.0,
                 enabled: bool = True) -> None:
        self.enabled = bool(enabled)
        self.sensor_height = float(sensor_height)
        if self.enabled and not self.sensor_height > LOWEST_LAYER:
            raise GeometryError(f"The sensor's height {self.sensor_height:.3f} m is below any terrain (the refraction "
                                f"model's atmosphere ends at {LOWEST_LAYER:g} m): check the pose's height")
        lo = float(h_min) - 10.0
        hi = min(float(h_max) + 10.0, self.sensor_height - 1.0)
        if hi <= lo:
            lo = hi - 20.0
        self.theta, self.heights = _table_nodes(lo, hi, float(theta_max))
        if self.enabled:
            self.q = _q_table(self.sensor_height, lo, hi, float(theta_max))
        else:
            self.q = np.zeros((self.N_THETA, self.N_H))

    def delta(self, theta: ArrayLike, h: ArrayLike) -> np.ndarray:
        """Refraction angle (rad) at apparent nadir angle theta (rad) and ground height h (m).

        Host twin of the kernel lookup (bilinear in the table), for tests and planning.

        Parameters
        ----------
        theta : array_like
            Apparent nadir angle (rad).
        h : array_like
            Ground height (m), broadcasting with ``theta``; clamped to the table's range.

        Returns
        -------
        ndarray, the broadcast shape of ``theta`` and ``h``
            delta (rad); zeros when the model is not ``enabled``.
        """
        ft = np.clip(np.asarray(theta) / (self.theta[1] - self.theta[0]), 0, self.N_THETA - 1)
        fh = np.clip((np.asarray(h) - self.heights[0]) / (self.heights[1] - self.heights[0]), 0, self.N_H - 1)
        it = np.minimum(ft.astype(int), self.N_THETA - 2)
        ih = np.minimum(fh.astype(int), self.N_H - 2)
        at, ah = ft - it, fh - ih
        q = ((1 - at) * ((1 - ah) * self.q[it, ih] + ah * self.q[it, ih + 1])
             + at * ((1 - ah) * self.q[it + 1, ih] + ah * self.q[it + 1, ih + 1]))
        return q * np.tan(theta) if self.enabled else np.zeros_like(q)

    def to_struct(self, device: wp.DeviceLike) -> RefractionTable:
        """Pack into :class:`orthowarp.kernels.refraction.RefractionTable` on ``device``.

        Parameters
        ----------
        device : str or warp.context.Device
            Where the table's array is allocated.

        Returns
        -------
        RefractionTable
            The Warp struct the kernels read (its ``q`` a float64 Warp array on ``device``).
        """
        s = RefractionTable()
        s.enabled = 1 if self.enabled else 0
        s.theta0 = 0.0
        s.dtheta = float(self.theta[1] - self.theta[0])
        s.h0 = float(self.heights[0])
        s.dh = float(self.heights[1] - self.heights[0])
        s.inv_dtheta, s.inv_dh = 1.0 / s.dtheta, 1.0 / s.dh
        s.q = upload(self.q, dtype=wp.float64, device=device)  # (enqueued: see orthowarp._device.upload)
        return s
