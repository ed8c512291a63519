"""Mosaic tiles on the device: ranking the images of a tile and blending them.

For one output tile, each image that has pixels in it was rendered by the ortho's tile
function (:mod:`orthowarp.kernels.ortho`). Then:

0. With feathering, :func:`edge_node_pixels_kernel` and :func:`edge_nodes_kernel`, once per
   image: at the tile's coarse-grid nodes, the distance (output pixels) of the node's image
   from the image's border.
1. :func:`mosaic_candidate_kernel`, once per image: its values balanced (gain and offset per
   band) into the tile's stack, and its rank per pixel: the signed distance (output pixels,
   negative inside) from the image's region of the seam labelling, bilinear in a window of
   the reduced grid the host computed, plus, with feathering, a fade towards the image's
   border (bilinear in the edge distance at the tile's coarse-grid nodes); +inf where the
   image has no value.
2. :func:`mosaic_blend_kernel`, one thread per pixel: the image of smallest rank (blend
   "none"), or every image within ``feather`` of it with weights falling linearly across
   that band; the weighted mean stored in the output's dtype, the mask, and the index of the
   image with the largest weight.

Multi-band blending (Burt and Adelson's multiresolution spline in Brown and Lowe's three
bands) instead: :func:`multiband_planes_kernel` (the best image and the planes to blur),
:func:`blur_axis_kernel` twice per sigma (a separable Gaussian), and
:func:`multiband_combine_kernel` (the bands, their weights, the sum).
"""

from typing import Any

import warp as wp

from .dem import DemData, dem_sample
from .ortho import CoarseGrid, node_point, store_nodata, store_pixel
from .refraction import RefractionTable
from .sensor import SENSOR_ARGS, sensor_project_xyz

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

NO_SOURCE = wp.constant(wp.uint16(65535))


@wp.struct
class ReducedWindow:
    """A window of a field on the mosaic's reduced grid (``f`` output pixels per reduced
    pixel), and where the tile lies in it."""

    field: wp.array3d(dtype=wp.float32)  # (images, rows, cols), the window of each of the tile's images
    f: wp.float32  # output pixels per reduced pixel
    r0: wp.int32  # the tile's first output row and column
    c0: wp.int32
    wr0: wp.int32  # the window's first reduced row and column
    wc0: wp.int32
    rows: wp.int32  # the reduced grid's size (positions clamped to it)
    cols: wp.int32


@wp.func
def reduced_axis(p: wp.int32, f: wp.float32, n: wp.int32, w0: wp.int32):
    """Output pixel index p -> (window index of the reduced pixel centre at or before it, the
    fraction towards the next): bilinear between reduced pixel centres, clamped at the grid's
    first and last centres."""
    y = (wp.float32(p) + wp.float32(0.5)) / f - wp.float32(0.5)
    fl = wp.floor(y)
    frac = wp.clamp(y - fl, wp.float32(0.0), wp.float32(1.0))
    if y < wp.float32(0.0):
        frac = wp.float32(0.0)
    return wp.clamp(wp.int32(fl), 0, n - 1) - w0, frac


@wp.func
def reduced_sample(win: ReducedWindow, k: wp.int32, i: wp.int32, j: wp.int32):
    """Image k's field, bilinear at the tile's pixel (i, j)."""
    iy, fy = reduced_axis(win.r0 + i, win.f, win.rows, win.wr0)
    ix, fx = reduced_axis(win.c0 + j, win.f, win.cols, win.wc0)
    a = win.field[k, iy, ix] * (wp.float32(1.0) - fy) + win.field[k, iy + 1, ix] * fy
    b = win.field[k, iy, ix + 1] * (wp.float32(1.0) - fy) + win.field[k, iy + 1, ix + 1] * fy
    return a * (wp.float32(1.0) - fx) + b * fx


@wp.func
def node_sample(nodes: wp.array3d(dtype=wp.float32), k: wp.int32, step: wp.float32, i: wp.int32, j: wp.int32):
    """Image k's values at coarse-grid nodes every ``step`` pixels from the tile's first pixel,
    bilinear at the tile's pixel (i, j)."""
    fi = wp.float32(i) / step
    fj = wp.float32(j) / step
    i0 = wp.min(wp.int32(fi), nodes.shape[1] - 2)
    j0 = wp.min(wp.int32(fj), nodes.shape[2] - 2)
    ai = fi - wp.float32(i0)
    aj = fj - wp.float32(j0)
    a = nodes[k, i0, j0] * (wp.float32(1.0) - aj) + nodes[k, i0, j0 + 1] * aj
    b = nodes[k, i0 + 1, j0] * (wp.float32(1.0) - aj) + nodes[k, i0 + 1, j0 + 1] * aj
    return a * (wp.float32(1.0) - ai) + b * ai


@wp.kernel
def edge_node_pixels_kernel(
    arg: Any,
    refr: RefractionTable,
    dem: DemData,
    grid: CoarseGrid,
    pixels: wp.array2d(dtype=wp.vec2d),
):
    """Source pixel (col, row) of each coarse-grid node's ground point at its DEM height (NaN
    off the DEM and where the sensor does not see the point)."""
    i, j = wp.tid()
    uv = grid.uv[i, j]
    h = dem_sample(dem, uv[0], uv[1])
    if wp.isfinite(h):
        pixels[i, j] = sensor_project_xyz(arg, refr, node_point(grid, i, j, h), h, wp.float64(0.0))
    else:
        pixels[i, j] = wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))


@wp.func
def add_step(acc: wp.vec2d, pixels: wp.array2d(dtype=wp.vec2d), p: wp.vec2d, i: wp.int32, j: wp.int32):
    """``acc`` + (the distance in source pixels from ``p`` to node (i, j)'s pixel, 1) where
    that node exists and the distance is finite, else ``acc``."""
    if i < 0 or j < 0 or i >= pixels.shape[0] or j >= pixels.shape[1]:
        return acc
    s = wp.length(pixels[i, j] - p)
    if wp.isfinite(s):
        return acc + wp.vec2d(s, wp.float64(1.0))
    return acc


@wp.kernel
def edge_nodes_kernel(
    pixels: wp.array2d(dtype=wp.vec2d),
    width: wp.float64,
    height: wp.float64,
    step: wp.float64,
    k: wp.int32,
    edge: wp.array3d(dtype=wp.float32),
):
    """``edge[k]`` at each coarse-grid node (nodes every ``step`` output pixels): the distance
    of the node's pixel (``pixels``, :func:`edge_node_pixels_kernel`) from the border of the
    image (``width`` x ``height`` pixels; negative outside), in output pixels: divided by the
    local scale, the mean length of the steps to the node's finite neighbours (source pixels)
    over ``step`` (1 where it has none). 0 where the node's pixel is NaN."""
    i, j = wp.tid()
    p = pixels[i, j]
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1])):
        edge[k, i, j] = wp.float32(0.0)
        return
    d = wp.min(wp.min(p[0], width - p[0]), wp.min(p[1], height - p[1]))
    acc = wp.vec2d(wp.float64(0.0), wp.float64(0.0))  # (sum of the steps, their count)
    acc = add_step(acc, pixels, p, i, j + 1)
    acc = add_step(acc, pixels, p, i, j - 1)
    acc = add_step(acc, pixels, p, i + 1, j)
    acc = add_step(acc, pixels, p, i - 1, j)
    scale = wp.float64(1.0)
    if acc[0] > wp.float64(0.0):
        scale = acc[0] / (acc[1] * step)
    edge[k, i, j] = wp.float32(d / scale)


for _arg in SENSOR_ARGS:
    wp.overload(edge_node_pixels_kernel, {"arg": _arg})


@wp.kernel
def mosaic_candidate_kernel(
    values: wp.array3d(dtype=Any),
    valid: wp.array2d(dtype=wp.uint8),
    gains: wp.array2d(dtype=wp.float32),
    offsets: wp.array2d(dtype=wp.float32),
    image: wp.int32,
    dist: ReducedWindow,
    edge: wp.array3d(dtype=wp.float32),
    edge_step: wp.float32,
    fade: wp.int32,
    feather: wp.float32,
    k: wp.int32,
    stack: wp.array4d(dtype=wp.float32),
    rank: wp.array3d(dtype=wp.float32),
):
    """The tile's k-th image (``image`` among the mosaic's): its values balanced by
    ``gains[image]`` and ``offsets[image]`` (images, bands) into ``stack[k]`` (th, tw, bands)
    and its rank into ``rank[k]`` (th, tw). ``edge[k]`` (coarse nodes every ``edge_step``
    pixels, see :func:`edge_nodes_kernel`): distance of the pixel's image from the image's
    border, output pixels; with ``fade`` (1) the rank gets ``feather`` * (1 - edge /
    ``feather``), clipped to [0, feather]: the image fades out over ``feather`` pixels."""
    i, j = wp.tid()
    if valid[i, j] == wp.uint8(0):
        rank[k, i, j] = wp.float32(wp.inf)
        for b in range(stack.shape[3]):
            stack[k, i, j, b] = wp.float32(0.0)
        return
    r = reduced_sample(dist, k, i, j)
    if fade != 0:
        e = node_sample(edge, k, edge_step, i, j)
        r = r + feather * wp.clamp(wp.float32(1.0) - e / feather, wp.float32(0.0), wp.float32(1.0))
    rank[k, i, j] = r
    for b in range(stack.shape[3]):
        stack[k, i, j, b] = wp.float32(values[i, j, b]) * gains[image, b] + offsets[image, b]


@wp.func
def blend_weight(e: wp.float32, lo: wp.float32, k: wp.int32, best: wp.int32, feather: wp.float32, hard: wp.int32):
    if not (e < wp.float32(wp.inf)):
        return wp.float32(0.0)
    if hard != 0:
        if k == best:
            return wp.float32(1.0)
        return wp.float32(0.0)
    return wp.clamp(wp.float32(1.0) - (e - lo) / feather, wp.float32(0.0), wp.float32(1.0))


@wp.func
def smallest_rank(rank: wp.array3d(dtype=wp.float32), n: wp.int32, i: wp.int32, j: wp.int32):
    """(the image of smallest rank at pixel (i, j), the first of equals, -1 where none of the
    ``n`` has a value (+inf); that rank)."""
    lo = wp.float32(wp.inf)
    arg = wp.int32(-1)
    for k in range(n):
        e = rank[k, i, j]
        if e < lo:
            lo = e
            arg = k
    return arg, lo


@wp.kernel
def mosaic_blend_kernel(
    stack: wp.array4d(dtype=wp.float32),
    rank: wp.array3d(dtype=wp.float32),
    images: wp.array1d(dtype=wp.int32),
    n: wp.int32,
    feather: wp.float32,
    hard: wp.int32,
    top: wp.float32,
    out: wp.array3d(dtype=Any),
    valid: wp.array2d(dtype=wp.uint8),
    source: wp.array2d(dtype=wp.uint16),
):
    """One output pixel from the tile's ``n`` images (see the module's description): ``hard``
    != 0 takes the image of smallest rank alone; ``top`` as for
    :func:`~orthowarp.kernels.ortho.store_pixel`; ``source`` gets ``images[k]`` of the image
    with the largest weight (the first of equals), NO_SOURCE where none has a value."""
    i, j = wp.tid()
    best, lo = smallest_rank(rank, n, i, j)
    total = wp.float32(0.0)
    wmax = wp.float32(0.0)
    arg = wp.int32(-1)
    if best >= 0:
        for k in range(n):
            w = blend_weight(rank[k, i, j], lo, k, best, feather, hard)
            total += w
            if w > wmax:
                wmax = w
                arg = k
    if total <= wp.float32(0.0):
        store_nodata(out, valid, i, j, top)
        source[i, j] = NO_SOURCE
        return
    for b in range(out.shape[2]):
        acc = wp.float32(0.0)
        for k in range(n):
            w = blend_weight(rank[k, i, j], lo, k, best, feather, hard)
            if w > wp.float32(0.0):
                acc += w * stack[k, i, j, b]
        store_pixel(out, i, j, b, acc / total, top)
    valid[i, j] = wp.uint8(1)
    source[i, j] = wp.uint16(images[arg])


@wp.kernel
def mosaic_fill_kernel(
    out: wp.array3d(dtype=Any),
    valid: wp.array2d(dtype=wp.uint8),
    source: wp.array2d(dtype=wp.uint16),
    part: wp.array3d(dtype=Any),
    part_valid: wp.array2d(dtype=wp.uint8),
    part_source: wp.array2d(dtype=wp.uint16),
    r0: wp.int32,
    c0: wp.int32,
):
    """Where the tile (``out``, ``valid``, ``source``) has no value, the value of ``part``, a
    block of it whose first pixel is (r0, c0) of the tile, where that has one."""
    i, j = wp.tid()
    if valid[r0 + i, c0 + j] != wp.uint8(0) or part_valid[i, j] == wp.uint8(0):
        return
    for b in range(out.shape[2]):
        out[r0 + i, c0 + j, b] = part[i, j, b]
    valid[r0 + i, c0 + j] = wp.uint8(1)
    source[r0 + i, c0 + j] = part_source[i, j]


@wp.kernel
def fallback_need_kernel(
    valid: wp.array2d(dtype=wp.uint8),
    cover: wp.array2d(dtype=wp.uint8),
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    block: wp.int32,
    marked: wp.array2d(dtype=wp.int32),
):
    """The ``block`` x ``block`` pixel blocks of a tile (``marked``, set to 1) that hold a
    pixel without a value (``valid`` 0) where ``cover`` is set: the reduced labelling's cover,
    grown by one reduced pixel, on the tile's window, at the window row and column of each
    tile row and column (``rows``, ``cols``)."""
    i, j = wp.tid()
    if valid[i, j] != wp.uint8(0):
        return
    if cover[rows[i], cols[j]] != wp.uint8(0):
        marked[i // block, j // block] = 1


@wp.kernel
def count_sources_kernel(source: wp.array2d(dtype=wp.uint16), counts: wp.array(dtype=wp.int64)):
    """Per row of a tile's source index (one thread each): its pixels of each image added to
    ``counts`` (images,), one atomic add per run of equal values along the row; NO_SOURCE
    pixels are not counted."""
    i = wp.tid()
    cur = source[i, 0]
    run = wp.int64(0)
    for j in range(source.shape[1]):
        v = source[i, j]
        if v != cur:
            if cur != NO_SOURCE:
                wp.atomic_add(counts, wp.int32(cur), run)
            cur = v
            run = wp.int64(0)
        run += wp.int64(1)
    if cur != NO_SOURCE:
        wp.atomic_add(counts, wp.int32(cur), run)


@wp.kernel
def multiband_planes_kernel(stack: wp.array4d(dtype=wp.float32), rank: wp.array3d(dtype=wp.float32),
                            planes: wp.array3d(dtype=wp.float32), best: wp.array2d(dtype=wp.int32)):
    """Multi-band blending, step 1, per pixel of the tile grown by the halo: ``best``, the
    image of smallest rank (the first of equals; -1 where no image has a value), and per
    image k the planes that the blurs take, k (bands + 2) + b: its balanced value of band b
    where it has a value, else 0; k (bands + 2) + bands: 1 where it has a value, else 0; k
    (bands + 2) + bands + 1: 1 where it is the best image, else 0."""
    i, j = wp.tid()
    n = rank.shape[0]
    nb = stack.shape[3]
    arg, lo = smallest_rank(rank, n, i, j)
    best[i, j] = arg
    for k in range(n):
        base = k * (nb + 2)
        ok = rank[k, i, j] < wp.float32(wp.inf)
        for b in range(nb):
            v = wp.float32(0.0)
            if ok:
                v = stack[k, i, j, b]
            planes[base + b, i, j] = v
        planes[base + nb, i, j] = wp.where(ok, wp.float32(1.0), wp.float32(0.0))
        planes[base + nb + 1, i, j] = wp.where(k == arg, wp.float32(1.0), wp.float32(0.0))


@wp.kernel
def blur_axis_kernel(src: wp.array3d(dtype=wp.float32), weights: wp.array(dtype=wp.float32), axis: wp.int32,
                     dst: wp.array3d(dtype=wp.float32)):
    """One pass of a separable blur: each plane of ``src`` correlated along ``axis`` (1 rows,
    2 columns) with ``weights`` (odd length, centred), the edge pixel repeated beyond the
    array (SciPy's mode "nearest")."""
    p, i, j = wp.tid()
    radius = weights.shape[0] // 2
    acc = wp.float32(0.0)
    for t in range(weights.shape[0]):
        if axis == 1:
            acc += weights[t] * src[p, wp.clamp(i + t - radius, 0, src.shape[1] - 1), j]
        else:
            acc += weights[t] * src[p, i, wp.clamp(j + t - radius, 0, src.shape[2] - 1)]
    dst[p, i, j] = acc


@wp.func
def band_low(blurred: wp.array3d(dtype=wp.float32), base: wp.int32, b: wp.int32, nb: wp.int32, i: wp.int32,
             j: wp.int32):
    """An image's band b blurred and normalised by its blurred valid pixels (NaN where that
    is 1e-6 or less)."""
    norm = blurred[base + nb, i, j]
    if norm > wp.float32(1e-6):
        return blurred[base + b, i, j] / norm
    return wp.float32(wp.nan)


@wp.func
def finite_or_zero(v: wp.float32):
    if wp.isfinite(v):
        return v
    return wp.float32(0.0)


@wp.kernel
def multiband_combine_kernel(
    planes: wp.array3d(dtype=wp.float32),
    mid: wp.array3d(dtype=wp.float32),
    low: wp.array3d(dtype=wp.float32),
    best: wp.array2d(dtype=wp.int32),
    images: wp.array1d(dtype=wp.int32),
    halo: wp.int32,
    top: wp.float32,
    out: wp.array3d(dtype=Any),
    valid: wp.array2d(dtype=wp.uint8),
    source: wp.array2d(dtype=wp.uint16),
):
    """Multi-band blending, step 2, per pixel of the inner tile (the grown tile less ``halo``
    on each side), from :func:`multiband_planes_kernel`'s ``planes`` and their blurs at the
    middle (``mid``) and the low band's sigma (``low``): per image the high band (value minus
    its normalised ``mid`` blur), the middle band (that minus the normalised ``low`` blur) and
    the low band (the latter), NaN parts taken as 0; each band averaged over the images with
    the best image's one-hot weight (high band), or its blur (middle, low), where the image
    has a value; the three bands added, stored as :func:`~orthowarp.kernels.ortho.store_pixel`
    does; ``source`` gets ``images`` of the best image, NO_SOURCE where none has a value."""
    i, j = wp.tid()
    gi = i + halo
    gj = j + halo
    arg = best[gi, gj]
    if arg < 0:
        store_nodata(out, valid, i, j, top)
        source[i, j] = NO_SOURCE
        return
    n = images.shape[0]
    nb = out.shape[2]
    for b in range(nb):
        # per band level (high, middle, low): the weighted sum and the sum of the weights
        num = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        total = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        for k in range(n):
            base = k * (nb + 2)
            if planes[base + nb, gi, gj] > wp.float32(0.0):
                lo1 = band_low(mid, base, b, nb, gi, gj)
                lo2 = band_low(low, base, b, nb, gi, gj)
                w = wp.vec3d(wp.float64(planes[base + nb + 1, gi, gj]), wp.float64(mid[base + nb + 1, gi, gj]),
                             wp.float64(low[base + nb + 1, gi, gj]))
                part = wp.vec3d(wp.float64(finite_or_zero(planes[base + b, gi, gj] - lo1)),
                                wp.float64(finite_or_zero(lo1 - lo2)), wp.float64(finite_or_zero(lo2)))
                num += wp.cw_mul(w, part)
                total += w
        acc = wp.float64(0.0)
        for level in range(3):
            if total[level] > wp.float64(0.0):
                acc += num[level] / total[level]
            else:
                acc = wp.float64(wp.nan)
        store_pixel(out, i, j, b, wp.float32(acc), top)
    valid[i, j] = wp.uint8(1)
    source[i, j] = wp.uint16(images[arg])


# the output dtypes (uint8, uint16, float32), built at import: an overload made at a launch
# would change the module under the threads launching from it
for _t in (wp.uint8, wp.uint16, wp.float32):
    wp.overload(multiband_combine_kernel, {"out": wp.array3d(dtype=_t)})
    wp.overload(mosaic_candidate_kernel, {"values": wp.array3d(dtype=_t)})
    wp.overload(mosaic_blend_kernel, {"out": wp.array3d(dtype=_t)})
    wp.overload(mosaic_fill_kernel, {"out": wp.array3d(dtype=_t), "part": wp.array3d(dtype=_t)})
