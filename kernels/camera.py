"""Frame camera interior orientation, device code.

Conventions (docs/design.md): pixel (col, row) with the origin at the top-left corner of the
top-left pixel; camera frame x right, y up, z backwards (looks along -z); image coordinates
(x, y) in mm from the principal point; Brown-Conrady distortion on OpenCV normalised
coordinates (u, v) = (x / f, -y / f), undistorted -> distorted.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})  # forward-only kernels: halves compile time


@wp.struct
class FrameCameraData:
    """Interior orientation packed for kernels (all float64).

    focal: focal length (mm); pixel_size: (x, y) pixel pitch (mm) and inv_pixel_size its
    reciprocal (1/mm, so that kernels multiply); size: (width, height) in
    pixels; pp: principal point offset (mm) from the image centre, x right, y up; k1, k2, k3,
    p1, p2: OpenCV-normalised Brown coefficients.
    """

    focal: wp.float64
    pixel_size: wp.vec2d
    inv_pixel_size: wp.vec2d
    size: wp.vec2d
    pp: wp.vec2d
    k1: wp.float64
    k2: wp.float64
    k3: wp.float64
    p1: wp.float64
    p2: wp.float64


@wp.func
def distort(cam: FrameCameraData, uv: wp.vec2d):
    """Undistorted -> distorted normalised coordinates (closed form)."""
    u = uv[0]
    v = uv[1]
    r2 = u * u + v * v
    radial = wp.float64(1.0) + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3))
    two = wp.float64(2.0)
    return wp.vec2d(
        u * radial + two * cam.p1 * u * v + cam.p2 * (r2 + two * u * u),
        v * radial + cam.p1 * (r2 + two * v * v) + two * cam.p2 * u * v,
    )


@wp.func
def undistort(cam: FrameCameraData, uvd: wp.vec2d):
    """Distorted -> undistorted normalised coordinates by Newton's method.

    The 2x2 Jacobian of :func:`distort` is analytic; iteration stops when the step is below
    1e-15 (normalised units, ~1e-11 px) or after 30 steps.
    """
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    u = uvd[0]
    v = uvd[1]
    for _ in range(30):
        r2 = u * u + v * v
        radial = one + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3))
        # d(radial)/d(r2)
        dradial = cam.k1 + r2 * (two * cam.k2 + wp.float64(3.0) * r2 * cam.k3)
        fu = u * radial + two * cam.p1 * u * v + cam.p2 * (r2 + two * u * u) - uvd[0]
        fv = v * radial + cam.p1 * (r2 + two * v * v) + two * cam.p2 * u * v - uvd[1]
        j00 = radial + two * u * u * dradial + two * cam.p1 * v + wp.float64(6.0) * cam.p2 * u
        j01 = two * u * v * dradial + two * cam.p1 * u + two * cam.p2 * v
        j10 = two * u * v * dradial + two * cam.p1 * u + two * cam.p2 * v
        j11 = radial + two * v * v * dradial + wp.float64(6.0) * cam.p1 * v + two * cam.p2 * u
        inv_det = one / (j00 * j11 - j01 * j10)
        du = (j11 * fu - j01 * fv) * inv_det
        dv = (j00 * fv - j10 * fu) * inv_det
        u = u - du
        v = v - dv
        if wp.abs(du) + wp.abs(dv) < wp.float64(1.0e-15):
            break
    return wp.vec2d(u, v)


@wp.func
def pixel_to_normalized(cam: FrameCameraData, pix: wp.vec2d):
    """Pixel (col, row) -> distorted OpenCV-normalised coordinates (u right, v down)."""
    half = wp.float64(0.5)
    x = (pix[0] - half * cam.size[0]) * cam.pixel_size[0] - cam.pp[0]
    y = (half * cam.size[1] - pix[1]) * cam.pixel_size[1] - cam.pp[1]
    return wp.vec2d(x / cam.focal, -y / cam.focal)


@wp.func
def normalized_to_pixel(cam: FrameCameraData, uv: wp.vec2d):
    """Distorted OpenCV-normalised coordinates -> pixel (col, row)."""
    half = wp.float64(0.5)
    x = uv[0] * cam.focal
    y = -uv[1] * cam.focal
    return wp.vec2d(
        (x + cam.pp[0]) * cam.inv_pixel_size[0] + half * cam.size[0],
        half * cam.size[1] - (y + cam.pp[1]) * cam.inv_pixel_size[1],
    )


@wp.func
def pixel_to_camera(cam: FrameCameraData, pix: wp.vec2d):
    """Pixel (col, row) -> unit ray in the camera frame (x right, y up, z back)."""
    uv = undistort(cam, pixel_to_normalized(cam, pix))
    return wp.normalize(wp.vec3d(uv[0], -uv[1], wp.float64(-1.0)))


@wp.func
def camera_to_pixel(cam: FrameCameraData, vec: wp.vec3d):
    """Camera-frame direction -> pixel (col, row); NaN where the direction is not in front."""
    if vec[2] >= wp.float64(0.0):
        nan = wp.float64(wp.nan)
        return wp.vec2d(nan, nan)
    iz = wp.float64(1.0) / vec[2]
    uv = wp.vec2d(-vec[0] * iz, vec[1] * iz)
    return normalized_to_pixel(cam, distort(cam, uv))


@wp.kernel
def pixel_to_camera_kernel(
    cam: FrameCameraData, pix: wp.array(dtype=wp.vec2d), out: wp.array(dtype=wp.vec3d)
):
    i = wp.tid()
    out[i] = pixel_to_camera(cam, pix[i])


@wp.kernel
def camera_to_pixel_kernel(
    cam: FrameCameraData, vec: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec2d)
):
    i = wp.tid()
    out[i] = camera_to_pixel(cam, vec[i])
