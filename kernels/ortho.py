"""Backward (indirect) orthorectification, device code.

Backward (default), per output tile:

1. :func:`node_pixels_kernel`: the source pixels of
   the nodes of the tile's coarse grid at the lowest and the highest DEM height under the
   tile. Each output pixel's ground point lies on the vertical between those heights of a
   point inside a grid cell, so its source pixel lies in the nodes' bounding box (grown by a
   margin for the projection's curvature within a cell): the host reads that window.
2. :func:`ortho_kernel`, one thread per output pixel: pixel
   centre -> horizontal coordinates of the pose's frame (bilinear in the coarse grid the host
   transforms exactly with PROJ) -> DEM height -> backward projection (collinearity,
   refraction, distortion; or the pushbroom's line-time iteration; or an RPC image's closed
   form) -> source pixel (col,
   row), float64; NaN where there is no DEM height or the point falls outside the image ->
   :func:`resample_at`: every band of the window (read in its own dtype) sampled with
   nearest, bilinear, bicubic (Keys, a = -0.5) or Lanczos-3 weights, skipping source pixels
   marked invalid and renormalising the remaining weights (an output pixel whose valid
   weight is under half of the total is nodata), stored in the output's dtype,
   pixel-interleaved, as the file wants it. The source coordinates never leave registers.

Forward ([P3]'s direct method): :func:`forward_nodes_kernel` runs the forward chain for
every source pixel of the window that maps into the tile, and :func:`forward_scatter_kernel`
inverts that map quad by quad into per-output-pixel source coordinates, which
:func:`ortho_resample_kernel` resamples with the same :func:`resample_at`.
"""

from typing import Any

import warp as wp

from .camera import FrameCameraData, camera_to_pixel
from .dem import DemData, dem_sample
from .geodesy import geodetic_to_ecef
from .pushbroom import PushbroomData, pb_line_time, pb_project
from .ray import apparent_direction
from .orthoimage import OrthoData, ortho_pixel
from .rpc import RpcData, rpc_pixel
from .refraction import RefractionTable
from .ray import SearchParams
from .sensor import SENSOR_ARGS, FrameArg, sensor_geolocate, sensor_project_xyz

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

# threads per block of the per-pixel kernels (a CUDA module is built per block size, so the
# module is loaded with it as well as with Warp's default): on an H100, 128 ran a few per cent
# faster than Warp's default 256 (bench/ortho.py's block-size scan)
BLOCK_DIM = 128

NEAREST = wp.constant(0)
BILINEAR = wp.constant(1)
BICUBIC = wp.constant(2)
LANCZOS = wp.constant(3)


@wp.struct
class SourceWindow:
    """Where a window of the source image lies: valid (rows, cols) uint8 (1 = valid; read only
    when ``masked`` is non-zero, else every pixel is valid), its top-left pixel (col0, row0) in
    the full image, and its pixels per image pixel (inv_sx, inv_sy: 1, or less for a window
    read reduced). The window's pixels travel beside the struct as an array (bands, rows,
    cols) of the source's own dtype."""

    valid: wp.array2d(dtype=wp.uint8)
    masked: wp.int32
    col0: wp.int32
    row0: wp.int32
    inv_sx: wp.float64
    inv_sy: wp.float64


@wp.func
def grid_cell(rows: wp.int32, cols: wp.int32, fi: wp.float64, fj: wp.float64):
    """The cell (i0, j0) of a rows x cols grid that bilinear interpolation at fractional
    (row, col) index (fi, fj) uses (a border cell outside the grid: linear extrapolation),
    and the fractions (ai, aj) within it."""
    i0 = wp.clamp(wp.int32(wp.floor(fi)), 0, rows - 2)
    j0 = wp.clamp(wp.int32(wp.floor(fj)), 0, cols - 2)
    return i0, j0, fi - wp.float64(i0), fj - wp.float64(j0)


@wp.func
def grid_lerp(grid: wp.array2d(dtype=Any), i0: wp.int32, j0: wp.int32, ai: wp.float64, aj: wp.float64):
    """Bilinear interpolation of a grid of vec2d / vec3d / float64 in cell (i0, j0) at
    fractions (ai, aj)."""
    one = wp.float64(1.0)
    return (one - ai) * ((one - aj) * grid[i0, j0] + aj * grid[i0, j0 + 1]) + ai * (
        (one - aj) * grid[i0 + 1, j0] + aj * grid[i0 + 1, j0 + 1])


@wp.func
def grid_bilinear(grid: wp.array2d(dtype=Any), fi: wp.float64, fj: wp.float64):
    """Bilinear interpolation of a grid at fractional (row, col) index (fi, fj), extrapolating
    linearly from the border cells outside it."""
    i0, j0, ai, aj = grid_cell(grid.shape[0], grid.shape[1], fi, fj)
    return grid_lerp(grid, i0, j0, ai, aj)


@wp.struct
class CoarseGrid:
    """Nodes every ``step`` output pixels of a tile (the last at or past its last pixel):
    uv, the horizontal coordinates of the pose's frame (lon, lat in degrees for geocentric
    poses, else map x, y), transformed exactly on the host; for geocentric poses also xyz0,
    the ECEF point (m) of (lon, lat) on the ellipsoid, and up, its unit normal, so that a
    pixel's ECEF point at height h is xyz0 + h up (exact for the ellipsoid; interpolating
    over a cell of size s costs ~ s^2 / 8R, 5e-8 m at s = 1.6 m) without float64 sines.

    For a frame camera the nodes also carry that line in the camera frame: cam_a =
    R^T (x(0) - C) and cam_b = R^T dx/dh (R, C: the pose's rotation and projection centre;
    dx/dh = up, or (0, 0, 1) for map poses), with cam_up = R^T up(C): a pixel's camera-frame
    chord is a + h b, interpolated like the rest (exactly: the map is affine), with no
    rotation or subtraction per pixel.

    With ``refr_nodes`` set (see :func:`frame_node_refraction_kernel`), the refraction turn
    of that chord is interpolated too: refr_a + h refr_b is the correction that
    :func:`~orthowarp.kernels.ray.apparent_direction` adds to the chord at the node, as a
    line through its values at the two heights that bound the tile's DEM. The correction is
    |v| delta (~0.1 m from an aircraft) and smooth: over a cell of 16 output pixels and a
    height range of hundreds of metres the interpolation moves the chord by micrometres
    (tests/test_ortho.py measures it against the per-pixel turn), and spares per pixel the
    refraction table's lookup and the turn's arithmetic (a third of the CPU kernel's time).
    Off (0) the kernel turns every pixel's chord itself.

    For a pushbroom scene ``times`` holds each node's line time (s), the first guess of the
    per-pixel line-time iteration (:func:`pb_node_times_kernel`)."""

    uv: wp.array2d(dtype=wp.vec2d)
    xyz0: wp.array2d(dtype=wp.vec3d)
    up: wp.array2d(dtype=wp.vec3d)
    cam_a: wp.array2d(dtype=wp.vec3d)
    cam_b: wp.array2d(dtype=wp.vec3d)
    cam_up: wp.vec3d
    refr_a: wp.array2d(dtype=wp.vec3d)
    refr_b: wp.array2d(dtype=wp.vec3d)
    refr_nodes: wp.int32
    times: wp.array2d(dtype=wp.float64)
    step: wp.float64
    geocentric: wp.int32


@wp.func
def grid_ground(grid: CoarseGrid, dem: DemData, fi: wp.float64, fj: wp.float64):
    """The ground point at fractional grid index (fi, fj): its position in the pose's
    Cartesian frame (ECEF for geocentric grids: x0 + h up; else map x, y, h) and its DEM
    height h (NaN off the DEM)."""
    i0, j0, ai, aj = grid_cell(grid.uv.shape[0], grid.uv.shape[1], fi, fj)  # one cell for all three grids
    uv = grid_lerp(grid.uv, i0, j0, ai, aj)
    h = dem_sample(dem, uv[0], uv[1])
    x = wp.vec3d(uv[0], uv[1], h)
    if grid.geocentric != 0:
        x = grid_lerp(grid.xyz0, i0, j0, ai, aj) + h * grid_lerp(grid.up, i0, j0, ai, aj)
    return x, h


@wp.func
def in_image(pix: wp.vec2d, width: wp.float64, height: wp.float64):
    """pix where it lies on the image (0 <= col <= width, 0 <= row <= height), else NaN."""
    zero = wp.float64(0.0)
    if pix[0] >= zero and pix[1] >= zero and pix[0] <= width and pix[1] <= height:
        return pix
    return wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))


@wp.func
def frame_source_pixel(cam: FrameCameraData, refr: RefractionTable, dem: DemData, grid: CoarseGrid, i: wp.int32,
                       j: wp.int32, width: wp.float64, height: wp.float64):
    """Source pixel (col, row) of output-tile pixel (i, j) by the frame's backward chain, in
    the camera frame (the pose is in the grid: see :class:`CoarseGrid`); NaN where there is no
    DEM height or the point falls outside the image."""
    i0, j0, ai, aj = grid_cell(grid.uv.shape[0], grid.uv.shape[1], wp.float64(i) / grid.step,
                               wp.float64(j) / grid.step)
    uv = grid_lerp(grid.uv, i0, j0, ai, aj)
    h = dem_sample(dem, uv[0], uv[1])
    if not wp.isfinite(h):
        return wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))
    v = grid_lerp(grid.cam_a, i0, j0, ai, aj) + h * grid_lerp(grid.cam_b, i0, j0, ai, aj)
    if refr.enabled != 0 and grid.refr_nodes != 0:
        v = v + grid_lerp(grid.refr_a, i0, j0, ai, aj) + h * grid_lerp(grid.refr_b, i0, j0, ai, aj)
    else:
        v = apparent_direction(refr, grid.cam_up, v, h)
    return in_image(camera_to_pixel(cam, v), width, height)


@wp.func
def pb_source_pixel(pb: PushbroomData, refr: RefractionTable, dem: DemData, grid: CoarseGrid, i: wp.int32,
                    j: wp.int32, width: wp.float64, height: wp.float64):
    """:func:`frame_source_pixel` for a pushbroom scene: the line time is solved from the
    coarse grid's interpolated time (``grid.times``, s)."""
    fi = wp.float64(i) / grid.step
    fj = wp.float64(j) / grid.step
    x, h = grid_ground(grid, dem, fi, fj)
    if not wp.isfinite(h):
        return wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))
    t0 = grid_bilinear(grid.times, fi, fj)
    if not wp.isfinite(t0):
        t0 = wp.float64(0.0)
    return in_image(pb_project(pb, refr, x, h, t0), width, height)


@wp.func
def source_pixel(arg: FrameArg, refr: RefractionTable, dem: DemData, grid: CoarseGrid, i: wp.int32, j: wp.int32,
                 width: wp.float64, height: wp.float64):
    """Source pixel of output-tile pixel (i, j) (see :class:`CoarseGrid`): a frame's."""
    return frame_source_pixel(arg.cam, refr, dem, grid, i, j, width, height)


@wp.func
def source_pixel(arg: PushbroomData, refr: RefractionTable, dem: DemData, grid: CoarseGrid, i: wp.int32,
                 j: wp.int32, width: wp.float64, height: wp.float64):
    """Source pixel of output-tile pixel (i, j): a pushbroom scene's."""
    return pb_source_pixel(arg, refr, dem, grid, i, j, width, height)


@wp.func
def rpc_source_pixel(r: RpcData, dem: DemData, grid: CoarseGrid, i: wp.int32, j: wp.int32, width: wp.float64,
                     height: wp.float64):
    """:func:`frame_source_pixel` for an RPC image: the RPCs' closed form at the pixel's
    longitude, latitude (the grid's uv) and DEM height (no refraction: the RPCs hold it)."""
    i0, j0, ai, aj = grid_cell(grid.uv.shape[0], grid.uv.shape[1], wp.float64(i) / grid.step,
                               wp.float64(j) / grid.step)
    uv = grid_lerp(grid.uv, i0, j0, ai, aj)
    h = dem_sample(dem, uv[0], uv[1])
    if not wp.isfinite(h):
        return wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))
    return in_image(rpc_pixel(r, uv[0], uv[1], h), width, height)


@wp.func
def source_pixel(arg: RpcData, refr: RefractionTable, dem: DemData, grid: CoarseGrid, i: wp.int32, j: wp.int32,
                 width: wp.float64, height: wp.float64):
    """Source pixel of output-tile pixel (i, j): an RPC image's."""
    return rpc_source_pixel(arg, dem, grid, i, j, width, height)


@wp.func
def source_pixel(arg: OrthoData, refr: RefractionTable, dem: DemData, grid: CoarseGrid, i: wp.int32, j: wp.int32,
                 width: wp.float64, height: wp.float64):
    """Source pixel of output-tile pixel (i, j): an orthoimage's, by the inverse geotransform
    at the pixel's horizontal coordinates in the image's CRS (the grid's uv; no height)."""
    uv = grid_bilinear(grid.uv, wp.float64(i) / grid.step, wp.float64(j) / grid.step)
    return in_image(ortho_pixel(arg, uv[0], uv[1]), width, height)


@wp.func
def node_point(grid: CoarseGrid, i: wp.int32, j: wp.int32, h: wp.float64):
    """The point of coarse node (i, j) at height h in the pose's Cartesian frame."""
    uv = grid.uv[i, j]
    if grid.geocentric != 0:
        return grid.xyz0[i, j] + h * grid.up[i, j]
    return wp.vec3d(uv[0], uv[1], h)


@wp.kernel
def coarse_fields_kernel(uv: wp.array2d(dtype=wp.vec2d), geocentric: wp.int32, has_pose: wp.int32,
                         center: wp.vec3d, rot: wp.mat33d, xyz0: wp.array2d(dtype=wp.vec3d),
                         up: wp.array2d(dtype=wp.vec3d), cam_a: wp.array2d(dtype=wp.vec3d),
                         cam_b: wp.array2d(dtype=wp.vec3d)):
    """A :class:`CoarseGrid`'s fields from its nodes' uv (float64): for ``geocentric`` grids
    (uv = longitude, latitude in degrees) xyz0, the ECEF point on the ellipsoid, and up, its
    unit normal; with ``has_pose`` (a frame camera of centre ``center`` and rotation ``rot``,
    camera to the pose's frame) cam_a = rot^T (x(0) - center) and cam_b = rot^T up, where
    x(0) and up are the point at height 0 and the vertical ((0, 0, 1) for map frames)."""
    i, j = wp.tid()
    p = uv[i, j]
    x0 = wp.vec3d(p[0], p[1], wp.float64(0.0))
    n = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0))
    if geocentric != 0:
        lat = wp.radians(p[1])
        lon = wp.radians(p[0])
        x0 = geodetic_to_ecef(lat, lon, wp.float64(0.0))
        n = wp.vec3d(wp.cos(lat) * wp.cos(lon), wp.cos(lat) * wp.sin(lon), wp.sin(lat))
        xyz0[i, j] = x0
        up[i, j] = n
    if has_pose != 0:
        rt = wp.transpose(rot)
        cam_a[i, j] = rt * (x0 - center)
        cam_b[i, j] = rt * n


@wp.kernel
def frame_node_refraction_kernel(refr: RefractionTable, grid: CoarseGrid, heights: wp.vec2d,
                                 refr_a: wp.array2d(dtype=wp.vec3d), refr_b: wp.array2d(dtype=wp.vec3d)):
    """The refraction correction of each node's camera-frame chord as a line in the height:
    refr_a + h refr_b through the corrections that :func:`apparent_direction` gives at the two
    heights (at least 1 m apart) that bound the tile's DEM (see :class:`CoarseGrid`)."""
    i, j = wp.tid()
    h1 = heights[0]
    h2 = wp.max(heights[1], h1 + wp.float64(1.0))
    a = grid.cam_a[i, j]
    b = grid.cam_b[i, j]
    v1 = a + h1 * b
    v2 = a + h2 * b
    c1 = apparent_direction(refr, grid.cam_up, v1, h1) - v1
    c2 = apparent_direction(refr, grid.cam_up, v2, h2) - v2
    slope = (c2 - c1) / (h2 - h1)
    refr_a[i, j] = c1 - h1 * slope
    refr_b[i, j] = slope


@wp.kernel
def node_pixels_kernel(
    arg: Any,
    refr: RefractionTable,
    grid: CoarseGrid,
    heights: wp.vec2d,
    pixels: wp.array3d(dtype=wp.vec2d),
):
    """Source pixel of every node of a tile's coarse grid at the two heights (k = 0, 1) that
    bound the tile's DEM: the tile's source pixels lie in their bounding box, but for the
    curvature of the projection within a grid cell (NaN where the sensor does not see the
    node: behind a frame camera, outside a scene's ephemeris)."""
    k, i, j = wp.tid()
    h = heights[k]
    pixels[k, i, j] = sensor_project_xyz(arg, refr, node_point(grid, i, j, h), h, wp.float64(0.0))


@wp.func
def node_step(a: wp.vec2d, b: wp.vec2d) -> wp.float64:
    """The distance between two nodes' source pixels (NaN where either has none)."""
    dx = b[0] - a[0]
    dy = b[1] - a[1]
    return wp.sqrt(dx * dx + dy * dy)


@wp.kernel
def node_window_rows_kernel(pixels: wp.array3d(dtype=wp.vec2d), part: wp.array3d(dtype=wp.float64)):
    """What a tile's source window and read reduction take from its node pixels (2, rows,
    cols), per height k and row i, over the row's nodes (``part[k, i]``): 0-3 the finite
    nodes' smallest column and row and largest column and row (+inf / -inf where none), 4
    their count, 5 the largest step from a node to its right or lower neighbour (both
    finite; -1 where none), 6 and 7 the smallest step to the lower and to the right
    neighbour (+inf where none). The host reduces the rows (see ``pipeline.ortho.tiles``)."""
    k, i = wp.tid()
    rows = pixels.shape[1]
    cols = pixels.shape[2]
    inf = wp.float64(wp.inf)
    lo_c = inf
    lo_r = inf
    hi_c = -inf
    hi_r = -inf
    count = wp.float64(0.0)
    big = wp.float64(-1.0)
    down = inf
    right = inf
    for j in range(cols):
        p = pixels[k, i, j]
        if wp.isfinite(p[0]) and wp.isfinite(p[1]):
            lo_c = wp.min(lo_c, p[0])
            lo_r = wp.min(lo_r, p[1])
            hi_c = wp.max(hi_c, p[0])
            hi_r = wp.max(hi_r, p[1])
            count += wp.float64(1.0)
            if j + 1 < cols:
                s = node_step(p, pixels[k, i, j + 1])
                if wp.isfinite(s):
                    big = wp.max(big, s)
                    right = wp.min(right, s)
            if i + 1 < rows:
                s = node_step(p, pixels[k, i + 1, j])
                if wp.isfinite(s):
                    big = wp.max(big, s)
                    down = wp.min(down, s)
    part[k, i, 0] = lo_c
    part[k, i, 1] = lo_r
    part[k, i, 2] = hi_c
    part[k, i, 3] = hi_r
    part[k, i, 4] = count
    part[k, i, 5] = big
    part[k, i, 6] = down
    part[k, i, 7] = right


@wp.kernel
def pb_node_times_kernel(
    pb: PushbroomData,
    refr: RefractionTable,
    dem: DemData,
    grid: CoarseGrid,
    h_default: wp.float64,
    times: wp.array2d(dtype=wp.float64),
):
    """Line time (s) of every node of a pushbroom tile's coarse grid (at its DEM height, or
    h_default off the DEM), the first guess of the per-pixel iteration; NaN where none."""
    i, j = wp.tid()
    uv = grid.uv[i, j]
    h = dem_sample(dem, uv[0], uv[1])
    if not wp.isfinite(h):
        h = h_default
    pix = pb_project(pb, refr, node_point(grid, i, j, h), h, wp.float64(0.0))
    times[i, j] = pb_line_time(pb, pix[1])


@wp.func
def sinc(x: wp.float32):
    if wp.abs(x) < wp.float32(1.0e-6):
        return wp.float32(1.0)
    px = wp.float32(3.14159265358979) * x
    return wp.sin(px) / px


@wp.func
def kernel_weight(method: wp.int32, t: wp.float32):
    """1-D interpolation weight at distance t (pixels) for the separable kernels (float32:
    the fraction t comes from float64 coordinates, and the weights need no more than the
    data's precision)."""
    a = wp.abs(t)
    one = wp.float32(1.0)
    if method == BILINEAR:
        return wp.max(one - a, wp.float32(0.0))
    if method == BICUBIC:  # Keys (1981), a = -0.5
        if a < one:
            return (wp.float32(1.5) * a - wp.float32(2.5)) * a * a + one
        if a < wp.float32(2.0):
            return ((wp.float32(-0.5) * a + wp.float32(2.5)) * a - wp.float32(4.0)) * a + wp.float32(2.0)
        return wp.float32(0.0)
    if a < wp.float32(3.0):  # Lanczos-3
        return sinc(a) * sinc(a / wp.float32(3.0))
    return wp.float32(0.0)


@wp.func
def store_pixel(out: wp.array3d(dtype=Any), i: wp.int32, j: wp.int32, b: wp.int32, v: wp.float32, top: wp.float32):
    """Band b of output pixel (i, j): for integer outputs (top > 0) v rounded half to even and
    clipped to [0, top]; float outputs take v as it is."""
    if top > wp.float32(0.0):
        v = wp.clamp(wp.rint(v), wp.float32(0.0), top)
    out[i, j, b] = out.dtype(v)


@wp.func
def store_nodata(out: wp.array3d(dtype=Any), valid: wp.array2d(dtype=wp.uint8), i: wp.int32, j: wp.int32,
                 top: wp.float32):
    """An output pixel without data: 0 in integer outputs (the mask says it), NaN in float ones."""
    v = wp.float32(wp.nan)
    if top > wp.float32(0.0):
        v = wp.float32(0.0)
    for b in range(out.shape[2]):
        out[i, j, b] = out.dtype(v)
    valid[i, j] = wp.uint8(0)


@wp.func
def tap_weight(src: SourceWindow, r: wp.int32, c: wp.int32, rows: wp.int32, cols: wp.int32, w: wp.float32):
    """w where source pixel (r, c) of the window exists and is valid, else 0."""
    if r < 0 or r >= rows or c < 0 or c >= cols:
        return wp.float32(0.0)
    if src.masked != 0:
        if src.valid[r, c] == wp.uint8(0):
            return wp.float32(0.0)
    return w


@wp.func
def resample_at(src: SourceWindow, data: wp.array3d(dtype=Any), pix: wp.vec2d, method: wp.int32, top: wp.float32,
                out: wp.array3d(dtype=Any), out_valid: wp.array2d(dtype=wp.uint8), i: wp.int32, j: wp.int32):
    """Resample all bands of a source window (data: bands, rows, cols, any dtype) at source
    pixel ``pix`` (NaN: no data) into output pixel (i, j), in the output's dtype,
    pixel-interleaved (rows, cols, bands): ``top`` is the largest value of an integer output
    (values are rounded half to even and clipped to [0, top]) and 0 for float outputs (NaN
    where there is no data)."""
    nb = out.shape[2]
    rows = data.shape[1]
    cols = data.shape[2]
    if not wp.isfinite(pix[0]):
        store_nodata(out, out_valid, i, j, top)
        return
    # the pixel in window coordinates (corner-based; exact when the window is not reduced)
    px = (pix[0] - wp.float64(src.col0)) * src.inv_sx
    py = (pix[1] - wp.float64(src.row0)) * src.inv_sy
    if method == NEAREST:
        c = wp.int32(wp.floor(px))
        r = wp.int32(wp.floor(py))
        c = wp.clamp(c, 0, cols - 1)  # the image's right/bottom edge belongs to the last pixel
        r = wp.clamp(r, 0, rows - 1)
        if tap_weight(src, r, c, rows, cols, wp.float32(1.0)) == wp.float32(0.0):
            store_nodata(out, out_valid, i, j, top)
            return
        for b in range(nb):
            store_pixel(out, i, j, b, wp.float32(data[b, r, c]), top)
        out_valid[i, j] = wp.uint8(1)
        return
    radius = 1
    if method == BICUBIC:
        radius = 2
    elif method == LANCZOS:
        radius = 3
    # centre-based coordinates inside the window
    x = px - wp.float64(0.5)
    y = py - wp.float64(0.5)
    x0 = wp.int32(wp.floor(x))
    y0 = wp.int32(wp.floor(y))
    fx = wp.float32(x - wp.float64(x0))  # in [0, 1): exact enough in float32
    fy = wp.float32(y - wp.float64(y0))
    one = wp.float32(1.0)
    if method == BILINEAR:  # the common case, unrolled: four taps, weights zero where no data
        x1 = x0 + 1
        y1 = y0 + 1
        w00 = tap_weight(src, y0, x0, rows, cols, (one - fx) * (one - fy))
        w01 = tap_weight(src, y0, x1, rows, cols, fx * (one - fy))
        w10 = tap_weight(src, y1, x0, rows, cols, (one - fx) * fy)
        w11 = tap_weight(src, y1, x1, rows, cols, fx * fy)
        wsum = (w00 + w01) + (w10 + w11)
        if wsum < wp.float32(0.5) or wsum <= wp.float32(0.0):
            store_nodata(out, out_valid, i, j, top)
            return
        # taps outside the window carry no weight: read an inside neighbour instead
        ca = wp.clamp(x0, 0, cols - 1)
        cb = wp.clamp(x1, 0, cols - 1)
        ra = wp.clamp(y0, 0, rows - 1)
        rb = wp.clamp(y1, 0, rows - 1)
        inv = one / wsum
        for b in range(nb):
            v = (w00 * wp.float32(data[b, ra, ca]) + w01 * wp.float32(data[b, ra, cb])) + (
                w10 * wp.float32(data[b, rb, ca]) + w11 * wp.float32(data[b, rb, cb]))
            store_pixel(out, i, j, b, v * inv, top)
        out_valid[i, j] = wp.uint8(1)
        return
    # bands in groups of four, accumulated in registers
    for b0 in range(0, nb, 4):
        acc = wp.vec4f(0.0)
        wsum = wp.float32(0.0)
        wtotal = wp.float32(0.0)
        for dy in range(1 - radius, radius + 1):
            wy = kernel_weight(method, fy - wp.float32(dy))
            r = y0 + dy
            for dx in range(1 - radius, radius + 1):
                w = wy * kernel_weight(method, fx - wp.float32(dx))
                wtotal += w
                c = x0 + dx
                if w != wp.float32(0.0):
                    w = tap_weight(src, r, c, rows, cols, w)
                    if w != wp.float32(0.0):
                        wsum += w
                        for k in range(4):
                            if b0 + k < nb:
                                acc[k] = acc[k] + w * wp.float32(data[b0 + k, r, c])
        if wsum < wp.float32(0.5) * wtotal or wsum <= wp.float32(0.0):
            store_nodata(out, out_valid, i, j, top)
            return
        inv = wp.float32(1.0) / wsum
        for k in range(4):
            if b0 + k < nb:
                store_pixel(out, i, j, b0 + k, acc[k] * inv, top)
    out_valid[i, j] = wp.uint8(1)


# Registers: left alone, nvcc gives the fused kernels ~115 per thread, which holds an H100 at
# 25 % occupancy, stalled on latency (Nsight Compute); capped at 64 (50 %) the frame kernel ran
# 1.38x faster with identical output (bench/ortho_registers.py).
FUSED_MAX_REGISTERS = 64


@wp.kernel(cuda_max_registers=FUSED_MAX_REGISTERS)
def ortho_kernel(
    arg: Any,
    refr: RefractionTable,
    dem: DemData,
    grid: CoarseGrid,
    width: wp.float64,
    height: wp.float64,
    src: SourceWindow,
    data: wp.array3d(dtype=Any),
    method: wp.int32,
    top: wp.float32,
    out: wp.array3d(dtype=Any),
    out_valid: wp.array2d(dtype=wp.uint8),
):
    """Backward ortho, one thread per output-tile pixel: its source pixel
    (:func:`source_pixel`; a frame's pose is in the grid), then :func:`resample_at`."""
    i, j = wp.tid()
    pix = source_pixel(arg, refr, dem, grid, i, j, width, height)
    resample_at(src, data, pix, method, top, out, out_valid, i, j)


@wp.kernel
def ortho_resample_kernel(
    src: SourceWindow,
    data: wp.array3d(dtype=Any),
    coords: wp.array2d(dtype=wp.vec2d),
    method: wp.int32,
    top: wp.float32,
    out: wp.array3d(dtype=Any),
    out_valid: wp.array2d(dtype=wp.uint8),
):
    """:func:`resample_at` at given source coordinates per output pixel (the forward method)."""
    i, j = wp.tid()
    resample_at(src, data, coords[i, j], method, top, out, out_valid, i, j)


# the source's dtype and the output's: the same, or a float32 source (a widened integer source,
# or one of another dtype read as float32) resampled into an integer output
for _src, _out in ((wp.uint8, wp.uint8), (wp.uint16, wp.uint16), (wp.float32, wp.float32), (wp.float32, wp.uint8),
                   (wp.float32, wp.uint16)):
    wp.overload(ortho_resample_kernel, {"data": wp.array3d(dtype=_src), "out": wp.array3d(dtype=_out)})
    for _arg in SENSOR_ARGS:
        wp.overload(ortho_kernel, {"arg": _arg, "data": wp.array3d(dtype=_src), "out": wp.array3d(dtype=_out)})


@wp.kernel
def visibility_kernel(
    arg: Any,
    refr: RefractionTable,
    dem: DemData,
    search: SearchParams,
    grid: CoarseGrid,
    width: wp.float64,
    height: wp.float64,
    tol: wp.float64,
    valid: wp.array2d(dtype=wp.uint8),
):
    """Hidden ground off: output pixel (i, j)'s ground point is seen by the sensor when its
    source pixel, geolocated forward (the first ground point along the pixel's ray, the DEM
    relief search), comes back to it within ``tol`` (m); else terrain or an object on the DSM
    between them hides it and ``valid`` is set to 0 there (pixels already invalid stay so)."""
    i, j = wp.tid()
    if valid[i, j] == wp.uint8(0):
        return
    x, h = grid_ground(grid, dem, wp.float64(i) / grid.step, wp.float64(j) / grid.step)
    pix = source_pixel(arg, refr, dem, grid, i, j, width, height)
    if not wp.isfinite(h) or not wp.isfinite(pix[0]):
        return
    g = sensor_geolocate(arg, refr, dem, search, pix)
    p = g
    if grid.geocentric != 0:  # a geo triple (lon, lat deg, h) against the grid's ECEF point
        p = geodetic_to_ecef(wp.radians(g[1]), wp.radians(g[0]), g[2])
    if not wp.isfinite(p[0]) or wp.length(p - x) > tol:
        valid[i, j] = wp.uint8(0)


# -- forward (direct) method, [P3] ----------------------------------------------------------


@wp.struct
class FrameToOutput:
    """Bilinear lookup from the pose frame's horizontal coordinates (lon/lat deg or map x/y) to
    output-tile pixel coordinates (col, row), on a regular grid whose nodes the host transformed
    exactly: node (i, j) is at (x0 + j dx, y0 + i dy)."""

    grid: wp.array2d(dtype=wp.vec2d)
    x0: wp.float64
    dx: wp.float64
    y0: wp.float64
    dy: wp.float64


@wp.func
def frame_to_output(f: FrameToOutput, u: wp.float64, v: wp.float64):
    return grid_bilinear(f.grid, (v - f.y0) / f.dy, (u - f.x0) / f.dx)


@wp.kernel
def forward_nodes_kernel(
    arg: Any,
    refr: RefractionTable,
    dem: DemData,
    search: SearchParams,
    f2o: FrameToOutput,
    col0: wp.int32,
    row0: wp.int32,
    nodes: wp.array2d(dtype=wp.vec2d),
):
    """Forward chain for every source pixel centre of a window: its ground point, as
    output-tile pixel coordinates (NaN where the ray meets no ground). Built for frames only:
    the host runs the forward method for them alone."""
    i, j = wp.tid()
    half = wp.float64(0.5)
    g = sensor_geolocate(arg, refr, dem, search, wp.vec2d(wp.float64(col0 + j) + half, wp.float64(row0 + i) + half))
    if wp.isfinite(g[0]):
        nodes[i, j] = frame_to_output(f2o, g[0], g[1])
    else:
        nan = wp.float64(wp.nan)
        nodes[i, j] = wp.vec2d(nan, nan)


@wp.func
def cross2(a: wp.vec2d, b: wp.vec2d):
    return a[0] * b[1] - a[1] * b[0]


@wp.kernel
def forward_scatter_kernel(
    nodes: wp.array2d(dtype=wp.vec2d),
    col0: wp.int32,
    row0: wp.int32,
    max_edge: wp.float64,
    coords: wp.array2d(dtype=wp.vec2d),
):
    """Invert the forward map quad by quad: every output pixel centre inside the ground quad of
    four neighbouring source pixel centres gets its source position by inverse bilinear
    interpolation. Quads longer than ``max_edge`` output pixels (spanning an occlusion) or folded
    are skipped, so hidden ground stays nodata."""
    i, j = wp.tid()
    p00 = nodes[i, j]
    p01 = nodes[i, j + 1]
    p10 = nodes[i + 1, j]
    p11 = nodes[i + 1, j + 1]
    if not (wp.isfinite(p00[0]) and wp.isfinite(p01[0]) and wp.isfinite(p10[0]) and wp.isfinite(p11[0])):
        return
    if wp.length(p01 - p00) > max_edge or wp.length(p10 - p00) > max_edge or wp.length(p11 - p01) > max_edge or wp.length(
            p11 - p10) > max_edge:
        return
    # both triangles must keep the orientation of the source grid (no fold)
    if cross2(p01 - p00, p10 - p00) * cross2(p10 - p11, p01 - p11) <= wp.float64(0.0):
        return
    half = wp.float64(0.5)
    xmin = wp.min(wp.min(p00[0], p01[0]), wp.min(p10[0], p11[0]))
    xmax = wp.max(wp.max(p00[0], p01[0]), wp.max(p10[0], p11[0]))
    ymin = wp.min(wp.min(p00[1], p01[1]), wp.min(p10[1], p11[1]))
    ymax = wp.max(wp.max(p00[1], p01[1]), wp.max(p10[1], p11[1]))
    c_lo = wp.max(wp.int32(wp.ceil(xmin - half)), 0)
    c_hi = wp.min(wp.int32(wp.floor(xmax - half)), coords.shape[1] - 1)
    r_lo = wp.max(wp.int32(wp.ceil(ymin - half)), 0)
    r_hi = wp.min(wp.int32(wp.floor(ymax - half)), coords.shape[0] - 1)
    eps = wp.float64(1.0e-9)
    for r in range(r_lo, r_hi + 1):
        for c in range(c_lo, c_hi + 1):
            p = wp.vec2d(wp.float64(c) + half, wp.float64(r) + half)
            s = half
            t = half
            for _ in range(8):  # Newton on the bilinear map (s along the row, t down the column)
                one = wp.float64(1.0)
                q = (one - s) * (one - t) * p00 + s * (one - t) * p01 + (one - s) * t * p10 + s * t * p11
                ds = (one - t) * (p01 - p00) + t * (p11 - p10)
                dt = (one - s) * (p10 - p00) + s * (p11 - p01)
                det = cross2(ds, dt)
                e = p - q
                s = s + cross2(e, dt) / det
                t = t + cross2(ds, e) / det
            if s >= -eps and s <= wp.float64(1.0) + eps and t >= -eps and t <= wp.float64(1.0) + eps:
                coords[r, c] = wp.vec2d(wp.float64(col0 + j) + half + s, wp.float64(row0 + i) + half + t)


# -- source widening ----------------------------------------------------------------------------


@wp.kernel
def widen_kernel(src: wp.array3d(dtype=Any), dst: wp.array3d(dtype=wp.float32)):
    """Integer source window (bands, rows, cols) -> float32, for the resampler."""
    b, i, j = wp.tid()
    dst[b, i, j] = wp.float32(src[b, i, j])


wp.overload(widen_kernel, {"src": wp.array3d(dtype=wp.uint8)})
wp.overload(widen_kernel, {"src": wp.array3d(dtype=wp.uint16)})


@wp.kernel
def reduce_window_kernel(src: wp.array3d(dtype=Any), valid: wp.array2d(dtype=wp.uint8), masked: wp.int32,
                         col0: wp.int32, row0: wp.int32, factor: wp.int32, dst: wp.array3d(dtype=wp.float32),
                         dst_valid: wp.array2d(dtype=wp.uint8)):
    """A window of a whole source in device memory, reduced by an integer ``factor`` into
    float32: ``src`` (bands, rows, cols) of the whole image, its mask ``valid`` (rows, cols;
    read only where ``masked``); window pixel (i, j) of ``dst`` (bands, h, w) is the mean of
    the valid image pixels of block rows row0 + i f .. row0 + (i + 1) f - 1 and columns
    col0 + j f .. col0 + (j + 1) f - 1 (clipped to the image: area averaging, each image pixel
    in one block), valid where the block's centre pixel is (the nearest image pixel, as a
    reduced mask read takes it) and some pixel of the block is. ``factor`` 1: the window
    cropped and widened."""
    i, j = wp.tid()
    rows = src.shape[1]
    cols = src.shape[2]
    r_lo = row0 + i * factor
    c_lo = col0 + j * factor
    r_hi = wp.min(r_lo + factor, rows)
    c_hi = wp.min(c_lo + factor, cols)
    rc = wp.min(r_lo + factor / 2, rows - 1)
    cc = wp.min(c_lo + factor / 2, cols - 1)
    centre = wp.int32(1)
    if masked != 0:
        if valid[rc, cc] == wp.uint8(0):
            centre = wp.int32(0)
    n = wp.int32(0)
    for r in range(r_lo, r_hi):
        for c in range(c_lo, c_hi):
            ok = wp.int32(1)
            if masked != 0:
                if valid[r, c] == wp.uint8(0):
                    ok = wp.int32(0)
            n += ok
    if centre == 0 or n == 0:
        for b in range(src.shape[0]):
            dst[b, i, j] = wp.float32(0.0)
        dst_valid[i, j] = wp.uint8(0)
        return
    for b in range(src.shape[0]):
        acc = wp.float64(0.0)  # exact for any block of integer values
        for r in range(r_lo, r_hi):
            for c in range(c_lo, c_hi):
                if masked == 0 or valid[r, c] != wp.uint8(0):
                    acc += wp.float64(src[b, r, c])
        dst[b, i, j] = wp.float32(acc / wp.float64(n))
    dst_valid[i, j] = wp.uint8(1)


for _t in (wp.uint8, wp.uint16, wp.float32):
    wp.overload(reduce_window_kernel, {"src": wp.array3d(dtype=_t)})


@wp.kernel
def untile_kernel(raw: wp.array(dtype=Any), block_h: wp.int32, block_w: wp.int32, blocks_across: wp.int32,
                  row_off: wp.int32, col_off: wp.int32, out: wp.array3d(dtype=Any)):
    """A TIFF's blocks as stored (``raw``: a grid of blocks ``blocks_across`` wide, block t's
    pixel-interleaved samples from element t * block_h * block_w * bands) into (bands, rows,
    cols), as GDAL reads them, from pixel (``row_off``, ``col_off``) of the blocks' grid (0, 0
    for a whole image): one thread per output sample."""
    b, r, c = wp.tid()
    bands = out.shape[0]
    rr = r + row_off
    cc = c + col_off
    t = (rr / block_h) * blocks_across + cc / block_w
    k = ((t * block_h + rr % block_h) * block_w + cc % block_w) * bands + b
    out[b, r, c] = raw[k]


for _t in (wp.uint8, wp.uint16, wp.float32):
    wp.overload(untile_kernel, {"raw": wp.array(dtype=_t), "out": wp.array3d(dtype=_t)})


@wp.kernel
def source_coords_kernel(
    arg: Any,
    refr: RefractionTable,
    dem: DemData,
    grid: CoarseGrid,
    width: wp.float64,
    height: wp.float64,
    out: wp.array2d(dtype=wp.vec2d),
):
    """The source pixel (col, row) of every output pixel of a tile, as the fused kernel
    computes it (:func:`source_pixel`), stored: for checking the backends against each other
    and against independent references."""
    i, j = wp.tid()
    out[i, j] = source_pixel(arg, refr, dem, grid, i, j, width, height)


for _arg in SENSOR_ARGS:
    wp.overload(node_pixels_kernel, {"arg": _arg})
    wp.overload(source_coords_kernel, {"arg": _arg})
    wp.overload(visibility_kernel, {"arg": _arg})
wp.overload(forward_nodes_kernel, {"arg": FrameArg})
