"""Pushbroom (SPOT level-1A) sensor model, device code: the float64 twin of
:class:`orthowarp.PushbroomScene` (see its module for the model and the conventions).

- :func:`pb_ray`: pixel -> satellite position and unit look direction (ECEF).
- :func:`pb_geolocate`: pixel -> ground through the frame kernels' relief search
  (:func:`orthowarp.kernels.ray.geolocate_ray`) with a pose built at the line's position.
- :func:`pb_project`: ground (ECEF) -> pixel: secant iteration on the line time until the
  apparent direction lies in the detector line's plane (the along-track look angle of the
  detector the across-track angle points at), then the column from the look-angle table.

The scene's kernels are the sensor-generic ones of :mod:`orthowarp.kernels.sensor`
(:class:`PushbroomData` is the scene's argument there); :func:`pb_project_kernel` takes first
guesses of the line times (for benchmarks).
"""

import warp as wp

from .dem import DemData
from .ray import MODE_GEOCENTRIC, FramePoseData, SearchParams, apparent_direction, geolocate_ray
from .geodesy import ecef_to_geodetic_sc
from .refraction import RefractionTable

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})


@wp.struct
class PushbroomData:
    """A scene packed for kernels: ephemeris (times s, ECEF positions m, velocities m/s),
    attitudes (times s; yaw, pitch, roll rad), look angles per detector (psi_x, psi_y rad),
    line period (s), DIMAP centre line, first_order (1: [P1]'s eq. 4 attitude matrix),
    and the extrapolation (s) allowed past the attitudes.

    line_p, line_r: the satellite position and the rotation R = [X2 Y2 Z2] M of the rows
    line_row0, line_row0 + 1, ... (the scene's line centres and a margin), computed by the
    rigorous model on the host; between them P and R are linear in the row (errors ~ a dt^2 / 8
    = 6e-7 m and 1e-12 rad at SPOT's line period), outside them the rigorous model runs here.
    det_u: the unit look vector u1 of every detector, likewise linear between detectors.
    poly, use_poly: [P1]'s 27 coefficients (position, velocity, attitude as 2nd-degree
    polynomials in t; entry 3 q + k holds the power-k coefficients of quantity q), used instead
    of the ephemeris and attitude samples when use_poly is 1."""

    eph_t: wp.array(dtype=wp.float64)
    eph_p: wp.array(dtype=wp.vec3d)
    eph_v: wp.array(dtype=wp.vec3d)
    att_t: wp.array(dtype=wp.float64)
    att: wp.array(dtype=wp.vec3d)
    psi: wp.array(dtype=wp.vec2d)
    line_period: wp.float64
    center_line: wp.float64
    first_order: wp.int32
    att_extra: wp.float64
    line_p: wp.array(dtype=wp.vec3d)
    line_r: wp.array(dtype=wp.mat33d)
    line_row0: wp.float64
    det_u: wp.array(dtype=wp.vec3d)
    poly: wp.array(dtype=wp.vec3d)
    use_poly: wp.int32


@wp.func
def pb_line_time(pb: PushbroomData, row: wp.float64):
    """Seconds from the scene-centre time of the (continuous) row coordinate."""
    return (row + wp.float64(0.5) - pb.center_line) * pb.line_period


@wp.func
def pb_line_row(pb: PushbroomData, t: wp.float64):
    """The row coordinate of line time t (the inverse of :func:`pb_line_time`)."""
    return t / pb.line_period + pb.center_line - wp.float64(0.5)


@wp.func
def pb_time_ok(pb: PushbroomData, t: wp.float64):
    n = pb.eph_t.shape[0]
    m = pb.att_t.shape[0]
    return (t >= pb.eph_t[0] and t <= pb.eph_t[n - 1] and t >= pb.att_t[0] - pb.att_extra
            and t <= pb.att_t[m - 1] + pb.att_extra)


@wp.func
def search_sorted(a: wp.array(dtype=wp.float64), t: wp.float64):
    """Index of the first element >= t (binary search)."""
    lo = wp.int32(0)
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] < t:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.func
def pb_poly(pb: PushbroomData, q: wp.int32, t: wp.float64):
    return pb.poly[3 * q] + t * pb.poly[3 * q + 1] + (t * t) * pb.poly[3 * q + 2]


@wp.func
def pb_lagrange(pb: PushbroomData, values: wp.array(dtype=wp.vec3d), t: wp.float64):
    """8-point Lagrange interpolation of ephemeris samples (positions or velocities) at t."""
    n = pb.eph_t.shape[0]
    i0 = wp.clamp(search_sorted(pb.eph_t, t) - 4, 0, n - 8)
    out = wp.vec3d()
    for j in range(8):
        w = wp.float64(1.0)
        tj = pb.eph_t[i0 + j]
        for k in range(8):
            if k != j:
                tk = pb.eph_t[i0 + k]
                w = w * (t - tk) / (tj - tk)
        out = out + w * values[i0 + j]
    return out


@wp.func
def pb_orbit_position(pb: PushbroomData, t: wp.float64):
    """Satellite position at t: the ephemeris interpolated, or the polynomial."""
    if pb.use_poly != 0:
        return pb_poly(pb, 0, t)
    return pb_lagrange(pb, pb.eph_p, t)


@wp.func
def pb_orbit_velocity(pb: PushbroomData, t: wp.float64):
    """Satellite velocity at t: the ephemeris interpolated, or the polynomial."""
    if pb.use_poly != 0:
        return pb_poly(pb, 1, t)
    return pb_lagrange(pb, pb.eph_v, t)


@wp.func
def pb_attitude_matrix(pb: PushbroomData, t: wp.float64):
    """M = Mp Mr My at t (yaw, pitch, roll linear in time), or its first-order form."""
    m = pb.att_t.shape[0]
    i = wp.clamp(search_sorted(pb.att_t, t) - 1, 0, m - 2)
    w = (t - pb.att_t[i]) / (pb.att_t[i + 1] - pb.att_t[i])
    a = (wp.float64(1.0) - w) * pb.att[i] + w * pb.att[i + 1]
    if pb.use_poly != 0:
        a = pb_poly(pb, 2, t)
    y = a[0]
    p = a[1]
    r = a[2]
    one = wp.float64(1.0)
    if pb.first_order != 0:
        return wp.mat33d(one, -y, -r, y, one, p, r, -p, one)
    cy = wp.cos(y)
    sy = wp.sin(y)
    cp = wp.cos(p)
    sp = wp.sin(p)
    cr = wp.cos(r)
    sr = wp.sin(r)
    return wp.mat33d(cr * cy, -cr * sy, -sr,
                     cp * sy + sp * sr * cy, cp * cy - sp * sr * sy, sp * cr,
                     -sp * sy + cp * sr * cy, -sp * cy - cp * sr * sy, cp * cr)


@wp.func
def pb_frame(pb: PushbroomData, t: wp.float64, p: wp.vec3d):
    """R = [X2 Y2 Z2] M at t: navigation (instrument) frame -> ECEF."""
    v = pb_orbit_velocity(pb, t)
    z2 = wp.normalize(p)
    x2 = wp.normalize(wp.cross(v, z2))
    y2 = wp.cross(z2, x2)
    orb = wp.mat33d(x2[0], y2[0], z2[0], x2[1], y2[1], z2[1], x2[2], y2[2], z2[2])
    return orb * pb_attitude_matrix(pb, t)


@wp.func
def pb_state(pb: PushbroomData, row: wp.float64, strict: bool):
    """Satellite position and R = [X2 Y2 Z2] M at a (continuous) row, from the line table where
    it covers the row, else from the rigorous model; with ``strict``, NaN outside the
    ephemeris/attitude span (else the attitudes extrapolate freely: the backward iteration may
    pass there on its way)."""
    n = pb.line_p.shape[0]
    f = row - pb.line_row0
    if n > 1 and f >= wp.float64(0.0) and f <= wp.float64(n - 1):
        k = wp.min(wp.int32(f), n - 2)
        a = f - wp.float64(k)
        b = wp.float64(1.0) - a
        return b * pb.line_p[k] + a * pb.line_p[k + 1], b * pb.line_r[k] + a * pb.line_r[k + 1]
    t = pb_line_time(pb, row)
    nan = wp.float64(wp.nan)
    if strict and not pb_time_ok(pb, t):
        return wp.vec3d(nan, nan, nan), wp.mat33d()
    p = pb_orbit_position(pb, t)
    return p, pb_frame(pb, t, p)


@wp.func
def pb_look(pb: PushbroomData, col: wp.float64):
    """Unit look vector u1 of a continuous column (linear between detectors, extended past the
    ends; the table of u1 makes it free of tangents)."""
    n = pb.det_u.shape[0]
    if n == 1:
        return pb.det_u[0]
    f = col - wp.float64(0.5)
    i = wp.clamp(wp.int32(wp.floor(f)), 0, n - 2)
    a = f - wp.float64(i)
    return wp.normalize((wp.float64(1.0) - a) * pb.det_u[i] + a * pb.det_u[i + 1])


@wp.func
def pb_psi(pb: PushbroomData, col: wp.float64):
    """(psi_x, psi_y) of a continuous column: linear in the detector number col + 0.5,
    extended linearly past the first and last detectors."""
    n = pb.psi.shape[0]
    if n == 1:
        return pb.psi[0]
    f = col - wp.float64(0.5)  # 0-based detector index
    i = wp.clamp(wp.int32(wp.floor(f)), 0, n - 2)
    a = f - wp.float64(i)
    return (wp.float64(1.0) - a) * pb.psi[i] + a * pb.psi[i + 1]


@wp.func
def pb_ray(pb: PushbroomData, pix: wp.vec2d):
    """Satellite position and unit look direction (ECEF) of pixel (col, row); NaN outside
    the ephemeris or attitude span."""
    p, r = pb_state(pb, pix[1], True)
    if not wp.isfinite(p[0]):
        return p, p
    return p, wp.normalize(r * pb_look(pb, pix[0]))


@wp.func
def pb_pose(p: wp.vec3d):
    """A geocentric frame pose at the satellite position, for the relief search."""
    pose = FramePoseData()
    pose.mode = MODE_GEOCENTRIC
    pose.center = p
    g, slat, clat, r = ecef_to_geodetic_sc(p)
    pose.up = wp.vec3d(clat * p[0] / r, clat * p[1] / r, slat)
    pose.height = g[2]
    pose.rot = wp.identity(3, dtype=wp.float64)
    return pose


@wp.func
def pb_geolocate(pb: PushbroomData, refr: RefractionTable, dem: DemData, search: SearchParams, pix: wp.vec2d):
    """Pixel -> geo triple (lon, lat deg, h m) of its first ground point; NaN if none."""
    p, d = pb_ray(pb, pix)
    nan = wp.float64(wp.nan)
    if not wp.isfinite(p[0]):
        return wp.vec3d(nan, nan, nan)
    return geolocate_ray(pb_pose(p), refr, dem, search, d)


@wp.func
def pb_column(pb: PushbroomData, tan_psi_y: wp.float64):
    """Continuous column whose detector has this tan(psi_y) (psi_y monotonic in the detector
    number), and that detector's tan(psi_x)."""
    n = pb.psi.shape[0]
    target = wp.atan(tan_psi_y)
    first = pb.psi[0][1]
    last = pb.psi[n - 1][1]
    sgn = wp.float64(1.0)
    if last < first:
        sgn = wp.float64(-1.0)
    lo = wp.int32(0)
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if sgn * (pb.psi[mid][1] - target) <= wp.float64(0.0):
            lo = mid
        else:
            hi = mid
    a = (target - pb.psi[lo][1]) / (pb.psi[hi][1] - pb.psi[lo][1])
    col = wp.float64(lo) + a + wp.float64(0.5)
    psi = pb_psi(pb, col)
    return col, wp.tan(psi[0])


@wp.func
def pb_residual(pb: PushbroomData, refr: RefractionTable, x: wp.vec3d, h: wp.float64, t: wp.float64):
    """(tan psi_x of the apparent direction - tan psi_x of its detector, column) at time t."""
    p, r = pb_state(pb, pb_line_row(pb, t), False)
    nan = wp.float64(wp.nan)
    if not wp.isfinite(p[0]):
        return nan, nan
    q = wp.transpose(r) * apparent_direction(refr, pb_pose(p).up, x - p, h)
    if q[2] >= wp.float64(0.0):
        return nan, nan
    col, tx = pb_column(pb, q[0] / q[2])
    return q[1] / -q[2] - tx, col


@wp.func
def pb_project(pb: PushbroomData, refr: RefractionTable, x: wp.vec3d, h: wp.float64, t0: wp.float64):
    """ECEF point x at ellipsoidal height h -> pixel (col, row), by secant iteration on the
    line time from t0 (s); NaN if it does not converge within the ephemeris span."""
    nan = wp.float64(wp.nan)
    ta = t0
    tb = t0 + wp.float64(100.0) * pb.line_period
    fa, ca = pb_residual(pb, refr, x, h, ta)
    fb, cb = pb_residual(pb, refr, x, h, tb)
    tol = wp.float64(1.0e-6) * pb.line_period
    for _ in range(40):
        if not (wp.isfinite(fa) and wp.isfinite(fb)) or fb == fa:
            break
        tc = tb - fb * (tb - ta) / (fb - fa)
        n = pb.eph_t.shape[0]
        tc = wp.clamp(tc, pb.eph_t[0], pb.eph_t[n - 1])
        ta = tb
        fa = fb
        tb = tc
        fb, cb = pb_residual(pb, refr, x, h, tb)
        if wp.abs(tb - ta) < tol:
            if not pb_time_ok(pb, tb):
                return wp.vec2d(nan, nan)
            return wp.vec2d(cb, pb_line_row(pb, tb))
    return wp.vec2d(nan, nan)


@wp.kernel
def pb_project_kernel(
    pb: PushbroomData,
    refr: RefractionTable,
    xyz: wp.array(dtype=wp.vec3d),
    heights: wp.array(dtype=wp.float64),
    t0: wp.array(dtype=wp.float64),
    out: wp.array(dtype=wp.vec2d),
):
    """ECEF points (N,) at ellipsoidal heights (N,), first line-time guesses (N,) -> pixels."""
    i = wp.tid()
    out[i] = pb_project(pb, refr, xyz[i], heights[i], t0[i])

