"""Digital elevation model sampling, device code.

A DEM is a north-up regular grid in the horizontal coordinates of the geometry mode (longitude
and latitude in degrees for geocentric poses, map x and y for map-Cartesian poses). Cell (i, j)
has its centre at (x0 + (j + 0.5) dx, y0 + (i + 0.5) dy). Heights are float32 metres with NaN
for nodata; bilinear interpolation between cell centres; NaN outside the grid.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})  # forward-only kernels: halves compile time


@wp.struct
class DemData:
    """Grid heights and georeferencing. A constant DEM has ``constant = 1`` and ``value``.

    ``bmax`` accelerates ray marching: ``bmax[I, J]`` bounds every bilinear height sampled at
    a grid point within ``block`` cells of any point of block (I, J) (cells
    ``[I block, (I + 1) block)`` x ``[J block, (J + 1) block)``), and -inf where that
    neighbourhood holds no data at all. Skipping a run of march steps whose heights all lie
    above the bound changes nothing: no sample in it can be at or above the terrain, and the
    run's last sample is taken as the marcher would.
    """

    data: wp.array2d(dtype=wp.float32)
    bmax: wp.array2d(dtype=wp.float32)
    block: wp.int32
    x0: wp.float64
    dx: wp.float64
    y0: wp.float64
    dy: wp.float64
    inv_dx: wp.float64
    inv_dy: wp.float64
    constant: wp.int32
    value: wp.float64
    hmin: wp.float64
    hmax: wp.float64


@wp.func
def dem_grid(dem: DemData, x: wp.float64, y: wp.float64):
    """Horizontal coordinates -> fractional cell-centre grid coordinates (col, row)."""
    half = wp.float64(0.5)
    return wp.vec2d((x - dem.x0) * dem.inv_dx - half, (y - dem.y0) * dem.inv_dy - half)


@wp.func
def dem_sample_grid(dem: DemData, g: wp.vec2d):
    """Bilinear height (m) at grid coordinates g; NaN outside the grid or next to nodata."""
    if dem.constant != 0:
        return dem.value
    nan = wp.float64(wp.nan)
    if not (wp.isfinite(g[0]) and wp.isfinite(g[1])):
        return nan
    h = dem.data.shape[0]
    w = dem.data.shape[1]
    half = wp.float64(0.5)
    # Cells are valid out to their outer edges; clamp to the outermost centres there.
    if g[0] < -half or g[1] < -half or g[0] > wp.float64(w) - half or g[1] > wp.float64(h) - half:
        return nan
    gx = wp.clamp(g[0], wp.float64(0.0), wp.float64(w - 1))
    gy = wp.clamp(g[1], wp.float64(0.0), wp.float64(h - 1))
    j = wp.min(wp.int32(gx), wp.max(w - 2, 0))
    i = wp.min(wp.int32(gy), wp.max(h - 2, 0))
    j1 = wp.min(j + 1, w - 1)
    i1 = wp.min(i + 1, h - 1)
    ax = gx - wp.float64(j)
    ay = gy - wp.float64(i)
    one = wp.float64(1.0)
    z00 = wp.float64(dem.data[i, j])
    z01 = wp.float64(dem.data[i, j1])
    z10 = wp.float64(dem.data[i1, j])
    z11 = wp.float64(dem.data[i1, j1])
    return (one - ay) * ((one - ax) * z00 + ax * z01) + ay * ((one - ax) * z10 + ax * z11)


@wp.func
def dem_sample_grid_f32(dem: DemData, gx: wp.float32, gy: wp.float32):
    """Single-precision twin of :func:`dem_sample_grid` for ray marching (finite gx, gy).

    Heights are interpolated relative to nothing, so they carry float32's ~3e-5 m at 500 m:
    enough to find the sign changes the march brackets; the refinement is float64.
    """
    if dem.constant != 0:
        return wp.float32(dem.value)
    h = dem.data.shape[0]
    w = dem.data.shape[1]
    half = wp.float32(0.5)
    if gx < -half or gy < -half or gx > wp.float32(w) - half or gy > wp.float32(h) - half:
        return wp.float32(wp.nan)
    cx = wp.clamp(gx, wp.float32(0.0), wp.float32(w - 1))
    cy = wp.clamp(gy, wp.float32(0.0), wp.float32(h - 1))
    j = wp.min(wp.int32(cx), wp.max(w - 2, 0))
    i = wp.min(wp.int32(cy), wp.max(h - 2, 0))
    j1 = wp.min(j + 1, w - 1)
    i1 = wp.min(i + 1, h - 1)
    ax = cx - wp.float32(j)
    ay = cy - wp.float32(i)
    top = dem.data[i, j] + ax * (dem.data[i, j1] - dem.data[i, j])
    bot = dem.data[i1, j] + ax * (dem.data[i1, j1] - dem.data[i1, j])
    return top + ay * (bot - top)


@wp.func
def dem_block_bound(dem: DemData, gx: wp.float32, gy: wp.float32):
    """Upper bound (m) of the heights sampled within ``dem.block`` cells of grid point (gx, gy)."""
    half = wp.float32(0.5)
    inv_b = wp.float32(1.0) / wp.float32(dem.block)
    bj = wp.int32(wp.floor((gx + half) * inv_b))
    bi = wp.int32(wp.floor((gy + half) * inv_b))
    if bi < 0 or bj < 0 or bi >= dem.bmax.shape[0] or bj >= dem.bmax.shape[1]:
        return wp.float32(wp.inf)
    return dem.bmax[bi, bj]


@wp.func
def dem_sample(dem: DemData, x: wp.float64, y: wp.float64):
    """Bilinear height (m) at horizontal coordinates (x, y); NaN outside or at nodata."""
    return dem_sample_grid(dem, dem_grid(dem, x, y))

