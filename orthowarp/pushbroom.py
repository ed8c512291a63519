"""Rigorous pushbroom model of SPOT level-1A scenes ([P1]; docs/design.md, "Pushbroom").

Float64 NumPy on the host: the reference the kernels are checked against, and the place where
the exterior orientation is fitted as polynomials in line time.

Pixel (col, row) (GDAL convention, centre of the top-left pixel at (0.5, 0.5)) ->
line time ``t = (row + 0.5 - center_line) * line_period`` (s from the scene-centre time; DIMAP
line L is at row L - 0.5) and detector ``col + 0.5`` (1-based, fractional: look angles are
interpolated linearly between detectors) ->

- satellite position P and velocity V (ECEF) by 8-point Lagrange interpolation of the
  ephemeris;
- yaw, pitch, roll linearly interpolated in time;
- orbital frame ``Z2 = P/|P|, X2 = (V x Z2)/|V x Z2|, Y2 = Z2 x X2``;
- attitude ``M = Mp Mr My`` (SPOT geometry handbook eq. 11), or [P1]'s first-order form;
- look vector ``u1 = normalize(-tan psi_y, tan psi_x, -1)``;
- ray ``P + s [X2 Y2 Z2] M u1`` intersected with the ellipsoid (or the DEM).

Reference: SPOT Image, "SPOT Satellite Geometry Handbook", S-NT-73-12-SI, 2002.
"""

from __future__ import annotations

import math
import operator
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import GeometryError, ParamError
from .geodesy import WGS84_A, WGS84_B, ecef_to_geodetic
from .sensor import GeocentricPositions, SensorKernels, SensorModel, generic_kernels

if TYPE_CHECKING:  # annotations only: Warp is imported where a scene is packed for a device
    import warp as wp
    from numpy.typing import ArrayLike
    from pyproj import CRS

    from .kernels.pushbroom import PushbroomData

__all__ = ["PushbroomScene", "POLYNOMIAL_PARAMETERS", "attitude_matrix", "lagrange", "MAX_LINES", "MAX_DETECTORS", "MIN_LINE_PERIOD",
           "MAX_LINE_PERIOD"]

ATTITUDE_MODELS = ("full", "first_order")

#: Most lines a scene may have. The kernels' line table holds a position and a rotation (96
#: bytes) for every line and 256 lines each side, built on the host at about 360 bytes a line
#: at its peak: 2**20 lines need about 0.1 GB on the device and 0.4 GB on the host. A SPOT-5
#: level-1A scene has 12 000 to 24 000 lines, an HRS strip about 120 000.
MAX_LINES = 1 << 20

#: Most detectors (columns) a scene may have (a look vector of 24 bytes each on the device, the
#: look angles on the host); SPOT-5 has 12 000 (24 000 in supermode).
MAX_DETECTORS = 1 << 20

#: Range of the line period (s). SPOT-5 HRG/HRS take 0.75 ms per line, SPOT 1-4 1.5 ms; the
#: bounds leave two to three orders of magnitude either way. A shorter period makes the
#: line-time iteration's tolerance (1e-6 lines) fall below float64's resolution of the times.
MIN_LINE_PERIOD = 1e-6
MAX_LINE_PERIOD = 1.0


def _count(name: str, value: Any, bound: int, what: str) -> int:
    """A whole number in 1..bound, or ParamError saying what is wrong (never truncated)."""
    if isinstance(value, (bool, np.bool_)):
        raise ParamError(f"{name} must be a whole number, got {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        try:
            f = float(value)
        except (TypeError, ValueError) as e:
            raise ParamError(f"{name} must be a whole number, got {value!r}") from e
        if not math.isfinite(f) or f != int(f):
            raise ParamError(f"{name} must be a whole number, got {value!r}") from None
        v = int(f)
    if v < 1:
        raise ParamError(f"{name} must be positive, got {v}")
    if v > bound:
        raise ParamError(f"{name} {v} is over the limit of {bound} {what} (orthowarp.pushbroom.MAX_{what.upper()})")
    return v


def check_line_period(value: Any, name: str = "line_period") -> float:
    """``value`` (s) as a float if finite and within [MIN_LINE_PERIOD, MAX_LINE_PERIOD], else
    ParamError saying so.

    Parameters
    ----------
    value : float
        A line period (s).
    name : str, optional
        The argument's name, for the message.

    Returns
    -------
    float
        The line period (s).

    Raises
    ------
    ParamError
        Not a number, not finite, or outside [:data:`MIN_LINE_PERIOD`, :data:`MAX_LINE_PERIOD`].
    """
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be a number of seconds, got {value!r}") from e
    if not (math.isfinite(v) and MIN_LINE_PERIOD <= v <= MAX_LINE_PERIOD):
        raise ParamError(f"{name} must be within [{MIN_LINE_PERIOD:g}, {MAX_LINE_PERIOD:g}] s "
                         f"(SPOT-5: 0.00075 s), got {value!r}")
    return v


def _array(name: str, value: ArrayLike, shape: tuple[int | None, ...]) -> np.ndarray:
    """A finite float64 array of the given shape (None: any length), or ParamError naming it."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be numbers, got {type(value).__name__}") from e
    if arr.ndim != len(shape) or any(n is not None and n != k for n, k in zip(shape, arr.shape)):
        want = " x ".join("n" if n is None else str(n) for n in shape)
        raise ParamError(f"{name} must have shape ({want}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ParamError(f"{name} holds NaN or infinite values")
    return arr


def _poly(c: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Evaluate (3, 3) [axis][power] coefficients at times t (n,) -> (n, 3)."""
    return c[None, :, 0] + t[:, None] * c[None, :, 1] + (t * t)[:, None] * c[None, :, 2]


def lagrange(t: ArrayLike, times: np.ndarray, values: np.ndarray, order: int = 8) -> np.ndarray:
    """Lagrange interpolation with the ``order`` samples around each time.

    Parameters
    ----------
    t : array_like, shape (n,) or scalar
        Times (s), within ``times``' span.
    times : ndarray, shape (m,)
        Sample times (s), increasing, m >= ``order``.
    values : ndarray, shape (m, k)
        Samples (any unit) at ``times``.
    order : int, optional
        Samples per interpolation (the polynomial's degree plus one).

    Returns
    -------
    ndarray, shape (n, k)
        Interpolated values, in the unit of ``values``.
    """
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    m = len(times)
    i0 = np.clip(np.searchsorted(times, t) - order // 2, 0, m - order)
    idx = i0[:, None] + np.arange(order)  # (n, order)
    tt = times[idx]
    out = np.zeros((len(t), values.shape[1]))
    for j in range(order):
        w = np.ones(len(t))
        for k in range(order):
            if k != j:
                w *= (t - tt[:, k]) / (tt[:, j] - tt[:, k])
        out += w[:, None] * values[idx[:, j]]
    return out


def attitude_matrix(yaw: ArrayLike, pitch: ArrayLike, roll: ArrayLike, *, first_order: bool = False) -> np.ndarray:
    """M = Mp Mr My (handbook eq. 11) for arrays of angles (rad) -> (n, 3, 3).

    With ``first_order``, the handbook's linearisation (angles to first order), which is what
    [P1]'s eq. 4 stands for: with the roll and pitch signs the DIMAP angles need (the rows
    above, the full matrix's first-order terms). [P1]'s eq. 4 as printed, fed the DIMAP
    angles, moves ground points by ~1.9 km at the SPOT-5 sample scene; the seed's text says to
    negate roll and pitch, which gives this form.

    Parameters
    ----------
    yaw, pitch, roll : array_like, shape (n,) or scalar
        Attitude angles (rad), as the DIMAP metadata give them.
    first_order : bool, optional
        The linearised matrix instead of the full product.

    Returns
    -------
    ndarray, shape (n, 3, 3)
        M, mapping navigation-frame look vectors to the orbital frame (dimensionless).
    """
    y, p, r = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (yaw, pitch, roll))
    if first_order:
        one, zero = np.ones_like(y), np.zeros_like(y)
        rows = [[one, -y, -r], [y, one, p], [r, -p, one]]
        return np.stack([np.stack(row, -1) for row in rows], -2) + zero[:, None, None]
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    rows = [[cr * cy, -cr * sy, -sr],
            [cp * sy + sp * sr * cy, cp * cy - sp * sr * sy, sp * cr],
            [-sp * sy + cp * sr * cy, -sp * cy - cp * sr * sy, cp * cr]]
    return np.stack([np.stack(row, -1) for row in rows], -2)


def ellipsoid_distance(p: np.ndarray, d: np.ndarray, h: float | np.ndarray) -> np.ndarray:
    """Distance (m) along unit rays (p, d) (n, 3) to the ellipsoid of semi-axes a + h, b + h;
    NaN where a ray misses.

    Parameters
    ----------
    p : ndarray, shape (n, 3)
        Ray origins, ECEF (m), outside the ellipsoid.
    d : ndarray, shape (n, 3)
        Unit ray directions, ECEF.
    h : float or ndarray, shape (n,)
        Height (m) added to both semi-axes of WGS84.

    Returns
    -------
    ndarray, shape (n,)
        Distance (m) from ``p`` to the first intersection; NaN where the ray misses or points
        away.
    """
    ia, ib = 1.0 / (WGS84_A + h), 1.0 / (WGS84_B + h)
    scale = np.stack(np.broadcast_arrays(ia, ia, ib), -1)
    cs, ds = p * scale, d * scale
    qa = np.sum(ds * ds, -1)
    qb = np.sum(cs * ds, -1)
    qc = np.sum(cs * cs, -1) - 1.0
    disc = qb * qb - qa * qc
    ok = (qc > 0) & (qb < 0) & (disc >= 0)
    with np.errstate(invalid="ignore"):
        return np.where(ok, qc / (np.sqrt(np.where(ok, disc, 0.0)) - qb), np.nan)


# Names of the 27 exterior-orientation coefficients (PushbroomScene.parameters):
# quantity_axis_power, [quantity][axis][power] of ``polynomials``.
_QUANTITIES = (("position", "xyz"), ("velocity", "xyz"), ("attitude", ("yaw", "pitch", "roll")))
POLYNOMIAL_PARAMETERS = tuple(f"{q}_{a}_{k}" for q, axes in _QUANTITIES for a in axes for k in range(3))


class PushbroomScene(SensorModel):
    """A pushbroom scene's rigorous sensor model (see the module doc): a
    :class:`~orthowarp.sensor.SensorModel`.

    Parameters
    ----------
    width, height : int
        Detectors per line and lines.
    line_period : float
        Seconds per line.
    center_line : float
        DIMAP line (1-based, pixel centre) imaged at t = 0.
    eph_time : array_like, shape (n,), n >= 8
        Ephemeris times (s from the scene-centre time).
    eph_position, eph_velocity : array_like, shape (n, 3)
        ECEF (m, m/s).
    att_time : array_like, shape (m,), m >= 2
    att_angles : array_like, shape (m, 3)
        Yaw, pitch, roll (rad).
    psi_x, psi_y : array_like, shape (width,)
        Look angles (rad) of every detector.
    attitude_model : {"full", "first_order"}, optional
        "full": the attitude matrix of the three angles (handbook eq. 11); "first_order": its
        linearisation ([P1]'s eq. 4 with roll and pitch signed as the DIMAP angles need;
        see :func:`attitude_matrix`).
    epoch : numpy.datetime64, optional
        UTC of t = 0 (informative).
    attitude_extrapolation : float, optional
        Seconds the attitudes may be extrapolated past their first/last sample (default 0.5:
        level-1A files start the attitudes a few lines after the first line).
    source : str, optional
        The metadata file the scene comes from (informative, for messages).
    polynomials : array_like, shape (3, 3, 3), optional
        [P1]'s exterior orientation as 2nd-degree polynomials in line time t (s):
        ``[quantity][axis][power]`` for quantity position (m), velocity (m/s), attitude (yaw,
        pitch, roll, rad): 27 coefficients that replace the ephemeris interpolation and the
        attitude samples when given (see :meth:`fit_polynomials`). They are the scene's
        :meth:`parameters` (named as :data:`POLYNOMIAL_PARAMETERS`: ``position_x_0`` ..
        ``attitude_roll_2``; units m, m/s, rad per s to the power). (No adjustment of them
        exists yet: [P1]'s Gauss-Helmert bundle adjustment of these groups is planned work.)

    Raises
    ------
    ParamError
        An argument is missing its shape, not finite or out of range (sizes over
        :data:`MAX_DETECTORS` / :data:`MAX_LINES`, a line period outside
        [:data:`MIN_LINE_PERIOD`, :data:`MAX_LINE_PERIOD`], fewer than 8 ephemeris points or 2
        attitudes, times not increasing, an unknown attitude model).
    GeometryError
        The scene's line times fall outside its ephemeris or its attitudes (beyond
        ``attitude_extrapolation``).
    """

    kind = "pushbroom"
    noun = "scene"
    forward_method = False
    line_timed = True
    orthorectified = False

    def __init__(self, *, width: int, height: int, line_period: float, center_line: float, eph_time: ArrayLike,
                 eph_position: ArrayLike, eph_velocity: ArrayLike, att_time: ArrayLike, att_angles: ArrayLike,
                 psi_x: ArrayLike, psi_y: ArrayLike, attitude_model: str = "full", epoch: Any = None,
                 attitude_extrapolation: float = 0.5, source: str | None = None,
                 polynomials: ArrayLike | None = None) -> None:
        if attitude_model not in ATTITUDE_MODELS:
            raise ParamError(f"attitude_model must be one of {ATTITUDE_MODELS}, got {attitude_model!r}")
        # sizes first: every array below is allocated from them
        self.width = _count("width", width, MAX_DETECTORS, "detectors")
        self.height = _count("height", height, MAX_LINES, "lines")
        self.line_period = check_line_period(line_period)
        self.center_line = float(center_line)
        if not math.isfinite(self.center_line):
            raise ParamError(f"center_line must be finite, got {center_line!r}")
        self.eph_time = _array("eph_time", eph_time, (None,))
        self.eph_position = _array("eph_position", eph_position, (len(self.eph_time), 3))
        self.eph_velocity = _array("eph_velocity", eph_velocity, (len(self.eph_time), 3))
        self.att_time = _array("att_time", att_time, (None,))
        self.att_angles = _array("att_angles", att_angles, (len(self.att_time), 3))
        self.psi_x = _array("psi_x", psi_x, (self.width,))
        self.psi_y = _array("psi_y", psi_y, (self.width,))
        if len(self.eph_time) < 8 or np.any(np.diff(self.eph_time) <= 0):
            raise ParamError("the ephemeris needs at least 8 points at increasing times")
        if len(self.att_time) < 2 or np.any(np.diff(self.att_time) <= 0):
            raise ParamError("the attitudes need at least 2 samples at increasing times")
        self.attitude_model = attitude_model
        self.epoch = epoch
        self.attitude_extrapolation = float(attitude_extrapolation)
        self.source = source
        self.polynomials = None if polynomials is None else _array("polynomials", polynomials, (3, 3, 3))
        t = self.line_time(np.array([0.0, float(self.height)]))
        where = f" of '{source}'" if source else ""
        e = self.attitude_extrapolation
        if t[0] < self.eph_time[0] or t[1] > self.eph_time[-1]:
            raise GeometryError(f"The scene's line times{where} ({t[0]:.3f}..{t[1]:.3f} s from its centre) fall "
                                f"outside its ephemeris ({self.eph_time[0]:.3f}..{self.eph_time[-1]:.3f} s)")
        if t[0] < self.att_time[0] - e or t[1] > self.att_time[-1] + e:
            raise GeometryError(f"The scene's line times{where} ({t[0]:.3f}..{t[1]:.3f} s from its centre) fall "
                                f"outside its attitudes ({self.att_time[0]:.3f}..{self.att_time[-1]:.3f} s)")

    @classmethod
    def from_metadata(cls, m: Any, *, attitude_model: str = "full") -> PushbroomScene:
        """The scene of parsed level-1A metadata (a
        :class:`~orthowarp.pipeline.formats.dimap.DimapMetadata`; files are read by
        :func:`orthowarp.read_scene`).

        Parameters
        ----------
        m : DimapMetadata
            Any object with the attributes ``ncols``, ``nrows``, ``line_period``,
            ``center_line``, ``eph_time``, ``eph_position``, ``eph_velocity``, ``att_time``,
            ``att_angles``, ``psi_x``, ``psi_y``, ``epoch`` and ``path`` (units as the
            constructor's arguments).
        attitude_model : {"full", "first_order"}, optional
            As for the constructor.

        Returns
        -------
        PushbroomScene
        """
        return cls(width=m.ncols, height=m.nrows, line_period=m.line_period, center_line=m.center_line,
                   eph_time=m.eph_time, eph_position=m.eph_position, eph_velocity=m.eph_velocity,
                   att_time=m.att_time, att_angles=m.att_angles, psi_x=m.psi_x, psi_y=m.psi_y,
                   attitude_model=attitude_model, epoch=m.epoch, source=m.path)

    def __repr__(self) -> str:
        return (f"PushbroomScene({self.width} x {self.height}, line period {self.line_period:.6g} s, "
                f"{len(self.eph_time)} ephemeris points, {len(self.att_time)} attitudes, {self.attitude_model})")

    # -- the model, float64 ------------------------------------------------------------------

    # -- sensor-model protocol (orthowarp.sensor.SensorModel) ---------------------------------
    image_size = property(lambda self: (self.width, self.height), doc="(width, height) in pixels.")
    geocentric = True
    positions = GeocentricPositions()

    @property
    def frame_crs(self) -> CRS:
        """EPSG:4979: geo triples are lon, lat (deg), ellipsoidal height (m)."""
        from ._validate import as_crs

        return as_crs("EPSG:4979")

    def reference_height(self) -> float:
        """The satellite's mean ellipsoidal height over the scene (m): :meth:`mean_height`."""
        return self.mean_height()

    @property
    def kernels(self) -> SensorKernels:
        """The generic kernels (:func:`orthowarp.sensor.generic_kernels`)."""
        return generic_kernels()

    def _pack(self, device: wp.Device) -> PushbroomData:
        return self.to_struct(device)

    def project(self, xyz: ArrayLike) -> np.ndarray:
        """ECEF points (N, 3) -> pixels (N, 2), float64, without refraction (see
        :meth:`project_ecef`).

        Parameters
        ----------
        xyz : array_like, shape (N, 3)
            ECEF points (m).

        Returns
        -------
        ndarray, shape (N, 2)
            Pixel (col, row); NaN rows where the line-time iteration does not converge.
        """
        return self.project_ecef(xyz)

    def parameters(self) -> dict[str, float]:
        """The 27 exterior-orientation coefficients by name (:data:`POLYNOMIAL_PARAMETERS`).

        Returns
        -------
        dict of str to float
            ``position_x_0`` .. ``attitude_roll_2``: m, m/s and rad per second to the power.

        Raises
        ------
        ParamError
            The scene's orientation is its ephemeris and attitude samples, not polynomials:
            ``scene.with_polynomials(scene.fit_polynomials()[0])`` gives the scene that has them.
        """
        if self.polynomials is None:
            raise ParamError("this scene's orientation is its ephemeris and attitude samples, not polynomials: "
                             "scene.with_polynomials(scene.fit_polynomials()[0]) gives the scene that has them")
        return dict(zip(POLYNOMIAL_PARAMETERS, map(float, self.polynomials.ravel())))

    def with_parameters(self, **values: float) -> PushbroomScene:
        """This scene with the named polynomial coefficients changed.

        Parameters
        ----------
        **values : float
            New values by name (:data:`POLYNOMIAL_PARAMETERS`, in their units).

        Returns
        -------
        PushbroomScene
            A new scene; this one is unchanged.

        Raises
        ------
        ParamError
            An unknown name, or a scene without polynomials (see :meth:`parameters`).
        """
        self._check_names(values)
        poly = self.polynomials.copy()
        for name, v in values.items():
            poly.flat[POLYNOMIAL_PARAMETERS.index(name)] = float(v)
        return self.with_polynomials(poly)

    def project_jacobian(self, xyz: ArrayLike, *, wrt: tuple[str, ...] | None = None) -> tuple[np.ndarray, ...]:
        """:meth:`project` and its derivatives by the coefficients named in ``wrt`` (default
        all 27; per unit of each) and by the ECEF point (pixels per m).

        Central differences of the float64 projection (steps: 0.5 m for the point; 1 m,
        1 mm/s and 0.1 microradian over the scene's half duration to the power for the
        coefficients), the line-time iteration converged to 1e-9 lines.

        Parameters
        ----------
        xyz : array_like, shape (N, 3)
            ECEF points (m).
        wrt : tuple of str, optional
            Names from :data:`POLYNOMIAL_PARAMETERS` (length q), in the order of ``d_params``'
            columns.

        Returns
        -------
        pixels : ndarray, shape (N, 2)
            Pixel (col, row), as :meth:`project`.
        d_params : ndarray, shape (N, 2, q)
            By the named coefficients (pixels per unit of each).
        d_point : ndarray, shape (N, 2, 3)
            By the ECEF point (pixels per m).

        Raises
        ------
        ParamError
            The scene has no polynomials (see :meth:`parameters`) and ``wrt`` names some.
        """
        xyz = _array("xyz", xyz, (None, 3))
        wrt = POLYNOMIAL_PARAMETERS if wrt is None else tuple(wrt)
        params = self.parameters() if wrt else {}
        self._check_names(wrt)
        t_half = 0.5 * self.height * self.line_period
        pix = self.project_ecef(xyz, tol=1e-9)
        j_point = np.empty((len(xyz), 2, 3))
        for a in range(3):
            dx = np.zeros(3)
            dx[a] = 0.5
            j_point[:, :, a] = self.project_ecef(xyz + dx, tol=1e-9) - self.project_ecef(xyz - dx, tol=1e-9)  # / 1 m
        base = {"position": 1.0, "velocity": 1e-3, "attitude": 1e-7}
        out = np.empty((len(xyz), 2, len(wrt)))
        for k, name in enumerate(wrt):
            quantity, _, power = name.rsplit("_", 2)
            power = int(power)
            h = base[quantity] / t_half**power
            hi = self.with_parameters(**{name: params[name] + h}).project_ecef(xyz, tol=1e-9)
            lo = self.with_parameters(**{name: params[name] - h}).project_ecef(xyz, tol=1e-9)
            out[:, :, k] = (hi - lo) / (2 * h)
        return pix, out, j_point

    def line_time(self, row: ArrayLike) -> np.ndarray:
        """Seconds from the scene-centre time of the (continuous) row coordinate.

        Parameters
        ----------
        row : array_like
            Row coordinates (pixels, top edge of the image at 0).

        Returns
        -------
        ndarray, shape of ``row``
            Line times t (s from the scene-centre time).
        """
        return (np.asarray(row, dtype=np.float64) + 0.5 - self.center_line) * self.line_period

    def line_row(self, t: ArrayLike) -> np.ndarray:
        """The (continuous) row coordinate of line time ``t`` (s from the scene-centre time):
        the inverse of :meth:`line_time`.

        Parameters
        ----------
        t : array_like
            Line times (s from the scene-centre time).

        Returns
        -------
        ndarray, shape of ``t``
            Row coordinates (pixels).
        """
        return np.asarray(t, dtype=np.float64) / self.line_period + self.center_line - 0.5

    def _check_times(self, t: np.ndarray) -> None:
        if np.any((t < self.eph_time[0]) | (t > self.eph_time[-1])):
            raise GeometryError(f"line times {t.min():.3f}..{t.max():.3f} s fall outside the ephemeris "
                                f"({self.eph_time[0]:.3f}..{self.eph_time[-1]:.3f} s)")
        e = self.attitude_extrapolation
        if np.any((t < self.att_time[0] - e) | (t > self.att_time[-1] + e)):
            raise GeometryError(f"line times {t.min():.3f}..{t.max():.3f} s fall outside the attitudes "
                                f"({self.att_time[0]:.3f}..{self.att_time[-1]:.3f} s, +-{e} s)")

    def orbit(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Position and velocity (n, 3) (ECEF, m and m/s) at times t (s).

        Parameters
        ----------
        t : array_like, shape (n,) or scalar
            Line times (s from the scene-centre time).

        Returns
        -------
        position : ndarray, shape (n, 3)
            ECEF (m).
        velocity : ndarray, shape (n, 3)
            ECEF (m/s).

        Raises
        ------
        GeometryError
            A time falls outside the ephemeris or the attitudes (beyond
            ``attitude_extrapolation``).
        """
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        self._check_times(t)
        if self.polynomials is not None:
            return _poly(self.polynomials[0], t), _poly(self.polynomials[1], t)
        return lagrange(t, self.eph_time, self.eph_position), lagrange(t, self.eph_time, self.eph_velocity)

    def attitude(self, t: ArrayLike) -> np.ndarray:
        """Yaw, pitch, roll (n, 3) (rad), linear in time (extrapolated past the ends).

        Parameters
        ----------
        t : array_like, shape (n,) or scalar
            Line times (s from the scene-centre time).

        Returns
        -------
        ndarray, shape (n, 3)
            Yaw, pitch, roll (rad).
        """
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        if self.polynomials is not None:
            return _poly(self.polynomials[2], t)
        tt, a = self.att_time, self.att_angles
        i = np.clip(np.searchsorted(tt, t) - 1, 0, len(tt) - 2)
        w = ((t - tt[i]) / (tt[i + 1] - tt[i]))[:, None]
        return (1 - w) * a[i] + w * a[i + 1]

    def look_vector(self, col: ArrayLike) -> np.ndarray:
        """Unit look vectors u1 (n, 3) of (continuous) column coordinates, navigation frame.

        Parameters
        ----------
        col : array_like, shape (n,)
            Column coordinates (pixels; detector number ``col + 0.5``).

        Returns
        -------
        ndarray, shape (n, 3)
            ``normalize(-tan psi_y, tan psi_x, -1)``.
        """
        det = np.asarray(col, dtype=np.float64) + 0.5  # 1-based detector number
        px, py = self._psi_at(self.psi_x, det), self._psi_at(self.psi_y, det)
        u = np.stack([-np.tan(py), np.tan(px), -np.ones_like(px)], -1)
        return u / np.linalg.norm(u, axis=-1, keepdims=True)

    def orbital_frame(self, p: ArrayLike, v: ArrayLike) -> np.ndarray:
        """Columns X2, Y2, Z2 of the orbital frame at positions/velocities (n, 3) -> (n, 3, 3).

        Parameters
        ----------
        p : array_like, shape (n, 3)
            Satellite positions, ECEF (m).
        v : array_like, shape (n, 3)
            Satellite velocities, ECEF (m/s).

        Returns
        -------
        ndarray, shape (n, 3, 3)
            Unit columns ``Z2 = P/|P|``, ``X2 = (V x Z2)/|V x Z2|``, ``Y2 = Z2 x X2`` (as
            [X2 Y2 Z2]).
        """
        z2 = p / np.linalg.norm(p, axis=-1, keepdims=True)
        x2 = np.cross(v, z2)
        x2 /= np.linalg.norm(x2, axis=-1, keepdims=True)
        y2 = np.cross(z2, x2)
        return np.stack([x2, y2, z2], -1)

    def rays(self, pixels: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Satellite positions and unit look directions (ECEF) of pixels (n, 2) (col, row).

        Parameters
        ----------
        pixels : array_like, shape (n, 2)
            Pixel (col, row).

        Returns
        -------
        positions : ndarray, shape (n, 3)
            Satellite positions at the pixels' line times, ECEF (m).
        directions : ndarray, shape (n, 3)
            Unit look directions, ECEF.
        """
        pixels = _array("pixels", pixels, (None, 2))
        t = self.line_time(pixels[:, 1])
        p, v = self.orbit(t)
        ypr = self.attitude(t)
        m = attitude_matrix(ypr[:, 0], ypr[:, 1], ypr[:, 2], first_order=self.attitude_model == "first_order")
        u = self.look_vector(pixels[:, 0])
        d = np.einsum("nij,nj->ni", self.orbital_frame(p, v), np.einsum("nij,nj->ni", m, u))
        return p, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def geolocate_ellipsoid(self, pixels: ArrayLike, h: float = 0.0) -> np.ndarray:
        """Ground points (n, 3) (lon, lat in degrees, h in m) of pixels (n, 2) on the surface
        of ellipsoidal height h: the closed form on the ellipsoid of semi-axes a + h, b + h,
        then a Newton correction along the ray to the exact geodetic height.

        Parameters
        ----------
        pixels : array_like, shape (n, 2)
            Pixel (col, row).
        h : float or array_like, shape (n,), optional
            Ellipsoidal height (m) of the surface.

        Returns
        -------
        ndarray, shape (n, 3)
            Longitude, latitude (deg) and ellipsoidal height (m); NaN rows for rays that miss.
        """
        p, d = self.rays(pixels)
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), (len(p),))
        s = ellipsoid_distance(p, d, h)
        for _ in range(3):
            lat, lon, hh = ecef_to_geodetic(p + s[:, None] * d)
            # d(height)/ds = d . n (n: the ellipsoid normal there)
            n = np.stack([np.cos(np.radians(lat)) * np.cos(np.radians(lon)),
                          np.cos(np.radians(lat)) * np.sin(np.radians(lon)), np.sin(np.radians(lat))], -1)
            s = s - (hh - h) / np.sum(d * n, -1)
        lat, lon, hh = ecef_to_geodetic(p + s[:, None] * d)
        return np.stack([lon, lat, hh], -1)

    # -- packing and the backward reference --------------------------------------------------

    def to_struct(self, device: wp.DeviceLike) -> PushbroomData:
        """Pack into :class:`orthowarp.kernels.pushbroom.PushbroomData` on a Warp device.

        Parameters
        ----------
        device : str or warp.context.Device
            Where the struct's arrays (ephemeris, attitudes, look vectors, line table) go.

        Returns
        -------
        PushbroomData
            The Warp struct the kernels read.
        """
        import warp as wp

        from .kernels.pushbroom import PushbroomData

        s = PushbroomData()
        s.eph_t = wp.array(self.eph_time, dtype=wp.float64, device=device)
        s.eph_p = wp.array(self.eph_position, dtype=wp.vec3d, device=device)
        s.eph_v = wp.array(self.eph_velocity, dtype=wp.vec3d, device=device)
        s.att_t = wp.array(self.att_time, dtype=wp.float64, device=device)
        s.att = wp.array(self.att_angles, dtype=wp.vec3d, device=device)
        s.psi = wp.array(np.stack([self.psi_x, self.psi_y], -1), dtype=wp.vec2d, device=device)
        s.line_period = self.line_period
        s.center_line = self.center_line
        s.first_order = int(self.attitude_model == "first_order")
        s.att_extra = self.attitude_extrapolation
        poly = np.zeros((3, 3, 3)) if self.polynomials is None else self.polynomials
        # [quantity * 3 + power] -> vec3 over the axes
        s.poly = wp.array(np.ascontiguousarray(poly.transpose(0, 2, 1).reshape(9, 3)), dtype=wp.vec3d, device=device)
        s.use_poly = int(self.polynomials is not None)
        p, r, row0 = self.line_table()
        s.line_p = wp.array(p, dtype=wp.vec3d, device=device)
        s.line_r = wp.array(r, dtype=wp.mat33d, device=device)
        s.line_row0 = row0
        s.det_u = wp.array(self.look_vector(np.arange(self.width) + 0.5), dtype=wp.vec3d, device=device)
        return s

    def line_table(self, margin: int = 256) -> tuple[np.ndarray, np.ndarray, float]:
        """Satellite positions (n, 3) and rotations R = [X2 Y2 Z2] M (n, 3, 3) at the line
        centres of the scene and ``margin`` lines each side, as far as the ephemeris and the
        attitudes reach, and the row coordinate of the first (see the kernels' PushbroomData).

        Parameters
        ----------
        margin : int, optional
            Lines tabulated beyond each end of the scene.

        Returns
        -------
        positions : ndarray, shape (n, 3)
            ECEF (m); shape (0, 3) when fewer than two lines are covered.
        rotations : ndarray, shape (n, 3, 3)
            Navigation frame -> ECEF.
        row0 : float
            Row coordinate of the first line (its centre).
        """
        rows = np.arange(-margin, self.height + margin) + 0.5
        t = self.line_time(rows)
        e = self.attitude_extrapolation
        ok = ((t >= self.eph_time[0]) & (t <= self.eph_time[-1]) & (t >= self.att_time[0] - e)
              & (t <= self.att_time[-1] + e))
        idx = np.flatnonzero(ok)
        if len(idx) < 2:
            return np.zeros((0, 3)), np.zeros((0, 3, 3)), 0.0
        rows, t = rows[idx[0]:idx[-1] + 1], t[idx[0]:idx[-1] + 1]
        p, v = self.orbit(t)
        ypr = self.attitude(t)
        m = attitude_matrix(ypr[:, 0], ypr[:, 1], ypr[:, 2], first_order=self.attitude_model == "first_order")
        return p, self.orbital_frame(p, v) @ m, float(rows[0])

    def _psi_at(self, values: np.ndarray, det: ArrayLike) -> np.ndarray:
        """A look angle (psi_x or psi_y, (width,)) at fractional 1-based detector numbers:
        linear between detectors, and extended linearly past the first and last (as the
        kernels do)."""
        det = np.asarray(det, dtype=np.float64)
        if self.width == 1:
            return np.full_like(det, values[0])
        i = np.clip(np.floor(det).astype(int) - 1, 0, self.width - 2)
        a = det - (i + 1)
        return (1 - a) * values[i] + a * values[i + 1]

    def fit_polynomials(self, *, samples: int = 201) -> tuple[np.ndarray, dict[str, float]]:
        """Fit [P1]'s 27 coefficients: position, velocity and attitude as 2nd-degree
        polynomials in line time, by least squares over the scene's lines (the metadata's
        interpolated orbit and attitudes, ``samples`` lines evenly spread).

        Parameters
        ----------
        samples : int, optional
            Lines sampled, evenly from the first line's top to the last line's bottom.

        Returns
        -------
        coefficients : ndarray, shape (3, 3, 3)
            [position | velocity | attitude][axis][power of t].
        rms : dict of str to float
            Fit residual RMS of position (m), velocity (m/s) and attitude (rad).
        """
        t = self.line_time(np.linspace(0.0, self.height, samples))
        p, v = self.orbit(t)
        a = self.attitude(t)
        design = np.stack([np.ones_like(t), t, t * t], 1)
        coef, rms = np.zeros((3, 3, 3)), {}
        for q, (name, y) in enumerate((("position", p), ("velocity", v), ("attitude", a))):
            c, *_ = np.linalg.lstsq(design, y, rcond=None)
            coef[q] = c.T
            rms[name] = float(np.sqrt(np.mean((design @ c - y) ** 2)))
        return coef, rms

    def replace(self, **changes: Any) -> PushbroomScene:
        """This scene with some of its constructor arguments changed (checked as in the
        constructor).

        Parameters
        ----------
        **changes
            Constructor arguments by name.

        Returns
        -------
        PushbroomScene
            A new scene; this one is unchanged.
        """
        args = dict(width=self.width, height=self.height, line_period=self.line_period, center_line=self.center_line,
                    eph_time=self.eph_time, eph_position=self.eph_position, eph_velocity=self.eph_velocity,
                    att_time=self.att_time, att_angles=self.att_angles, psi_x=self.psi_x, psi_y=self.psi_y,
                    attitude_model=self.attitude_model, epoch=self.epoch,
                    attitude_extrapolation=self.attitude_extrapolation, source=self.source,
                    polynomials=self.polynomials)
        args.update(changes)
        return PushbroomScene(**args)

    def with_polynomials(self, coefficients: ArrayLike) -> PushbroomScene:
        """This scene with its exterior orientation given by 27 polynomial coefficients.

        Parameters
        ----------
        coefficients : array_like, shape (3, 3, 3)
            [position | velocity | attitude][axis][power of t] (m, m/s, rad; per second to the
            power), as :meth:`fit_polynomials` returns them.

        Returns
        -------
        PushbroomScene
        """
        return self.replace(polynomials=coefficients)

    def mean_height(self) -> float:
        """Mean ellipsoidal height (m) of the satellite over the scene (9 lines evenly spread).

        Returns
        -------
        float
            m.
        """
        t = self.line_time(np.linspace(0, self.height, 9))
        p, _ = self.orbit(t)
        return float(np.mean(ecef_to_geodetic(p)[2]))

    def _orbit_any(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position and velocity without the span check (the iteration may pass outside)."""
        if self.polynomials is not None:
            return _poly(self.polynomials[0], t), _poly(self.polynomials[1], t)
        return lagrange(t, self.eph_time, self.eph_position), lagrange(t, self.eph_time, self.eph_velocity)

    def project_ecef(self, xyz: ArrayLike, *, t0: ArrayLike | None = None, tol: float = 1e-6,
                     max_iter: int = 40) -> np.ndarray:
        """Ground points (n, 3) (ECEF, m) -> pixels (n, 2), without refraction: the secant
        iteration of the kernels in float64 NumPy (the reference they are checked against).

        The line time t solves tan psi_x(q(t)) = tan psi_x(column(q(t))) where q(t) is the
        direction to the point in the instrument frame at t; ``tol`` is in lines.

        Parameters
        ----------
        xyz : array_like, shape (n, 3)
            ECEF points (m).
        t0 : array_like, shape (n,), optional
            First guesses of the line times (s; default 0, the scene centre).
        tol : float, optional
            Convergence tolerance (lines).
        max_iter : int, optional
            Most secant steps.

        Returns
        -------
        ndarray, shape (n, 2)
            Pixel (col, row); NaN rows where the iteration did not converge.
        """
        xyz = _array("xyz", xyz, (None, 3))
        n = len(xyz)
        ids = np.arange(1, self.width + 1, dtype=np.float64)
        order = np.argsort(self.psi_y)

        def residual(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            ok = (t >= self.eph_time[0]) & (t <= self.eph_time[-1])
            tt = np.where(ok, t, 0.0)
            p, v = self._orbit_any(tt)
            ypr = self.attitude(tt)
            r = self.orbital_frame(p, v) @ attitude_matrix(*ypr.T, first_order=self.attitude_model == "first_order")
            d = xyz - p
            q = np.einsum("nji,nj->ni", r, d / np.linalg.norm(d, axis=1, keepdims=True))
            psi_y = np.arctan(q[:, 0] / q[:, 2])
            det = np.interp(psi_y, self.psi_y[order], ids[order])
            # linear extension beyond the end detectors
            for end in (0, -1):
                sel = (psi_y - self.psi_y[end]) * np.sign(self.psi_y[-1] - self.psi_y[0]) * (1 if end else -1) > 0
                if np.any(sel) and self.width > 1:
                    nb = 1 if end == 0 else -2
                    det[sel] = ids[end] + (psi_y[sel] - self.psi_y[end]) * (ids[nb] - ids[end]) / (
                        self.psi_y[nb] - self.psi_y[end])
            px = self._psi_at(self.psi_x, det)
            f = q[:, 1] / -q[:, 2] - np.tan(px)
            return np.where(ok & (q[:, 2] < 0), f, np.nan), det - 0.5

        ta = np.zeros(n) if t0 is None else np.asarray(t0, dtype=np.float64).copy()
        tb = ta + 100 * self.line_period
        fa, _ = residual(ta)
        fb, col = residual(tb)
        done = np.zeros(n, bool)
        for _ in range(max_iter):
            with np.errstate(invalid="ignore", divide="ignore"):
                tc = tb - fb * (tb - ta) / (fb - fa)
            tc = np.where(done, tb, np.clip(tc, self.eph_time[0], self.eph_time[-1]))
            ta, fa = tb, fb
            tb = tc
            fb, col = residual(tb)
            done |= np.abs(tb - ta) < tol * self.line_period
            if done.all():
                break
        row = self.line_row(tb)
        return np.where(done[:, None], np.stack([col, row], -1), np.nan)


GM = 3.986004418e14  # m^3/s^2, WGS84
OMEGA_E = 7.292115e-5  # rad/s, WGS84


def synthetic_scene(*, width: int = 12000, height: int = 12000, gsd: float = 5.0, altitude: float = 832e3,
                    view_angle: float = 0.0, lat: float = 44.0, lon: float = 5.0, inclination: float = 98.7,
                    yaw: float = 1.0e-3, pitch: float = -5.0e-4, smile: float = 1.0e-4) -> PushbroomScene:
    """A SPOT-like scene with known geometry, for tests and benchmarks.

    A circular orbit (``altitude`` above the equatorial radius, ``inclination`` deg) whose
    sub-satellite point at t = 0 is (``lat``, ``lon``), in ECEF with the Earth's rotation;
    ephemeris every 10 s, attitudes every 0.125 s (roll = ``view_angle`` deg across the track,
    small constant yaw and pitch plus a slow drift); a linear array of ``width`` detectors of
    ``gsd`` m at nadir, its along-track look angle bent by ``smile`` rad at the ends; the line
    period gives ``gsd`` m along the track.

    Parameters
    ----------
    width, height : int, optional
        Detectors per line and lines.
    gsd : float, optional
        Ground sample distance at nadir (m), across and along the track.
    altitude : float, optional
        Orbit radius less the equatorial radius (m).
    view_angle : float, optional
        Roll across the track (deg).
    lat, lon : float, optional
        Sub-satellite point at t = 0 (deg).
    inclination : float, optional
        Orbit inclination (deg).
    yaw, pitch : float, optional
        Constant attitude offsets (rad), plus a drift of 2e-6 rad/s.
    smile : float, optional
        Along-track look angle (rad) of the end detectors (quadratic across the array).

    Returns
    -------
    PushbroomScene
    """
    r = WGS84_A + float(altitude)
    n = np.sqrt(GM / r**3)
    inc, lat0, lon0 = np.radians([inclination, lat, lon])
    u0 = np.arcsin(np.sin(lat0) / np.sin(inc))
    raan = lon0 - np.arctan2(np.cos(inc) * np.sin(u0), np.cos(u0))
    e1 = np.array([np.cos(raan), np.sin(raan), 0.0])
    e2 = np.array([-np.sin(raan) * np.cos(inc), np.cos(raan) * np.cos(inc), np.sin(inc)])
    ground_speed = n * r * WGS84_A / r - OMEGA_E * WGS84_A * np.cos(lat0) * np.cos(inc)
    line_period = gsd / ground_speed
    half = 0.5 * height * line_period
    t_eph = np.arange(-np.ceil((half + 40) / 10) * 10, half + 50, 10.0)

    def state(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = u0 + n * t
        p_in = r * (np.cos(u)[:, None] * e1 + np.sin(u)[:, None] * e2)
        v_in = r * n * (-np.sin(u)[:, None] * e1 + np.cos(u)[:, None] * e2)
        c, s = np.cos(OMEGA_E * t), np.sin(OMEGA_E * t)
        rot = np.stack([np.stack([c, s, 0 * c], -1), np.stack([-s, c, 0 * c], -1),
                        np.stack([0 * c, 0 * c, 1 + 0 * c], -1)], -2)  # Rz(-omega t)
        p = np.einsum("nij,nj->ni", rot, p_in)
        v = np.einsum("nij,nj->ni", rot, v_in) - np.cross([0.0, 0.0, OMEGA_E], p)
        return p, v

    p, v = state(t_eph)
    t_att = np.arange(-half - 1.0, half + 1.125, 0.125)
    drift = 2e-6 * t_att
    att = np.stack([yaw + drift, pitch - drift, np.radians(view_angle) + 0.5 * drift], -1)
    ifov = gsd / float(altitude)
    k = np.arange(width) - 0.5 * (width - 1)
    psi_y = np.arctan(k * ifov)
    psi_x = smile * (k / max(0.5 * (width - 1), 1)) ** 2
    return PushbroomScene(width=width, height=height, line_period=line_period, center_line=0.5 * height + 0.5,
                          eph_time=t_eph, eph_position=p, eph_velocity=v, att_time=t_att, att_angles=att,
                          psi_x=psi_x, psi_y=psi_y)
