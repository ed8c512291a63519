"""Geodesy on the WGS84 ellipsoid, float64, device code.

Angles are radians inside these functions; heights are ellipsoidal, metres.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})  # forward-only kernels: halves compile time

WGS84_A = wp.constant(wp.float64(6378137.0))
WGS84_F = wp.constant(wp.float64(1.0 / 298.257223563))
WGS84_B = wp.constant(wp.float64(6378137.0 * (1.0 - 1.0 / 298.257223563)))
WGS84_E2 = wp.constant(wp.float64((1.0 / 298.257223563) * (2.0 - 1.0 / 298.257223563)))
WGS84_EP2 = wp.constant(wp.float64((1.0 / 298.257223563) * (2.0 - 1.0 / 298.257223563)
                                   / (1.0 - (1.0 / 298.257223563) * (2.0 - 1.0 / 298.257223563))))
DEG = wp.constant(wp.float64(0.017453292519943295))
RAD2DEG = wp.constant(wp.float64(57.29577951308232))


@wp.func
def geodetic_to_ecef(lat: wp.float64, lon: wp.float64, h: wp.float64):
    """ECEF position (m) of geodetic latitude, longitude (rad) and ellipsoidal height (m)."""
    slat = wp.sin(lat)
    clat = wp.cos(lat)
    n = WGS84_A / wp.sqrt(wp.float64(1.0) - WGS84_E2 * slat * slat)
    return wp.vec3d(
        (n + h) * clat * wp.cos(lon),
        (n + h) * clat * wp.sin(lon),
        (n * (wp.float64(1.0) - WGS84_E2) + h) * slat,
    )


@wp.func
def ecef_to_geodetic_sc(p: wp.vec3d):
    """:func:`ecef_to_geodetic` that also returns sin(lat), cos(lat) and the distance r (m)
    from the polar axis, for callers that build the local frame there."""

    one = wp.float64(1.0)
    r = wp.sqrt(p[0] * p[0] + p[1] * p[1])
    z = p[2]
    rb = r * WGS84_B
    za = z * WGS84_A
    inv = one / wp.sqrt(rb * rb + za * za)
    cu = rb * inv
    su = za * inv
    num = z + WGS84_EP2 * WGS84_B * su * su * su
    dnm = r - WGS84_E2 * WGS84_A * cu * cu * cu
    inv = one / wp.sqrt(num * num + dnm * dnm)
    slat = num * inv
    clat = dnm * inv
    w = wp.sqrt(one - WGS84_E2 * slat * slat)
    h = r * clat + z * slat - WGS84_A * w
    dnm = r * (one - WGS84_E2 * WGS84_A / (WGS84_A + h * w))  # e2 N / (N + h), N = a / w
    inv = one / wp.sqrt(z * z + dnm * dnm)
    slat = z * inv
    clat = dnm * inv
    h = r * clat + z * slat - WGS84_A * wp.sqrt(one - WGS84_E2 * slat * slat)
    return wp.vec3d(wp.atan2(z, dnm), wp.atan2(p[1], p[0]), h), slat, clat, r


@wp.func
def ecef_to_geodetic(p: wp.vec3d):
    """Geodetic (lat rad, lon rad, h m) of an ECEF position (m).

    Bowring's (1976) parametric-latitude formula as the first guess, then one step of the
    fixed-point iteration ``tan(lat) = z / (r (1 - e2 N / (N + h)))`` with the height written as
    ``h = r cos(lat) + z sin(lat) - a sqrt(1 - e2 sin^2 lat)``, which stays well conditioned at
    the poles. Sines and cosines come from the tangent's numerator and denominator, so only
    two arc tangents are evaluated. Measured against PROJ: < 1e-8 m from -2 km to 900 km,
    poles included.
    """
    g, slat, clat, r = ecef_to_geodetic_sc(p)
    return g


@wp.kernel
def geodetic_to_ecef_kernel(llh: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    """(lat deg, lon deg, h m) -> ECEF (m), element-wise."""
    i = wp.tid()
    v = llh[i]
    out[i] = geodetic_to_ecef(v[0] * DEG, v[1] * DEG, v[2])


@wp.kernel
def ecef_to_geodetic_kernel(xyz: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    """ECEF (m) -> (lat deg, lon deg, h m), element-wise."""
    i = wp.tid()
    g = ecef_to_geodetic(xyz[i])
    out[i] = wp.vec3d(g[0] * RAD2DEG, g[1] * RAD2DEG, g[2])
