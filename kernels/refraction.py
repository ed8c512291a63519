"""Atmospheric refraction sampled from a per-image table, device code.

The host (:mod:`orthowarp.refraction`) traces rays through a layered atmosphere and tabulates
``q(theta, h) = delta / tan(theta)``: ``theta`` is the apparent nadir angle of a ray at the
sensor, ``h`` the ellipsoidal height of the ground it reaches, and ``delta`` the angle between
the apparent ray and the straight chord from the sensor to that ground point (rad). ``q`` is
smooth and nearly constant, so bilinear interpolation is accurate to well under 1e-3 of delta.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})  # forward-only kernels: halves compile time


@wp.struct
class RefractionTable:
    """``q = delta / tan(theta)`` on a regular (theta, h) grid; ``enabled = 0`` turns it off.

    q has shape (n_theta, n_h); theta0, dtheta in rad; h0, dh in metres.
    """

    enabled: wp.int32
    theta0: wp.float64
    dtheta: wp.float64
    h0: wp.float64
    dh: wp.float64
    inv_dtheta: wp.float64
    inv_dh: wp.float64
    q: wp.array2d(dtype=wp.float64)


@wp.func
def refraction_q(tab: RefractionTable, theta: wp.float64, h: wp.float64):
    """delta / tan(theta) at apparent nadir angle theta (rad) and ground height h (m)."""
    if tab.enabled == 0:
        return wp.float64(0.0)
    nt = tab.q.shape[0]
    nh = tab.q.shape[1]
    ft = wp.clamp((theta - tab.theta0) * tab.inv_dtheta, wp.float64(0.0), wp.float64(nt - 1))
    fh = wp.clamp((h - tab.h0) * tab.inv_dh, wp.float64(0.0), wp.float64(nh - 1))
    it = wp.min(wp.int32(ft), nt - 2)
    ih = wp.min(wp.int32(fh), nh - 2)
    at = ft - wp.float64(it)
    ah = fh - wp.float64(ih)
    one = wp.float64(1.0)
    q = (one - at) * ((one - ah) * tab.q[it, ih] + ah * tab.q[it, ih + 1]) + at * (
        (one - ah) * tab.q[it + 1, ih] + ah * tab.q[it + 1, ih + 1]
    )
    return q
