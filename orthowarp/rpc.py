"""Rational polynomial (RPC00B) sensor model of satellite images, with bias compensation in
image space: :class:`RpcCoefficients` (the vendor's coefficients) and :class:`RationalSensor`
(a :class:`~orthowarp.sensor.SensorModel`).

The model (NGA STDI-0002, "The Compendium of Controlled Extensions for the National Imagery
Transmission Format", appendix E, the RPC00B extension; GDAL's RPC metadata domain holds the
same numbers):

- a ground point's longitude, latitude (deg, WGS84) and ellipsoidal height (m) are normalised,
  ``L = (lon - LONG_OFF) / LONG_SCALE``, ``P = (lat - LAT_OFF) / LAT_SCALE``,
  ``H = (h - HEIGHT_OFF) / HEIGHT_SCALE`` (the longitude difference taken within +-180 deg);
- the normalised line and sample are ratios of cubic polynomials of the 20 terms
  :data:`RPC_TERMS`, in RPC00B's order ``1 L P H LP LH PH L^2 P^2 H^2 PLH L^3 LP^2 LH^2 L^2P P^3
  PH^2 L^2H P^2H H^3``: ``l = (a . t) / (b . t)``, ``s = (c . t) / (d . t)`` with ``a`` the line
  numerator, ``b`` the line denominator, ``c`` and ``d`` the sample's;
- ``line = l LINE_SCALE + LINE_OFF``, ``sample = s SAMP_SCALE + SAMP_OFF``, counted from 0 at the
  centre of the top-left pixel (as GDAL reads them): orthowarp's pixel (docs/design.md, "Pixel
  coordinates") is ``(col, row) = (sample + 0.5, line + 0.5)``.

Forward (ground -> image) is the closed form; inverse (image -> ground at a height) solves the
two normalised equations for (L, P) by Newton's method with their analytic Jacobian, damped by
step halving (:meth:`RationalSensor.locate` on the host, ``rpc_locate`` of
:mod:`orthowarp.kernels.rpc` on the device, which also meets the pixel's line of sight with a
DEM). The RPCs hold the atmosphere's effect already: an RPC image's kernels read no refraction
table.

**Bias compensation** (Grodecki & Dial 2003): RPCs from a satellite's direct georeferencing are
off by a few pixels, mostly a shift; ground control corrects them in image space,

    col' = col + dc0 + dc_col col + dc_row row,    row' = row + dr0 + dr_col col + dr_row row,

``(col, row)`` the RPC's pixel and ``(col', row')`` the compensated one: a shift
(``dc0, dr0``) or an affine map (all six, :data:`BIAS_PARAMETERS`). Grodecki and Dial write the
correction as a function of the measured image position; evaluating it at the RPC's own
position instead (as here) differs by the affine terms times the correction, ~1e-5 px, and
makes forward and inverse exact. The six terms are the sensor's adjustable
:meth:`~RationalSensor.parameters`; :func:`orthowarp.adjust.rpc.estimate_bias` estimates them
from ground control points.

References: J. Grodecki, G. Dial (2003), Block adjustment of high-resolution satellite images
described by rational polynomials, PE&RS 69(1), 59-68. C. V. Tao, Y. Hu (2001), A
comprehensive study of the rational function model for photogrammetric processing, PE&RS
67(12), 1347-1357 (the terrain-independent fit, :func:`orthowarp.adjust.rpc.fit_rpc`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from . import geodesy
from ._validate import finite
from ._validate import image_size as image_size_pair
from .errors import ParamError
from .sensor import GeocentricPositions, SensorKernels, SensorModel, generic_kernels

if TYPE_CHECKING:
    import warp as wp
    from numpy.typing import ArrayLike
    from pyproj import CRS

    from .kernels.rpc import RpcData

__all__ = ["RpcCoefficients", "RationalSensor", "RPC_TERMS", "TERM_POWERS", "BIAS_PARAMETERS", "BIAS_MODELS",
           "rpc_terms", "rpc_term_gradients", "NEWTON_TOLERANCE", "NEWTON_STEPS"]

#: The 20 terms of each RPC00B polynomial, in RPC00B's order (L: normalised longitude, P:
#: latitude, H: height).
RPC_TERMS = ("1", "L", "P", "H", "LP", "LH", "PH", "L^2", "P^2", "H^2", "PLH", "L^3", "LP^2", "LH^2", "L^2P",
             "P^3", "PH^2", "L^2H", "P^2H", "H^3")

#: Powers of (L, P, H) of each term of :data:`RPC_TERMS` (20, 3).
TERM_POWERS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [2, 0, 0],
                        [0, 2, 0], [0, 0, 2], [1, 1, 1], [3, 0, 0], [1, 2, 0], [1, 0, 2], [2, 1, 0], [0, 3, 0],
                        [0, 1, 2], [2, 0, 1], [0, 2, 1], [0, 0, 3]])

#: The image-space bias terms (:class:`RationalSensor`'s parameters): the column correction
#: dc0 + dc_col col + dc_row row and the row correction dr0 + dr_col col + dr_row row (px,
#: px per px).
BIAS_PARAMETERS = ("dc0", "dc_col", "dc_row", "dr0", "dr_col", "dr_row")

#: The bias models: the parameters each one frees (the others stay 0).
BIAS_MODELS = {"shift": ("dc0", "dr0"), "affine": BIAS_PARAMETERS}

#: The inverse's convergence: Newton stops when its step is below this in normalised ground
#: units (1e-12 of a scale of 0.1 deg is 1e-8 m), or after :data:`NEWTON_STEPS` steps.
NEWTON_TOLERANCE = 1e-12
NEWTON_STEPS = 30

# the largest affine bias term: the correction must stay a small, invertible change of the pixel
_MAX_BIAS_SLOPE = 0.1


def rpc_terms(u: ArrayLike) -> np.ndarray:
    """The 20 RPC00B terms (:data:`RPC_TERMS`) of normalised ground points.

    Parameters
    ----------
    u : array_like, shape (N, 3)
        Normalised (L, P, H).

    Returns
    -------
    ndarray, shape (N, 20)
    """
    u = np.asarray(u, dtype=np.float64)
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    one = np.ones_like(x)
    return np.stack([one, x, y, z, x * y, x * z, y * z, x * x, y * y, z * z, x * y * z, x * x * x, x * y * y,
                     x * z * z, x * x * y, y * y * y, y * z * z, x * x * z, y * y * z, z * z * z], -1)


def rpc_term_gradients(u: ArrayLike) -> np.ndarray:
    """The derivatives of the 20 terms by L, P and H.

    Parameters
    ----------
    u : array_like, shape (N, 3)
        Normalised (L, P, H).

    Returns
    -------
    ndarray, shape (N, 20, 3)
        d term / d (L, P, H).
    """
    u = np.asarray(u, dtype=np.float64)
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    o, one = np.zeros_like(x), np.ones_like(x)
    dx = [o, one, o, o, y, z, o, 2 * x, o, o, y * z, 3 * x * x, y * y, z * z, 2 * x * y, o, o, 2 * x * z, o, o]
    dy = [o, o, one, o, x, o, z, o, 2 * y, o, x * z, o, 2 * x * y, o, x * x, 3 * y * y, z * z, o, 2 * y * z, o]
    dz = [o, o, o, one, o, x, y, o, o, 2 * z, x * y, o, o, 2 * x * z, o, o, 2 * y * z, x * x, y * y, 3 * z * z]
    return np.stack([np.stack(dx, -1), np.stack(dy, -1), np.stack(dz, -1)], -1)


def _coefficients(name: str, value: ArrayLike) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be 20 numbers, got {type(value).__name__}") from e
    if arr.shape != (20,):
        raise ParamError(f"{name} must be 20 numbers (the RPC00B terms), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ParamError(f"{name} holds NaN or infinite values")
    return arr.copy()


def _number(name: str, value: Any, *, positive: bool = False, bound: float | None = None) -> float:
    v = finite(name, value)
    if positive and not v > 0:
        raise ParamError(f"{name} must be > 0, got {v!r}")
    if bound is not None and abs(v) > bound:
        raise ParamError(f"{name} must be within +-{bound:g}, got {v!r}")
    return v


class RpcCoefficients:
    """An image's RPC00B coefficients: the four polynomials and the normalisation (see the
    module doc). Immutable.

    Parameters
    ----------
    line_num, line_den, samp_num, samp_den : array_like, shape (20,)
        Numerators and denominators of the normalised line and sample, in the order of
        :data:`RPC_TERMS`.
    line_off, samp_off : float
        Image offsets (px, from 0 at the centre of the top-left pixel).
    lat_off, lon_off, height_off : float
        Ground offsets (deg, deg, m; WGS84 latitude and longitude, ellipsoidal height).
    line_scale, samp_scale : float
        Image scales (px), > 0.
    lat_scale, lon_scale, height_scale : float
        Ground scales (deg, deg, m), > 0.
    err_bias, err_rand : float, optional
        The vendor's bias and random error (m, one sigma of each horizontal axis); NaN where not
        given (informative).

    Raises
    ------
    ParamError
        A coefficient array is not 20 finite numbers, a number is not finite, a scale is not
        > 0, an offset is out of range (latitude beyond +-90 deg, longitude beyond +-360 deg),
        or a denominator's constant term is 0.
    """

    #: Attribute names of the numbers, in the order of GDAL's RPC domain.
    NUMBERS = ("line_off", "samp_off", "lat_off", "lon_off", "height_off", "line_scale", "samp_scale", "lat_scale",
               "lon_scale", "height_scale")
    #: Attribute names of the coefficient arrays.
    POLYNOMIALS = ("line_num", "line_den", "samp_num", "samp_den")

    def __init__(self, *, line_num: ArrayLike, line_den: ArrayLike, samp_num: ArrayLike, samp_den: ArrayLike,
                 line_off: float, samp_off: float, lat_off: float, lon_off: float, height_off: float,
                 line_scale: float, samp_scale: float, lat_scale: float, lon_scale: float, height_scale: float,
                 err_bias: float = math.nan, err_rand: float = math.nan) -> None:
        for name, value in (("line_num", line_num), ("line_den", line_den), ("samp_num", samp_num),
                            ("samp_den", samp_den)):
            arr = _coefficients(name, value)
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)
        bounds = {"lat_off": 90.0, "lon_off": 360.0}
        for name, value in zip(self.NUMBERS, (line_off, samp_off, lat_off, lon_off, height_off, line_scale,
                                              samp_scale, lat_scale, lon_scale, height_scale)):
            object.__setattr__(self, name, _number(name, value, positive=name.endswith("_scale"),
                                                   bound=bounds.get(name)))
        for name in ("line_den", "samp_den"):
            if getattr(self, name)[0] == 0.0:
                raise ParamError(f"{name}'s constant term is 0: the ratio is undefined at the RPCs' centre")
        for name, value in (("err_bias", err_bias), ("err_rand", err_rand)):
            try:
                v = float(value)
            except (TypeError, ValueError) as e:
                raise ParamError(f"{name} must be a number, got {value!r}") from e
            object.__setattr__(self, name, v)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("RpcCoefficients are immutable: make new ones (replace())")

    def __repr__(self) -> str:
        return (f"RpcCoefficients(lat {self.lat_off:g} +- {self.lat_scale:g}, lon {self.lon_off:g} +- "
                f"{self.lon_scale:g}, h {self.height_off:g} +- {self.height_scale:g}, line {self.line_off:g} +- "
                f"{self.line_scale:g}, sample {self.samp_off:g} +- {self.samp_scale:g})")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RpcCoefficients):
            return NotImplemented

        def same(a: float, b: float) -> bool:
            return a == b or (math.isnan(a) and math.isnan(b))

        return (all(np.array_equal(getattr(self, n), getattr(other, n)) for n in self.POLYNOMIALS)
                and all(getattr(self, n) == getattr(other, n) for n in self.NUMBERS)
                and same(self.err_bias, other.err_bias) and same(self.err_rand, other.err_rand))

    __hash__ = None  # mutable-looking arrays inside: compare, do not hash

    def as_dict(self) -> dict[str, Any]:
        """The constructor's arguments by name (coefficient arrays as lists of floats).

        Returns
        -------
        dict
        """
        out: dict[str, Any] = {n: [float(v) for v in getattr(self, n)] for n in self.POLYNOMIALS}
        out.update({n: float(getattr(self, n)) for n in self.NUMBERS})
        out.update(err_bias=float(self.err_bias), err_rand=float(self.err_rand))
        return out

    def replace(self, **changes: Any) -> RpcCoefficients:
        """These coefficients with some arguments changed (checked as in the constructor).

        Parameters
        ----------
        **changes
            Constructor arguments by name.

        Returns
        -------
        RpcCoefficients
        """
        args = self.as_dict()
        args.update(changes)
        return RpcCoefficients(**args)

    # -- normalisation -------------------------------------------------------------------------

    def normalise(self, geo: ArrayLike) -> np.ndarray:
        """Ground points (lon, lat deg, ellipsoidal h m) -> normalised (L, P, H).

        Parameters
        ----------
        geo : array_like, shape (N, 3)

        Returns
        -------
        ndarray, shape (N, 3)
            The longitude difference is taken within [-180, 180) deg.
        """
        g = np.asarray(geo, dtype=np.float64).reshape(-1, 3)
        dlon = g[:, 0] - self.lon_off
        dlon = dlon - 360.0 * np.floor((dlon + 180.0) / 360.0)
        return np.stack([dlon / self.lon_scale, (g[:, 1] - self.lat_off) / self.lat_scale,
                         (g[:, 2] - self.height_off) / self.height_scale], -1)

    def denormalise(self, u: ArrayLike) -> np.ndarray:
        """Normalised (L, P, H) -> ground points (lon, lat deg, h m): the inverse of
        :meth:`normalise` (longitudes within lon_off +- 180 deg).

        Parameters
        ----------
        u : array_like, shape (N, 3)

        Returns
        -------
        ndarray, shape (N, 3)
        """
        u = np.asarray(u, dtype=np.float64).reshape(-1, 3)
        return np.stack([u[:, 0] * self.lon_scale + self.lon_off, u[:, 1] * self.lat_scale + self.lat_off,
                         u[:, 2] * self.height_scale + self.height_off], -1)

    def image_offsets(self) -> np.ndarray:
        """(col, row) of the image offsets in orthowarp's pixel convention: (SAMP_OFF + 0.5,
        LINE_OFF + 0.5) (px)."""
        return np.array([self.samp_off + 0.5, self.line_off + 0.5])

    def image_scales(self) -> np.ndarray:
        """(SAMP_SCALE, LINE_SCALE) (px)."""
        return np.array([self.samp_scale, self.line_scale])

    # -- the polynomials -------------------------------------------------------------------------

    def ratios(self, u: ArrayLike) -> np.ndarray:
        """Normalised ground (L, P, H) -> normalised image (s, l).

        Parameters
        ----------
        u : array_like, shape (N, 3)

        Returns
        -------
        ndarray, shape (N, 2)
            (sample, line), normalised; NaN where a denominator is 0.
        """
        t = rpc_terms(u)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (t @ self.samp_num) / (t @ self.samp_den)
            ln = (t @ self.line_num) / (t @ self.line_den)
        out = np.stack([s, ln], -1)
        out[~np.isfinite(out).all(axis=1)] = np.nan
        return out

    def ratios_jacobian(self, u: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`ratios` and their derivatives by (L, P, H): d(N/D) = (N' D - N D') / D^2.

        Parameters
        ----------
        u : array_like, shape (N, 3)

        Returns
        -------
        ratios : ndarray, shape (N, 2)
        jacobian : ndarray, shape (N, 2, 3)
            d (s, l) / d (L, P, H).
        """
        t, dt = rpc_terms(u), rpc_term_gradients(u)
        rows, jac = [], []
        with np.errstate(divide="ignore", invalid="ignore"):
            for num, den in ((self.samp_num, self.samp_den), (self.line_num, self.line_den)):
                n, d = t @ num, t @ den
                dn, dd = np.einsum("nkj,k->nj", dt, num), np.einsum("nkj,k->nj", dt, den)
                rows.append(n / d)
                jac.append((dn * d[:, None] - n[:, None] * dd) / (d * d)[:, None])
        return np.stack(rows, -1), np.stack(jac, 1)

    def pixels(self, geo: ArrayLike) -> np.ndarray:
        """Ground points (lon, lat, h) -> pixels (col, row) of orthowarp's convention, without
        bias compensation.

        Parameters
        ----------
        geo : array_like, shape (N, 3)

        Returns
        -------
        ndarray, shape (N, 2)
        """
        return self.ratios(self.normalise(geo)) * self.image_scales() + self.image_offsets()


def _bias_vector(bias: Mapping[str, float] | ArrayLike | None) -> np.ndarray:
    """The six bias terms of :data:`BIAS_PARAMETERS` from a mapping (missing names 0) or six
    numbers; checked: finite, the affine part small enough to be a correction."""
    if bias is None:
        return np.zeros(6)
    if isinstance(bias, Mapping):
        unknown = [k for k in bias if k not in BIAS_PARAMETERS]
        if unknown:
            raise ParamError(f"unknown bias term(s) {unknown}; known: {list(BIAS_PARAMETERS)}")
        vec = np.array([_number(n, bias.get(n, 0.0)) for n in BIAS_PARAMETERS])
    else:
        try:
            vec = np.asarray(bias, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as e:
            raise ParamError(f"bias must be 6 numbers {BIAS_PARAMETERS} or a mapping of them, got {bias!r}") from e
        if vec.shape != (6,) or not np.all(np.isfinite(vec)):
            raise ParamError(f"bias must be 6 finite numbers {BIAS_PARAMETERS}, got {bias!r}")
    slopes = vec[[1, 2, 4, 5]]
    if np.any(np.abs(slopes) > _MAX_BIAS_SLOPE):
        raise ParamError(f"the bias's affine terms (dc_col, dc_row, dr_col, dr_row) must be within "
                         f"+-{_MAX_BIAS_SLOPE:g} px per px (a correction, not a new geometry), got {slopes.tolist()}")
    return vec


class RationalSensor(SensorModel):
    """A satellite image described by RPC00B coefficients, with an optional bias compensation
    in image space (see the module doc): a :class:`~orthowarp.sensor.SensorModel`.

    Parameters
    ----------
    rpc : RpcCoefficients
        The image's coefficients.
    image_size : (int, int)
        (width, height) of the image (px): RPCs do not carry it.
    bias : mapping or array_like, shape (6,), optional
        The bias compensation, :data:`BIAS_PARAMETERS` by name (missing ones 0) or in that
        order: ``dc0, dr0`` in px, the affine terms in px per px (each within +-0.1). Default:
        none.
    source : str, optional
        Where the RPCs come from (informative, for messages).

    Raises
    ------
    ParamError
        ``rpc`` is not :class:`RpcCoefficients`, a bad image size or bias.

    Notes
    -----
    Geo triples are (lon, lat deg, ellipsoidal height m), the object frame ECEF
    (:attr:`geocentric`). An RPC image has no sensor position or pose: :attr:`pose` is None
    (the layers above ask it where a frame would give its single pose), and
    :meth:`reference_height` is nominal. Refraction is in the RPCs: the kernels read no
    refraction table. :meth:`parameters` are the six bias terms.
    """

    kind = "rpc"
    noun = "image"
    forward_method = False
    line_timed = False
    orthorectified = False
    #: An RPC image has no pose (no projection centre, no attitude).
    pose = None
    geocentric = True
    positions = GeocentricPositions()
    #: The height :meth:`reference_height` gives (m): a satellite's.
    NOMINAL_HEIGHT = 700e3

    def __init__(self, rpc: RpcCoefficients, image_size: tuple[int, int], *,
                 bias: Mapping[str, float] | ArrayLike | None = None, source: str | None = None) -> None:
        if not isinstance(rpc, RpcCoefficients):
            raise ParamError(f"rpc must be RpcCoefficients, got {type(rpc).__name__}")
        w, h = image_size_pair(image_size)
        self.rpc, self.source = rpc, source
        self._size = (w, h)
        self.bias = _bias_vector(bias)
        self.bias.flags.writeable = False
        a = np.array([[1.0 + self.bias[1], self.bias[2]], [self.bias[4], 1.0 + self.bias[5]]])
        self._bias_matrix, self._bias_inverse = a, np.linalg.inv(a)
        self._bias_shift = self.bias[[0, 3]]

    def __repr__(self) -> str:
        bias = "" if not np.any(self.bias) else ", bias " + ", ".join(
            f"{n}={v:.4g}" for n, v in zip(BIAS_PARAMETERS, self.bias) if v)
        return f"RationalSensor({self._size[0]} x {self._size[1]}, {self.rpc!r}{bias})"

    image_size = property(lambda self: self._size, doc="(width, height) in pixels.")

    @property
    def frame_crs(self) -> CRS:
        """EPSG:4979: geo triples are lon, lat (deg), ellipsoidal height (m)."""
        from ._validate import as_crs

        return as_crs("EPSG:4979")

    def reference_height(self) -> float:
        """:data:`NOMINAL_HEIGHT`: RPCs name no sensor position, and the height only tops the
        refraction table, which an RPC image's kernels do not read (m)."""
        return self.NOMINAL_HEIGHT

    @property
    def kernels(self) -> SensorKernels:
        """The generic kernels (:func:`orthowarp.sensor.generic_kernels`)."""
        return generic_kernels()

    def _pack(self, device: wp.Device) -> RpcData:
        import warp as wp

        from .kernels.rpc import RpcData, vec20d

        r, arg = self.rpc, RpcData()
        arg.line_num, arg.line_den = vec20d(*r.line_num), vec20d(*r.line_den)
        arg.samp_num, arg.samp_den = vec20d(*r.samp_num), vec20d(*r.samp_den)
        arg.ground_off = wp.vec3d(r.lon_off, r.lat_off, r.height_off)
        arg.ground_scale = wp.vec3d(r.lon_scale, r.lat_scale, r.height_scale)
        arg.image_off = wp.vec2d(*r.image_offsets())
        arg.image_scale = wp.vec2d(*r.image_scales())
        arg.bias_shift = wp.vec2d(*self._bias_shift)
        arg.bias_matrix = wp.mat22d(*self._bias_matrix.ravel())
        arg.bias_inverse = wp.mat22d(*self._bias_inverse.ravel())
        return arg

    # -- host model ------------------------------------------------------------------------------

    def _compensate(self, raw: np.ndarray) -> np.ndarray:
        """RPC pixels (N, 2) -> compensated pixels."""
        return raw @ self._bias_matrix.T + self._bias_shift

    def _uncompensate(self, pix: np.ndarray) -> np.ndarray:
        """Compensated pixels (N, 2) -> the RPC's own pixels."""
        return (pix - self._bias_shift) @ self._bias_inverse.T

    def project_geo(self, geo: ArrayLike) -> np.ndarray:
        """Ground points (lon, lat deg, ellipsoidal h m) -> pixels (col, row), the bias
        compensation applied.

        Parameters
        ----------
        geo : array_like, shape (N, 3) or (3,)

        Returns
        -------
        ndarray, shape (N, 2)
            Pixel (col, row), float64; NaN rows for rows with NaN and where a denominator
            vanishes.
        """
        from ._validate import points

        return self._compensate(self.rpc.pixels(points(geo, 3, "geo")))

    def project(self, xyz: ArrayLike) -> np.ndarray:
        """ECEF points (N, 3) -> pixels (N, 2), float64 (see :meth:`project_geo`).

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)
            ECEF points (m).

        Returns
        -------
        ndarray, shape (N, 2)
            Pixel (col, row).
        """
        from ._validate import points

        lat, lon, h = geodesy.ecef_to_geodetic(points(xyz, 3, "xyz"))
        return self.project_geo(np.stack([lon, lat, h], -1))

    def project_geo_jacobian(self, geo: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`project_geo`, the RPC's own pixels, and the derivatives by the ground point.

        Parameters
        ----------
        geo : array_like, shape (N, 3)
            (lon, lat deg, ellipsoidal h m).

        Returns
        -------
        pixels : ndarray, shape (N, 2)
            Compensated (col, row).
        raw : ndarray, shape (N, 2)
            The RPC's (col, row), before the compensation.
        d_geo : ndarray, shape (N, 2, 3)
            d (col, row) / d (lon, lat, h): px per deg, deg, m.
        """
        from ._validate import points

        r = self.rpc
        g = points(geo, 3, "geo")
        ratios, jac = r.ratios_jacobian(r.normalise(g))
        raw = ratios * r.image_scales() + r.image_offsets()
        scale = r.image_scales()[:, None] / np.array([r.lon_scale, r.lat_scale, r.height_scale])[None, :]
        d_geo = np.einsum("ij,njk->nik", self._bias_matrix, jac * scale[None])
        return self._compensate(raw), raw, d_geo

    def project_jacobian(self, xyz: ArrayLike, *, wrt: tuple[str, ...] | None = None) -> tuple[np.ndarray, ...]:
        """:meth:`project` and its analytic derivatives.

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)
            ECEF points (m).
        wrt : tuple of str, optional
            Names from :data:`BIAS_PARAMETERS` (length q; default all six), in the order of
            ``d_params``' columns.

        Returns
        -------
        pixels : ndarray, shape (N, 2)
            Pixel (col, row), as :meth:`project`.
        d_params : ndarray, shape (N, 2, q)
            By the named bias terms (px per px for dc0, dr0; px per px per px for the others:
            the RPC's own column or row).
        d_point : ndarray, shape (N, 2, 3)
            By the ECEF point (px per m).
        """
        from ._validate import points

        wrt = BIAS_PARAMETERS if wrt is None else tuple(wrt)
        self._check_names(wrt)
        pts = points(xyz, 3, "xyz")
        lat, lon, h = geodesy.ecef_to_geodetic(pts)
        pix, raw, d_geo = self.project_geo_jacobian(np.stack([lon, lat, h], -1))
        # d(lon, lat, h) / d(X, Y, Z): the rows of the inverse of d ECEF / d(lon, lat, h), whose
        # columns (east, north, up, scaled) are orthogonal
        phi, lam = np.radians(lat), np.radians(lon)
        sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
        w = np.sqrt(1.0 - geodesy.WGS84_E2 * sp * sp)
        n = geodesy.WGS84_A / w
        m = n * (1.0 - geodesy.WGS84_E2) / (w * w)
        zero = np.zeros_like(sp)
        d_lon = np.stack([-sl, cl, zero], -1) / ((n + h) * cp)[:, None] * (180.0 / np.pi)
        d_lat = np.stack([-sp * cl, -sp * sl, cp], -1) / (m + h)[:, None] * (180.0 / np.pi)
        d_h = np.stack([cp * cl, cp * sl, sp], -1)
        d_point = np.einsum("nij,njk->nik", d_geo, np.stack([d_lon, d_lat, d_h], 1))
        d_params = np.empty((len(pts), 2, len(wrt)))
        for k, name in enumerate(wrt):
            axis = 0 if name.startswith("dc") else 1
            by = {"0": np.ones(len(pts)), "_col": raw[:, 0], "_row": raw[:, 1]}[name[2:]]
            d_params[:, :, k] = 0.0
            d_params[:, axis, k] = by
        bad = ~np.all(np.isfinite(pix), axis=1)
        d_params[bad] = np.nan
        d_point[bad] = np.nan
        return pix, d_params, d_point

    def locate(self, pixels: ArrayLike, h: ArrayLike, *, tol: float = NEWTON_TOLERANCE,
               max_iter: int = NEWTON_STEPS) -> np.ndarray:
        """Pixels -> ground points at ellipsoidal heights h: the inverse of :meth:`project_geo`
        by damped Newton in float64 NumPy (the kernels' reference).

        The two normalised equations s(L, P, H) = s*, l(L, P, H) = l* are solved for (L, P)
        from the RPCs' centre with the analytic Jacobian; a step that does not lower the
        residual is halved (up to 12 times).

        Parameters
        ----------
        pixels : array_like, shape (N, 2)
            (col, row), compensated (as :meth:`project_geo` gives them).
        h : float or array_like, shape (N,)
            Ellipsoidal heights (m).
        tol : float, optional
            Convergence: a step below this in normalised units.
        max_iter : int, optional
            Most Newton steps.

        Returns
        -------
        ndarray, shape (N, 3)
            (lon, lat deg, h m); NaN rows where it did not converge.
        """
        from ._validate import points

        pix = points(pixels, 2, "pixels")
        n = len(pix)
        hh = np.broadcast_to(np.asarray(h, dtype=np.float64), (n,)).copy()
        r = self.rpc
        target = (self._uncompensate(pix) - r.image_offsets()) / r.image_scales()
        z = (hh - r.height_off) / r.height_scale
        u = np.zeros((n, 2))
        done = ~(np.all(np.isfinite(target), axis=1) & np.isfinite(z))
        ok = np.zeros(n, bool)

        def residual(uu: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            rat, jac = r.ratios_jacobian(np.column_stack([uu, z[idx]]))
            return rat - target[idx], jac[:, :, :2]

        for _ in range(max_iter):
            idx = np.flatnonzero(~done)
            if not len(idx):
                break
            f, j = residual(u[idx], idx)
            with np.errstate(divide="ignore", invalid="ignore"):
                det = j[:, 0, 0] * j[:, 1, 1] - j[:, 0, 1] * j[:, 1, 0]
                step = np.stack([j[:, 1, 1] * f[:, 0] - j[:, 0, 1] * f[:, 1],
                                 j[:, 0, 0] * f[:, 1] - j[:, 1, 0] * f[:, 0]], -1) / det[:, None]
            bad = ~np.all(np.isfinite(step), axis=1)
            done[idx[bad]] = True
            idx, f, step = idx[~bad], f[~bad], step[~bad]
            conv = np.max(np.abs(step), axis=1) < tol
            u[idx[conv]] -= step[conv]
            ok[idx[conv]] = done[idx[conv]] = True
            idx, f, step = idx[~conv], f[~conv], step[~conv]
            norm0 = np.max(np.abs(f), axis=1)
            t = np.ones(len(idx))
            for _ in range(12):  # halve steps that do not lower the residual
                trial = u[idx] - t[:, None] * step
                fn, _ = residual(trial, idx)
                worse = ~(np.max(np.abs(fn), axis=1) < norm0)
                if not worse.any():
                    break
                t[worse] *= 0.5
            u[idx] -= t[:, None] * step
        lonlat = r.denormalise(np.column_stack([u, z]))[:, :2]
        out = np.column_stack([lonlat, hh])
        out[~ok] = np.nan
        return out

    # -- parameters -------------------------------------------------------------------------------

    def parameters(self) -> dict[str, float]:
        """The six bias terms by name (:data:`BIAS_PARAMETERS`; px and px per px).

        Returns
        -------
        dict of str to float
        """
        return dict(zip(BIAS_PARAMETERS, map(float, self.bias)))

    def with_parameters(self, **values: float) -> RationalSensor:
        """This sensor with the named bias terms changed.

        Parameters
        ----------
        **values : float
            New values by name (:data:`BIAS_PARAMETERS`).

        Returns
        -------
        RationalSensor
            A new sensor; this one is unchanged.

        Raises
        ------
        ParamError
            An unknown name, or a value the constructor refuses.
        """
        self._check_names(values)
        p = self.parameters()
        p.update({k: float(v) for k, v in values.items()})
        return self.with_bias(p)

    def with_bias(self, bias: Mapping[str, float] | ArrayLike | None) -> RationalSensor:
        """This image's RPCs with another bias compensation (None: none).

        Parameters
        ----------
        bias : mapping or array_like, shape (6,), or None
            As for the constructor.

        Returns
        -------
        RationalSensor
        """
        return RationalSensor(self.rpc, self._size, bias=bias, source=self.source)
