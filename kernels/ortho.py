"""Backward (indirect) orthorectification, device code.

Per output tile, two kernels:

1. :func:`ortho_coords_kernel`: output pixel centre -> horizontal coordinates of the pose's
   frame (bilinear in a coarse grid the host transforms exactly with PROJ) -> DEM height ->
   backward projection (collinearity, refraction, distortion) -> source pixel (col, row),
   float64; NaN where there is no DEM height or the point falls outside the source image.
   It also reduces the bounding box of the valid source coordinates, so that the host reads
   exactly the source window the tile needs.
2. :func:`ortho_resample_kernel`: samples every band of that window at the source
   coordinates with nearest, bilinear, bicubic (Keys, a = -0.5) or Lanczos-3 weights, skipping
   source pixels marked invalid and renormalising the remaining weights (an output pixel whose
   valid weight is under half of the total is nodata).
"""

import warp as wp

from .camera import FrameCameraData
from .dem import DemData, dem_sample
from .frame import FramePoseData, project_point
from .refraction import RefractionTable

wp.set_module_options({"enable_backward": False})

NEAREST = wp.constant(0)
BILINEAR = wp.constant(1)
BICUBIC = wp.constant(2)
LANCZOS = wp.constant(3)


@wp.struct
class SourceWindow:
    """A window of the source image: data (bands, rows, cols) float32, valid (rows, cols)
    uint8 (1 = valid), its top-left pixel (col0, row0) in the full image, and the full image
    size (width, height) in pixels."""

    data: wp.array3d(dtype=wp.float32)
    valid: wp.array2d(dtype=wp.uint8)
    col0: wp.int32
    row0: wp.int32
    width: wp.float64
    height: wp.float64


@wp.func
def coarse_position(coarse: wp.array2d(dtype=wp.vec2d), step: wp.int32, i: wp.int32, j: wp.int32):
    """Bilinear interpolation of the coarse grid (nodes every ``step`` pixels, the last node
    at the tile's last pixel) at tile pixel (i, j)."""
    fi = wp.float64(i) / wp.float64(step)
    fj = wp.float64(j) / wp.float64(step)
    i0 = wp.min(wp.int32(fi), coarse.shape[0] - 2)
    j0 = wp.min(wp.int32(fj), coarse.shape[1] - 2)
    ai = fi - wp.float64(i0)
    aj = fj - wp.float64(j0)
    one = wp.float64(1.0)
    return (one - ai) * ((one - aj) * coarse[i0, j0] + aj * coarse[i0, j0 + 1]) + ai * (
        (one - aj) * coarse[i0 + 1, j0] + aj * coarse[i0 + 1, j0 + 1])


@wp.kernel
def ortho_coords_kernel(
    cam: FrameCameraData,
    pose: FramePoseData,
    refr: RefractionTable,
    dem: DemData,
    coarse: wp.array2d(dtype=wp.vec2d),
    step: wp.int32,
    width: wp.float64,
    height: wp.float64,
    coords: wp.array2d(dtype=wp.vec2d),
    bounds: wp.array(dtype=wp.float32),
):
    """Source pixel (col, row) of every pixel of an output tile; bounds = (min col, min row,
    -max col, -max row) of the valid ones (atomic minima)."""
    i, j = wp.tid()
    uv = coarse_position(coarse, step, i, j)
    nan = wp.float64(wp.nan)
    h = dem_sample(dem, uv[0], uv[1])
    pix = wp.vec2d(nan, nan)
    if wp.isfinite(h):
        pix = project_point(cam, pose, refr, wp.vec3d(uv[0], uv[1], h))
        zero = wp.float64(0.0)
        if not (pix[0] >= zero and pix[1] >= zero and pix[0] <= width and pix[1] <= height):
            pix = wp.vec2d(nan, nan)
    coords[i, j] = pix
    if wp.isfinite(pix[0]):
        wp.atomic_min(bounds, 0, wp.float32(pix[0]))
        wp.atomic_min(bounds, 1, wp.float32(pix[1]))
        wp.atomic_min(bounds, 2, -wp.float32(pix[0]))
        wp.atomic_min(bounds, 3, -wp.float32(pix[1]))


@wp.func
def sinc(x: wp.float64):
    if wp.abs(x) < wp.float64(1.0e-12):
        return wp.float64(1.0)
    px = wp.float64(3.141592653589793) * x
    return wp.sin(px) / px


@wp.func
def kernel_weight(method: wp.int32, t: wp.float64):
    """1-D interpolation weight at distance t (pixels) for the separable kernels."""
    a = wp.abs(t)
    one = wp.float64(1.0)
    if method == BILINEAR:
        return wp.max(one - a, wp.float64(0.0))
    if method == BICUBIC:  # Keys (1981), a = -0.5
        if a < one:
            return (wp.float64(1.5) * a - wp.float64(2.5)) * a * a + one
        if a < wp.float64(2.0):
            return ((wp.float64(-0.5) * a + wp.float64(2.5)) * a - wp.float64(4.0)) * a + wp.float64(2.0)
        return wp.float64(0.0)
    if a < wp.float64(3.0):  # Lanczos-3
        return sinc(a) * sinc(a / wp.float64(3.0))
    return wp.float64(0.0)


@wp.kernel
def ortho_resample_kernel(
    src: SourceWindow,
    coords: wp.array2d(dtype=wp.vec2d),
    method: wp.int32,
    out: wp.array3d(dtype=wp.float32),
    out_valid: wp.array2d(dtype=wp.uint8),
):
    """Resample all bands of the source window at the tile's source coordinates."""
    i, j = wp.tid()
    pix = coords[i, j]
    nb = out.shape[0]
    rows = src.data.shape[1]
    cols = src.data.shape[2]
    out_valid[i, j] = wp.uint8(0)
    if not wp.isfinite(pix[0]):
        return
    if method == NEAREST:
        c = wp.int32(wp.floor(pix[0])) - src.col0
        r = wp.int32(wp.floor(pix[1])) - src.row0
        c = wp.clamp(c, 0, cols - 1)  # the image's right/bottom edge belongs to the last pixel
        r = wp.clamp(r, 0, rows - 1)
        if src.valid[r, c] == wp.uint8(0):
            return
        for b in range(nb):
            out[b, i, j] = src.data[b, r, c]
        out_valid[i, j] = wp.uint8(1)
        return
    radius = 1
    if method == BICUBIC:
        radius = 2
    elif method == LANCZOS:
        radius = 3
    # centre-based coordinates inside the window
    x = pix[0] - wp.float64(0.5) - wp.float64(src.col0)
    y = pix[1] - wp.float64(0.5) - wp.float64(src.row0)
    x0 = wp.int32(wp.floor(x))
    y0 = wp.int32(wp.floor(y))
    wsum = wp.float64(0.0)
    wtotal = wp.float64(0.0)
    for b in range(nb):
        out[b, i, j] = wp.float32(0.0)
    for dy in range(1 - radius, radius + 1):
        wy = kernel_weight(method, y - wp.float64(y0 + dy))
        r = y0 + dy
        for dx in range(1 - radius, radius + 1):
            w = wy * kernel_weight(method, x - wp.float64(x0 + dx))
            wtotal += w
            c = x0 + dx
            if w != wp.float64(0.0) and r >= 0 and r < rows and c >= 0 and c < cols:
                if src.valid[r, c] != wp.uint8(0):
                    wsum += w
                    for b in range(nb):
                        out[b, i, j] = out[b, i, j] + wp.float32(w) * src.data[b, r, c]
    if wsum < wp.float64(0.5) * wtotal or wsum <= wp.float64(0.0):
        return
    inv = wp.float32(wp.float64(1.0) / wsum)
    for b in range(nb):
        out[b, i, j] = out[b, i, j] * inv
    out_valid[i, j] = wp.uint8(1)
