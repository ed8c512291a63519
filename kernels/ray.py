"""Rays of any sensor met with the Earth, device code: the ellipsoid at a height, the
atmospheric refraction of the ray, and the DEM relief search ([P3]'s chain after the
camera: the frame kernels and the pushbroom kernels both end here).

A ray starts at a sensor position in an object frame (:class:`FramePoseData`: ECEF for
geocentric sensors, a map CRS with height as z for map-Cartesian frames) with a unit apparent
direction; :func:`geolocate_ray` returns the geo triple of its first ground point
((lon deg, lat deg, ellipsoidal height m) in geocentric mode, (x, y, z) of the map CRS in map
mode), and :func:`apparent_direction` turns a chord to a ground point into the direction the
sensor sees it under (the backward chain's refraction).
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})  # forward-only kernels: halves compile time

from .dem import DemData, dem_block_bound, dem_grid, dem_sample_grid, dem_sample_grid_f32
from .geodesy import RAD2DEG, WGS84_A, WGS84_B, WGS84_E2, ecef_to_geodetic, ecef_to_geodetic_sc
from .refraction import RefractionTable, refraction_q

MODE_GEOCENTRIC = wp.constant(0)
MODE_MAP = wp.constant(1)


@wp.struct
class FramePoseData:
    """Exterior orientation packed for kernels.

    mode: 0 geocentric (object frame ECEF), 1 map-Cartesian (object frame = projected CRS with
    height as z); center: projection centre in the object frame (m); rot: R_object<-camera;
    up: unit local vertical at the projection centre (object frame); height: ellipsoidal
    height (geocentric) or z (map) of the projection centre (m).
    """

    mode: wp.int32
    center: wp.vec3d
    rot: wp.mat33d
    up: wp.vec3d
    height: wp.float64


@wp.struct
class SearchParams:
    """Controls of the DEM relief search: height tolerance (m), march step cap."""

    htol: wp.float64
    max_steps: wp.int32


@wp.func
def point_at_height(pose: FramePoseData, d: wp.vec3d, h: wp.float64):
    """Geo triple where the ray (center, unit d) meets the surface of height h; NaN if it misses.

    Geocentric: the ellipsoid of semi-axes a + h, b + h ([P3] eqs. 10-12), solved in the
    cancellation-free form of the quadratic; the returned height is the exact geodetic height
    of the intersection, which differs from h by millimetres. Map mode: the plane z = h.
    """
    nan = wp.float64(wp.nan)
    miss = wp.vec3d(nan, nan, nan)
    c = pose.center
    if pose.mode == MODE_MAP:
        if d[2] >= wp.float64(0.0):
            return miss
        s = (h - c[2]) / d[2]
        if s <= wp.float64(0.0):
            return miss
        return wp.vec3d(c[0] + s * d[0], c[1] + s * d[1], h)
    s = ellipsoid_distance(c, d, h)
    if not wp.isfinite(s):
        return miss
    g = ecef_to_geodetic(c + s * d)
    return wp.vec3d(g[1] * RAD2DEG, g[0] * RAD2DEG, g[2])


@wp.func
def ellipsoid_distance(c: wp.vec3d, d: wp.vec3d, h: wp.float64):
    """Distance (m) along the unit ray (c, d) to the ellipsoid of semi-axes a + h, b + h.

    [P3] eqs. 10-12, the near root of the quadratic in its cancellation-free form; NaN
    when the ray misses, points away, or starts inside.
    """
    ia = wp.float64(1.0) / (WGS84_A + h)
    ib = wp.float64(1.0) / (WGS84_B + h)
    cs = wp.vec3d(c[0] * ia, c[1] * ia, c[2] * ib)
    ds = wp.vec3d(d[0] * ia, d[1] * ia, d[2] * ib)
    qa = wp.dot(ds, ds)
    qb = wp.dot(cs, ds)
    qc = wp.dot(cs, cs) - wp.float64(1.0)
    disc = qb * qb - qa * qc
    if qc <= wp.float64(0.0) or qb >= wp.float64(0.0) or disc < wp.float64(0.0):
        return wp.float64(wp.nan)
    return qc / (wp.sqrt(disc) - qb)


@wp.struct
class RayData:
    """An apparent ray (object frame) and what refraction needs of it, computed once per pixel.

    d: unit apparent direction; w: unit vector perpendicular to d in its vertical plane,
    pointing towards the nadir; theta, tan_theta: apparent nadir angle (rad) and its tangent.
    """

    d: wp.vec3d
    w: wp.vec3d
    theta: wp.float64
    tan_theta: wp.float64


@wp.func
def make_ray(pose: FramePoseData, d_app: wp.vec3d):
    r = RayData()
    r.d = d_app
    c = -wp.dot(d_app, pose.up)
    perp = -(pose.up + c * d_app)  # component of the nadir direction perpendicular to d
    s = wp.length(perp)
    # theta only indexes the refraction table, whose q changes by ~1e-4 per radian: float32 will do
    r.theta = wp.float64(wp.atan2(wp.float32(s), wp.float32(c)))
    if c > wp.float64(0.0):
        r.tan_theta = s / c
    else:
        r.tan_theta = wp.tan(r.theta)
    if s > wp.float64(1.0e-12):
        r.w = perp / s
    else:
        r.w = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    return r


@wp.func
def chord_direction(refr: RefractionTable, ray: RayData, h: wp.float64):
    """Unit chord from the sensor to ground at height h: the apparent ray turned towards the
    nadir by the refraction angle delta(theta, h)."""
    if refr.enabled == 0:
        return ray.d
    delta = refraction_q(refr, ray.theta, h) * ray.tan_theta
    d2 = delta * delta
    # cos and sin by their series: |delta| < 1e-2 rad, so the error is < 1e-14
    return (wp.float64(1.0) - wp.float64(0.5) * d2) * ray.d + delta * (
        wp.float64(1.0) - d2 * wp.float64(1.0 / 6.0)) * ray.w


@wp.func
def surface_gap(pose: FramePoseData, refr: RefractionTable, dem: DemData, ray: RayData, h: wp.float64):
    """Ground point at trial height h and the gap DEM(point) - height(point) (m, NaN if none)."""
    g = point_at_height(pose, chord_direction(refr, ray, h), h)
    z = dem_sample_grid(dem, dem_grid(dem, g[0], g[1]))
    return g, z - g[2]


@wp.func
def track_ends(pose: FramePoseData, refr: RefractionTable, ray: RayData, h_hi: wp.float64, h_lo: wp.float64):
    """Geo triples of the ray's ground track at heights h_hi (exact) and h_lo, and whether the
    latter is exact.

    In geocentric mode a short track (< 1 km horizontally, away from the poles) gets its lower
    end from the local frame at the upper one instead of a second intersection: first order in
    latitude and longitude, with the Earth's curvature in the path length. Its error (about
    (length)^2 / R: 1.6 mm at 100 m) only steers the march; the refinement is exact.
    """
    nan = wp.float64(wp.nan)
    miss = wp.vec3d(nan, nan, nan)
    exact = True
    if pose.mode == MODE_GEOCENTRIC:
        d = chord_direction(refr, ray, h_hi)
        s_hi = ellipsoid_distance(pose.center, d, h_hi)
        if not wp.isfinite(s_hi):
            return miss, miss, exact
        else:
            x = pose.center + s_hi * d
            g, slat, clat, r = ecef_to_geodetic_sc(x)
            g_hi = wp.vec3d(g[1] * RAD2DEG, g[0] * RAD2DEG, g[2])
            if clat > wp.float64(0.01) and r > wp.float64(0.0):
                cl = x[0] / r
                sl = x[1] / r
                du = wp.dot(d, wp.vec3d(clat * cl, clat * sl, slat))
                if du < wp.float64(-1.0e-3):
                    s0 = (h_lo - g[2]) / du
                    horiz2 = s0 * s0 * (wp.float64(1.0) - du * du)
                    if horiz2 < wp.float64(1.0e6):
                        s = s0 - horiz2 / (wp.float64(2.0) * WGS84_A) / du  # the surface drops away
                        w2 = wp.float64(1.0) - WGS84_E2 * slat * slat
                        n = WGS84_A / wp.sqrt(w2)
                        m = n * (wp.float64(1.0) - WGS84_E2) / w2
                        dlon = s * wp.dot(d, wp.vec3d(-sl, cl, wp.float64(0.0))) / ((n + g[2]) * clat)
                        dlat = s * wp.dot(d, wp.vec3d(-slat * cl, -slat * sl, clat)) / (m + g[2])
                        return g_hi, wp.vec3d(g_hi[0] + dlon * RAD2DEG, g_hi[1] + dlat * RAD2DEG, h_lo), False
            return g_hi, point_at_height(pose, chord_direction(refr, ray, h_lo), h_lo), exact
    g_hi = point_at_height(pose, chord_direction(refr, ray, h_hi), h_hi)
    return g_hi, point_at_height(pose, chord_direction(refr, ray, h_lo), h_lo), exact


@wp.func
def geolocate_ray(
    pose: FramePoseData, refr: RefractionTable, dem: DemData, search: SearchParams, d_app: wp.vec3d
):
    """First intersection of an apparent ray (unit, object frame) with the DEM, as a geo triple.

    Relief search (replaces the fixed-point iteration of [P3] eqs. 18-21, which diverges
    where slope x tan(off-nadir) > 1):

    1. the ray's ground track between the DEM's highest and lowest heights is computed
       exactly at both ends and marched, linearly in grid space, in steps of at most one DEM
       cell until the gap DEM - height changes sign: this brackets the first surface crossing
       seen from the sensor. Runs of ``dem.block`` steps whose lowest point lies above the
       DEM's block-wise upper bound are skipped whole (a max-pyramid of one level);
    2. the Illinois variant of regula falsi refines the bracket with exact evaluations to
       ``search.htol``, starting from the march's (approximate) gaps; if it ends on a bracket
       whose ends were never evaluated exactly, both ends are evaluated exactly (and widened
       by a step where the approximation misjudged a sign) and the refinement runs again.

    Rays that miss the Earth, leave the DEM before reaching it, enter it underground or start
    below it give NaN. The march itself runs in float32 (bracketing only); every number that
    reaches the result is float64.
    """
    nan = wp.float64(wp.nan)
    miss = wp.vec3d(nan, nan, nan)
    ray = make_ray(pose, d_app)
    margin = wp.float64(1.0)
    h_hi = wp.min(dem.hmax + margin, pose.height - wp.float64(0.01))
    h_lo = dem.hmin - margin
    if h_hi <= h_lo:
        return miss
    g_hi, g_lo, lo_exact = track_ends(pose, refr, ray, h_hi, h_lo)
    if not (wp.isfinite(g_hi[0]) and wp.isfinite(g_lo[0])):
        return miss
    ga = dem_grid(dem, g_hi[0], g_hi[1])
    gb = dem_grid(dem, g_lo[0], g_lo[1])
    n = wp.int32(wp.ceil(wp.length(gb - ga))) + 1
    if dem.constant != 0:
        n = 1
    n = wp.clamp(n, 1, search.max_steps)
    prev = dem_sample_grid(dem, ga) - g_hi[2]
    if prev >= wp.float64(0.0):
        return miss  # terrain above the start: the sensor is below the surface
    # The march runs in float32 (grid coordinates and heights); the bracket it finds is
    # re-sampled in float64 below.
    found = wp.int32(0)
    inv_n = wp.float32(1.0) / wp.float32(n)
    x0 = wp.float32(ga[0])
    y0 = wp.float32(ga[1])
    z0 = wp.float32(g_hi[2])
    dx = wp.float32(gb[0] - ga[0])
    dy = wp.float32(gb[1] - ga[1])
    dz = wp.float32(g_lo[2] - g_hi[2])
    prev32 = wp.float32(prev)
    k0 = wp.int32(0)
    while k0 < n and found == 0:
        # Coarse step over dem.block cells: skipped when its lowest point is above the block
        # bound (no crossing possible), else marched cell by cell.
        k1 = wp.min(k0 + dem.block, n)
        t0 = wp.float32(k0) * inv_n
        t1 = wp.float32(k1) * inv_n
        h1 = z0 + t1 * dz
        if dem.constant == 0 and h1 > dem_block_bound(dem, x0 + t0 * dx, y0 + t0 * dy):
            prev32 = dem_sample_grid_f32(dem, x0 + t1 * dx, y0 + t1 * dy) - h1
        else:
            for k in range(k0 + 1, k1 + 1):
                t = wp.float32(k) * inv_n
                f32 = dem_sample_grid_f32(dem, x0 + t * dx, y0 + t * dy) - (z0 + t * dz)
                if f32 >= wp.float32(0.0):
                    # a finite prev < 0 brackets the crossing; otherwise it entered the DEM underground
                    if not wp.isfinite(prev32):
                        return miss
                    found = k
                    break
                prev32 = f32
        k0 = k1
    if found == 0:
        return miss
    # float64 gaps at the bracket ends, on the linear track (exact at the track's ends)
    ta = wp.float64(found - 1) / wp.float64(n)
    tb = wp.float64(found) / wp.float64(n)
    fa = dem_sample_grid(dem, ga + ta * (gb - ga)) - (g_hi[2] + ta * (g_lo[2] - g_hi[2]))
    fb = dem_sample_grid(dem, ga + tb * (gb - ga)) - (g_hi[2] + tb * (g_lo[2] - g_hi[2]))
    hstep = (h_hi - h_lo) / wp.float64(n)
    a = h_hi - wp.float64(found - 1) * hstep
    b = a - hstep
    exact_a = found == 1  # the track's end points were evaluated exactly
    exact_b = found == n and lo_exact
    best = miss
    for attempt in range(2):
        if attempt == 1:
            # Exact gaps at the bracket ends, widened where the approximate march misjudged.
            ga3, fa = surface_gap(pose, refr, dem, ray, a)
            for _ in range(4):
                if not (fa >= wp.float64(0.0)):
                    break
                a = wp.min(a + hstep, h_hi)
                ga3, fa = surface_gap(pose, refr, dem, ray, a)
            gb3, fb = surface_gap(pose, refr, dem, ray, b)
            for _ in range(4):
                if not (fb < wp.float64(0.0)):
                    break
                b = wp.max(b - hstep, h_lo)
                gb3, fb = surface_gap(pose, refr, dem, ray, b)
            if not (fa < wp.float64(0.0) and fb >= wp.float64(0.0)):
                return miss
            exact_a = True
            exact_b = True
        elif not (fa < wp.float64(0.0) and fb >= wp.float64(0.0)):
            continue  # the float32 march misjudged a sign: go straight to exact ends
        side = wp.int32(0)
        for _ in range(100):
            c = b - fb * (b - a) / (fb - fa)
            gc, fc = surface_gap(pose, refr, dem, ray, c)
            if not wp.isfinite(fc):
                return miss
            best = gc
            if wp.abs(fc) < search.htol:
                return best
            if fc >= wp.float64(0.0):
                b = c
                fb = fc
                exact_b = True
                if side == 1:
                    fa = fa * wp.float64(0.5)
                side = 1
            else:
                a = c
                fa = fc
                exact_a = True
                if side == -1:
                    fb = fb * wp.float64(0.5)
                side = -1
            if a - b < search.htol:
                break
        if exact_a and exact_b:
            return best
    return best


@wp.func
def apparent_direction(refr: RefractionTable, up: wp.vec3d, v: wp.vec3d, h: wp.float64):
    """A vector along the apparent (refracted) direction at the sensor of the chord v (sensor
    to a ground point at height h, any length): the chord turned away from the nadir by delta.
    ``up`` is the unit local vertical at the sensor, in the same frame as v (any frame: only
    angles and combinations of the two are taken). The result's length is not 1: callers use
    ratios of its components only.

    delta = q(theta_a, h) tan(theta_a) at the apparent angle theta_a = theta_c + delta. q varies
    by ~1e-5 of itself over delta, so it is read once at theta_c; tan(theta_a) is linearised
    about theta_c (error ~ delta^2); two steps of the fixed point then leave < 1e-12 rad.

    The turn is computed in float32 and applied to the float64 chord as v - |v| k w, with w
    the unit vector towards the nadir perpendicular to v and k = delta (1 - delta^2/6) /
    (1 - delta^2/2): the term moves v by |v| delta (~0.1 m for aircraft, ~1 m from orbit), so
    its float32 rounding stays below 1e-6 m; the rounding of w, which grows as 1/sin(theta)
    towards the nadir, is multiplied by delta, which shrinks as tan(theta).
    """
    if refr.enabled == 0:
        return v
    v32 = wp.vec3f(wp.float32(v[0]), wp.float32(v[1]), wp.float32(v[2]))
    n = wp.length(v32)
    d = v32 / n
    up32 = wp.vec3f(wp.float32(up[0]), wp.float32(up[1]), wp.float32(up[2]))
    c = -wp.dot(d, up32)
    perp = -(up32 + c * d)  # component of the nadir direction perpendicular to v
    s = wp.length(perp)
    theta = wp.atan2(s, c)
    tan_theta = wp.tan(theta)
    if c > wp.float32(0.0):
        tan_theta = s / c
    w = wp.vec3f(0.0)
    if s > wp.float32(1.0e-12):
        w = perp / s
    q = wp.float32(refraction_q(refr, wp.float64(theta), h))
    one = wp.float32(1.0)
    delta = q * tan_theta
    delta = q * (tan_theta + delta * (one + tan_theta * tan_theta))
    d2 = delta * delta
    k = n * delta * (one - d2 / wp.float32(6.0)) / (one - wp.float32(0.5) * d2)
    return v - wp.vec3d(wp.float64(k * w[0]), wp.float64(k * w[1]), wp.float64(k * w[2]))
