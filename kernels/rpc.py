"""Rational polynomial (RPC00B) sensor model, device code: the float64 twin of
:class:`orthowarp.RationalSensor` (see :mod:`orthowarp.rpc` for the model, the term order and
the pixel convention).

- :func:`rpc_pixel`: ground (lon, lat deg, ellipsoidal h m) -> pixel (col, row), the bias
  compensation applied (the forward closed form);
- :func:`rpc_locate`: pixel -> (lon, lat) at a height: Newton's method on the two normalised
  equations with the polynomials' analytic Jacobian, a step that does not lower the residual
  halved (damped), from a given start;
- :func:`rpc_geolocate`: pixel -> the first ground point of its line of sight on the DEM. The
  line of sight is the curve of :func:`rpc_locate` over the height; it is marched from the
  DEM's highest height down in steps of at most one DEM cell, every step solved exactly (warm
  started from the last), until the gap DEM - height changes sign, and the bracket refined by
  the Illinois variant of regula falsi to ``search.htol``, as
  :func:`orthowarp.kernels.ray.geolocate_ray` does for straight rays.

The RPCs hold the atmosphere's effect: the refraction table the generic kernels pass is not
read. :class:`RpcData` is the sensor's argument of the generic kernels
(:mod:`orthowarp.kernels.sensor`) and of the ortho's per-pixel chain
(:func:`orthowarp.kernels.ortho.source_pixel`).
"""

import warp as wp

from .dem import DemData, dem_grid, dem_sample_grid
from .geodesy import RAD2DEG, ecef_to_geodetic
from .ray import SearchParams

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

#: 20 float64: one RPC00B polynomial's coefficients, or its terms at a point.
vec20d = wp.types.vector(length=20, dtype=wp.float64)

RPC_TOL = wp.constant(wp.float64(1.0e-12))  # Newton's step tolerance, normalised units (orthowarp.rpc.NEWTON_TOLERANCE)
RPC_STEPS = wp.constant(30)  # most Newton steps (orthowarp.rpc.NEWTON_STEPS)
RPC_HALVINGS = wp.constant(12)  # most halvings of one Newton step


@wp.struct
class RpcData:
    """An image's RPCs packed for kernels: the four polynomials (RPC00B term order), the
    ground offsets and scales (lon deg, lat deg, h m), the image offsets in orthowarp's pixel
    convention (SAMP_OFF + 0.5, LINE_OFF + 0.5) and scales (px), and the bias compensation
    pixel' = bias_matrix pixel + bias_shift with its inverse."""

    line_num: vec20d
    line_den: vec20d
    samp_num: vec20d
    samp_den: vec20d
    ground_off: wp.vec3d
    ground_scale: wp.vec3d
    image_off: wp.vec2d
    image_scale: wp.vec2d
    bias_shift: wp.vec2d
    bias_matrix: wp.mat22d
    bias_inverse: wp.mat22d


@wp.func
def rpc_terms(x: wp.float64, y: wp.float64, z: wp.float64):
    """The 20 terms 1 L P H LP LH PH L^2 P^2 H^2 PLH L^3 LP^2 LH^2 L^2P P^3 PH^2 L^2H P^2H H^3 at
    normalised (x, y, z) = (L, P, H)."""
    return vec20d(wp.float64(1.0), x, y, z, x * y, x * z, y * z, x * x, y * y, z * z, x * y * z, x * x * x,
                  x * y * y, x * z * z, x * x * y, y * y * y, y * z * z, x * x * z, y * y * z, z * z * z)


@wp.func
def rpc_terms_dx(x: wp.float64, y: wp.float64, z: wp.float64):
    """d terms / dL."""
    o = wp.float64(0.0)
    two = wp.float64(2.0)
    return vec20d(o, wp.float64(1.0), o, o, y, z, o, two * x, o, o, y * z, wp.float64(3.0) * x * x, y * y, z * z,
                  two * x * y, o, o, two * x * z, o, o)


@wp.func
def rpc_terms_dy(x: wp.float64, y: wp.float64, z: wp.float64):
    """d terms / dP."""
    o = wp.float64(0.0)
    two = wp.float64(2.0)
    return vec20d(o, o, wp.float64(1.0), o, x, o, z, o, two * y, o, x * z, o, two * x * y, o, x * x,
                  wp.float64(3.0) * y * y, z * z, o, two * y * z, o)


@wp.func
def rpc_normalise(r: RpcData, lon: wp.float64, lat: wp.float64, h: wp.float64):
    """Ground (lon, lat deg, h m) -> normalised (L, P, H), the longitude difference within
    [-180, 180) deg."""
    dlon = lon - r.ground_off[0]
    dlon = dlon - wp.float64(360.0) * wp.floor((dlon + wp.float64(180.0)) / wp.float64(360.0))
    return wp.vec3d(dlon / r.ground_scale[0], (lat - r.ground_off[1]) / r.ground_scale[1],
                    (h - r.ground_off[2]) / r.ground_scale[2])


@wp.func
def rpc_ratios(r: RpcData, u: wp.vec3d):
    """Normalised ground -> normalised image (s, l); NaN where a denominator vanishes."""
    t = rpc_terms(u[0], u[1], u[2])
    ds = wp.dot(r.samp_den, t)
    dl = wp.dot(r.line_den, t)
    nan = wp.float64(wp.nan)
    if ds == wp.float64(0.0) or dl == wp.float64(0.0):
        return wp.vec2d(nan, nan)
    return wp.vec2d(wp.dot(r.samp_num, t) / ds, wp.dot(r.line_num, t) / dl)


@wp.func
def rpc_image(r: RpcData, s: wp.vec2d):
    """Normalised image (s, l) -> compensated pixel (col, row)."""
    raw = wp.vec2d(s[0] * r.image_scale[0] + r.image_off[0], s[1] * r.image_scale[1] + r.image_off[1])
    return r.bias_matrix * raw + r.bias_shift


@wp.func
def rpc_pixel(r: RpcData, lon: wp.float64, lat: wp.float64, h: wp.float64):
    """Ground (lon, lat deg, ellipsoidal h m) -> pixel (col, row), compensated."""
    return rpc_image(r, rpc_ratios(r, rpc_normalise(r, lon, lat, h)))


@wp.func
def rpc_project_xyz(r: RpcData, x: wp.vec3d, h: wp.float64):
    """An ECEF point x whose ellipsoidal height is h -> pixel (col, row)."""
    g = ecef_to_geodetic(x)
    return rpc_pixel(r, g[1] * RAD2DEG, g[0] * RAD2DEG, h)


@wp.func
def rpc_target(r: RpcData, pix: wp.vec2d):
    """Compensated pixel -> the normalised image position (s, l) the RPCs must reach."""
    raw = r.bias_inverse * (pix - r.bias_shift)
    return wp.vec2d((raw[0] - r.image_off[0]) / r.image_scale[0], (raw[1] - r.image_off[1]) / r.image_scale[1])


@wp.func
def rpc_residual(r: RpcData, target: wp.vec2d, x: wp.float64, y: wp.float64, z: wp.float64):
    """(s, l)(x, y, z) - target, normalised; NaN where a denominator vanishes."""
    return rpc_ratios(r, wp.vec3d(x, y, z)) - target


@wp.func
def rpc_solve(r: RpcData, target: wp.vec2d, z: wp.float64, start: wp.vec2d):
    """Normalised (L, P) at normalised height z whose image is ``target``, by damped Newton
    from ``start``; NaN if it does not converge."""
    nan = wp.float64(wp.nan)
    u = start
    for _ in range(RPC_STEPS):
        t = rpc_terms(u[0], u[1], z)
        tx = rpc_terms_dx(u[0], u[1], z)
        ty = rpc_terms_dy(u[0], u[1], z)
        ns = wp.dot(r.samp_num, t)
        ds = wp.dot(r.samp_den, t)
        nl = wp.dot(r.line_num, t)
        dl = wp.dot(r.line_den, t)
        if ds == wp.float64(0.0) or dl == wp.float64(0.0):
            return wp.vec2d(nan, nan)
        f = wp.vec2d(ns / ds - target[0], nl / dl - target[1])
        # d(N/D) = (N' D - N D') / D^2, by L (x) and P (y)
        a = (wp.dot(r.samp_num, tx) * ds - ns * wp.dot(r.samp_den, tx)) / (ds * ds)
        b = (wp.dot(r.samp_num, ty) * ds - ns * wp.dot(r.samp_den, ty)) / (ds * ds)
        c = (wp.dot(r.line_num, tx) * dl - nl * wp.dot(r.line_den, tx)) / (dl * dl)
        d = (wp.dot(r.line_num, ty) * dl - nl * wp.dot(r.line_den, ty)) / (dl * dl)
        det = a * d - b * c
        step = wp.vec2d((d * f[0] - b * f[1]) / det, (a * f[1] - c * f[0]) / det)
        if not (wp.isfinite(step[0]) and wp.isfinite(step[1])):
            return wp.vec2d(nan, nan)
        if wp.max(wp.abs(step[0]), wp.abs(step[1])) < RPC_TOL:
            return u - step
        norm0 = wp.max(wp.abs(f[0]), wp.abs(f[1]))
        k = wp.float64(1.0)
        for _h in range(RPC_HALVINGS):  # a step that does not lower the residual is halved
            v = u - k * step
            fn = rpc_residual(r, target, v[0], v[1], z)
            if wp.max(wp.abs(fn[0]), wp.abs(fn[1])) < norm0:
                break
            k = k * wp.float64(0.5)
        u = u - k * step
    return wp.vec2d(nan, nan)


@wp.func
def rpc_lonlat(r: RpcData, u: wp.vec2d):
    """Normalised (L, P) -> (lon, lat) deg."""
    return wp.vec2d(u[0] * r.ground_scale[0] + r.ground_off[0], u[1] * r.ground_scale[1] + r.ground_off[1])


@wp.func
def rpc_locate(r: RpcData, pix: wp.vec2d, h: wp.float64):
    """Compensated pixel (col, row) -> geo triple (lon, lat deg, h) at ellipsoidal height h
    (m); NaN if the inverse does not converge."""
    z = (h - r.ground_off[2]) / r.ground_scale[2]
    u = rpc_solve(r, rpc_target(r, pix), z, wp.vec2d(wp.float64(0.0), wp.float64(0.0)))
    g = rpc_lonlat(r, u)
    return wp.vec3d(g[0], g[1], h)


@wp.func
def rpc_gap(r: RpcData, dem: DemData, target: wp.vec2d, h: wp.float64, start: wp.vec2d):
    """The line of sight's point at height h (normalised (L, P), solved from ``start``) and the
    gap DEM - h there (m; NaN off the DEM or where the inverse fails)."""
    u = rpc_solve(r, target, (h - r.ground_off[2]) / r.ground_scale[2], start)
    g = rpc_lonlat(r, u)
    return u, dem_sample_grid(dem, dem_grid(dem, g[0], g[1])) - h


@wp.func
def rpc_geolocate(r: RpcData, dem: DemData, search: SearchParams, pix: wp.vec2d):
    """Compensated pixel -> geo triple (lon, lat deg, ellipsoidal h m) of the first point of
    its line of sight on the DEM, seen from above; NaN where the line of sight leaves the DEM
    before meeting it, enters it underground, or the inverse fails."""
    nan = wp.float64(wp.nan)
    miss = wp.vec3d(nan, nan, nan)
    target = rpc_target(r, pix)
    origin = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    if dem.constant != 0:
        g = rpc_lonlat(r, rpc_solve(r, target, (dem.value - r.ground_off[2]) / r.ground_scale[2], origin))
        return wp.vec3d(g[0], g[1], dem.value)
    margin = wp.float64(1.0)
    h_hi = dem.hmax + margin
    h_lo = dem.hmin - margin
    u_hi, prev = rpc_gap(r, dem, target, h_hi, origin)
    if not wp.isfinite(u_hi[0]):
        return miss
    if prev >= wp.float64(0.0):
        return miss  # terrain above the DEM's top: not a DEM this line of sight can meet
    u_lo, _ = rpc_gap(r, dem, target, h_lo, u_hi)
    if not wp.isfinite(u_lo[0]):
        return miss
    g_hi = rpc_lonlat(r, u_hi)
    g_lo = rpc_lonlat(r, u_lo)
    n = wp.int32(wp.ceil(wp.length(dem_grid(dem, g_lo[0], g_lo[1]) - dem_grid(dem, g_hi[0], g_hi[1])))) + 1
    n = wp.clamp(n, 1, search.max_steps)
    hstep = (h_hi - h_lo) / wp.float64(n)
    # march: every step solved exactly (warm started), one DEM cell at most apart
    u = u_hi
    a = h_hi
    fa = prev
    ua = u_hi
    b = h_lo
    fb = nan
    ub = u_hi
    found = wp.int32(0)
    for k in range(1, n + 1):
        h = h_hi - wp.float64(k) * hstep
        uk, fk = rpc_gap(r, dem, target, h, u)
        if not wp.isfinite(uk[0]):
            return miss
        if fk >= wp.float64(0.0):
            if not wp.isfinite(fa):
                return miss  # it entered the DEM underground
            b = h
            fb = fk
            ub = uk
            found = 1
            break
        a = h
        fa = fk
        ua = uk
        u = uk
    if found == 0:
        return miss
    # Illinois regula falsi on exact gaps: fa < 0 at height a (above), fb >= 0 at b (below)
    best = rpc_lonlat(r, ub)
    hb = b
    side = wp.int32(0)
    for _ in range(100):
        c = b - fb * (b - a) / (fb - fa)
        start = ua
        if b - c < c - a:
            start = ub
        uc, fc = rpc_gap(r, dem, target, c, start)
        if not wp.isfinite(fc):
            return miss
        best = rpc_lonlat(r, uc)
        hb = c
        if wp.abs(fc) < search.htol:
            break
        if fc >= wp.float64(0.0):
            b = c
            fb = fc
            ub = uc
            if side == 1:
                fa = fa * wp.float64(0.5)
            side = 1
        else:
            a = c
            fa = fc
            ua = uc
            if side == -1:
                fb = fb * wp.float64(0.5)
            side = -1
        if a - b < search.htol:
            break
    return wp.vec3d(best[0], best[1], hb)
