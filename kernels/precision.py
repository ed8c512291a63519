"""Predicted accuracy of ground points seen by a frame image, device code ([P4]: C = A C_l A^T).

The ground point under an accuracy cell (the ortho's coarse-grid geometry: its horizontal
position interpolated from exact nodes, its height the DEM's bilinear) is fixed by three
conditions ([P4]'s monoplotting): its pixel is the measured one, ``p(x, l) - p_obs = 0`` (two),
and its height is the DEM's, ``u - s_e e - s_n n - e_h = 0``, in the point's own east-north-up
frame (e, n, u in m; s_e, s_n the DEM's slope). Linearised, ``F_X dX + F_l dl = 0``, so
``C_X = F_X^-1 F_l C_l F_l^T F_X^-T``.

The derivatives of ``p`` come from Warp's automatic differentiation of the kernels' own
projection, :func:`~orthowarp.kernels.frame.project_xyz` (refraction included), in
:func:`pixel_ad_kernel`: each cell gets its own zero offsets of the rotation matrix and of the
camera's eight calibration parameters, and the reverse pass for the column and then for the
row gives every cell's gradient by the point and by those raw parameters (the projection
centre's is the point's, negated). The host maps the user's inputs (pose inputs, calibration)
to the raw parameters once per image (``C_raw = M C_in M^T``, :data:`RAW`), so a cell's
image-side covariance is the quadratic form ``J C_raw J^T`` (:func:`accuracy_kernel`).
"""

import warp as wp

from .camera import FrameCameraData
from .dem import DemData, dem_sample
from .frame import project_xyz
from .geodesy import DEG, WGS84_A, WGS84_E2
from .ortho import CoarseGrid, grid_cell, grid_ground, grid_lerp
from .ray import FramePoseData
from .refraction import RefractionTable

RAW = 20  # raw parameters: projection centre (3, m), rotation R_object<-camera (9, row-major), camera (8)
vec8d = wp.types.vector(length=8, dtype=wp.float64)  # f, x0, y0 (mm); k1, k2, k3, p1, p2
# machine code (cubin), not PTX, on a GPU: no driver compile of PTX on a first run, and the
# cubins built with orthowarp are taken as they are (orthowarp._kernelcache)
wp.set_module_options({"cuda_output": "cubin"})


@wp.func
def offset_camera(cam: FrameCameraData, d: vec8d):
    """The camera with its calibration offset by d (f, x0, y0 mm; k1, k2, k3, p1, p2)."""
    c = FrameCameraData()
    c.focal = cam.focal + d[0]
    c.pixel_size = cam.pixel_size
    c.inv_pixel_size = cam.inv_pixel_size
    c.size = cam.size
    c.pp = wp.vec2d(cam.pp[0] + d[1], cam.pp[1] + d[2])
    c.k1 = cam.k1 + d[3]
    c.k2 = cam.k2 + d[4]
    c.k3 = cam.k3 + d[5]
    c.p1 = cam.p1 + d[6]
    c.p2 = cam.p2 + d[7]
    return c


@wp.func
def offset_pose(pose: FramePoseData, dr: wp.mat33d):
    """The pose with its rotation matrix offset by dr. (An offset of the centre needs no
    gradient of its own: the projection takes the point and the centre only as x - C, so
    dp/dC = -dp/dx.)"""
    p = FramePoseData()
    p.mode = pose.mode
    p.center = pose.center
    p.rot = pose.rot + dr
    p.up = pose.up
    p.height = pose.height
    return p


@wp.kernel
def pixel_ad_kernel(
    cam: FrameCameraData,
    pose: FramePoseData,
    refr: RefractionTable,
    x: wp.array(dtype=wp.vec3d),
    h: wp.array(dtype=wp.float64),
    d_rot: wp.array(dtype=wp.mat33d),
    d_cam: wp.array(dtype=vec8d),
    out: wp.array(dtype=wp.vec2d),
):
    """Pixel (N,) of the object-frame points x (N,) at heights h (N,) by
    :func:`~orthowarp.kernels.frame.project_xyz`, with per-point offsets (zero) of the
    rotation and the camera whose gradients the reverse pass gives (with x's)."""
    i = wp.tid()
    out[i] = project_xyz(offset_camera(cam, d_cam[i]), offset_pose(pose, d_rot[i]), refr, x[i], h[i])


@wp.func
def dem_slope(dem: DemData, uv: wp.vec2d, m_east: wp.float64, m_north: wp.float64):
    """The DEM's slope (rise per metre east, per metre north) at uv (the grid's horizontal
    coordinates): central differences of its bilinear surface over a tenth of a DEM cell
    (exact inside a cell); ``m_east``, ``m_north``: metres per unit of u and v."""
    du = wp.float64(0.1) * wp.abs(dem.dx)
    dv = wp.float64(0.1) * wp.abs(dem.dy)
    if dem.constant != 0:
        return wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    se = (dem_sample(dem, uv[0] + du, uv[1]) - dem_sample(dem, uv[0] - du, uv[1])) / (wp.float64(2.0) * du * m_east)
    sn = (dem_sample(dem, uv[0], uv[1] + dv) - dem_sample(dem, uv[0], uv[1] - dv)) / (wp.float64(2.0) * dv * m_north)
    return wp.vec2d(se, sn)


@wp.kernel(enable_backward=False)
def cell_points_kernel(
    dem: DemData,
    grid: CoarseGrid,
    start: wp.int32,
    cols: wp.int32,
    inv_node: wp.float64,
    inv_ax: wp.float64,
    inv_ey: wp.float64,
    x: wp.array(dtype=wp.vec3d),
    h: wp.array(dtype=wp.float64),
    basis: wp.array(dtype=wp.mat33d),
    slope: wp.array(dtype=wp.vec2d),
    to_out: wp.array(dtype=wp.mat22d),
):
    """The ground points of accuracy cells start + k (k < len(x); row-major over ``cols``
    columns), whose centres are the grid's points at fractional node index (i, j) *
    ``inv_node``: the object-frame point x and its height h (:func:`grid_ground`, as the
    ortho), its east-north-up axes in the object frame (columns of ``basis``; the identity
    for map poses), the DEM's slope, and ``to_out`` = d(output x, y)/d(east, north) from the
    grid's derivative (``inv_ax``, ``inv_ey``: node indices per unit of output x, y)."""
    k = wp.tid()
    c = start + wp.int32(k)
    fi = wp.float64(c // cols) * inv_node
    fj = wp.float64(c % cols) * inv_node
    xk, hk = grid_ground(grid, dem, fi, fj)
    i0, j0, ai, aj = grid_cell(grid.uv.shape[0], grid.uv.shape[1], fi, fj)
    uv = grid_lerp(grid.uv, i0, j0, ai, aj)
    one = wp.float64(1.0)
    duv_dj = (one - ai) * (grid.uv[i0, j0 + 1] - grid.uv[i0, j0]) + ai * (grid.uv[i0 + 1, j0 + 1] - grid.uv[i0 + 1, j0])
    duv_di = (one - aj) * (grid.uv[i0 + 1, j0] - grid.uv[i0, j0]) + aj * (grid.uv[i0 + 1, j0 + 1] - grid.uv[i0, j0 + 1])
    m_east = one
    m_north = one
    b = wp.identity(n=3, dtype=wp.float64)
    if grid.geocentric != 0:  # metres per degree of longitude and latitude at (lon, lat, h)
        lon = uv[0] * DEG
        lat = uv[1] * DEG
        sl = wp.sin(lat)
        cl = wp.cos(lat)
        so = wp.sin(lon)
        co = wp.cos(lon)
        w2 = one - WGS84_E2 * sl * sl
        n_rad = WGS84_A / wp.sqrt(w2)
        m_east = (n_rad + hk) * cl * DEG
        m_north = (n_rad * (one - WGS84_E2) / w2 + hk) * DEG
        b = wp.mat33d(-so, -sl * co, cl * co,
                      co, -sl * so, cl * so,
                      wp.float64(0.0), cl, sl)
    # d(east, north)/d(output x, y): columns by output x (node j) and output y (node i)
    en_out = wp.mat22d(m_east * duv_dj[0] * inv_ax, m_east * duv_di[0] * inv_ey,
                       m_north * duv_dj[1] * inv_ax, m_north * duv_di[1] * inv_ey)
    x[k] = xk
    h[k] = hk
    basis[k] = b
    slope[k] = dem_slope(dem, uv, m_east, m_north)
    to_out[k] = wp.inverse(en_out)


vec20d = wp.types.vector(length=RAW, dtype=wp.float64)


@wp.func
def raw_gradient(gx: wp.vec3d, gr: wp.mat33d, gk: vec8d):
    """A pixel coordinate's gradient by the raw parameters (:data:`RAW`) from its gradients by
    the point (the centre's is its negative), the rotation and the camera."""
    g = vec20d()
    for m in range(3):
        g[m] = -gx[m]
    for m in range(9):
        g[3 + m] = gr[m // 3, m % 3]
    for m in range(8):
        g[12 + m] = gk[m]
    return g


LE90_FACTOR = wp.constant(wp.float64(1.6448536269514722))  # the standard normal's 95 % quantile


@wp.func
def ce90(table: wp.array(dtype=wp.float64), c: wp.mat22d):
    """CE90 (m) of a horizontal covariance c (m^2): sigma_major times the table's factor at
    sigma_minor / sigma_major (linear between its entries)."""
    zero = wp.float64(0.0)
    half = wp.float64(0.5)
    mean = half * (c[0, 0] + c[1, 1])
    d = wp.sqrt(wp.max(half * half * (c[0, 0] - c[1, 1]) * (c[0, 0] - c[1, 1]) + c[0, 1] * c[1, 0], zero))
    major = wp.sqrt(wp.max(mean + d, zero))
    minor = wp.sqrt(wp.max(mean - d, zero))
    if major <= zero:
        return zero
    n = table.shape[0]
    f = wp.min(minor / major, wp.float64(1.0)) * wp.float64(n - 1)
    i = wp.min(wp.int32(f), n - 2)
    a = f - wp.float64(i)
    return major * ((wp.float64(1.0) - a) * table[i] + a * table[i + 1])


@wp.kernel(enable_backward=False)
def accuracy_kernel(
    pix: wp.array(dtype=wp.vec2d),
    gx0: wp.array(dtype=wp.vec3d),
    gx1: wp.array(dtype=wp.vec3d),
    gr0: wp.array(dtype=wp.mat33d),
    gr1: wp.array(dtype=wp.mat33d),
    gk0: wp.array(dtype=vec8d),
    gk1: wp.array(dtype=vec8d),
    basis: wp.array(dtype=wp.mat33d),
    slope: wp.array(dtype=wp.vec2d),
    to_out: wp.array(dtype=wp.mat22d),
    c_raw: wp.array2d(dtype=wp.float64),
    pixel_var: wp.float64,
    dem_var: wp.float64,
    width: wp.float64,
    height: wp.float64,
    ce_table: wp.array(dtype=wp.float64),
    start: wp.int32,
    out: wp.array2d(dtype=wp.float32),
):
    """Sigma of the output CRS's x, y and of up (m) of each cell's ground point into columns
    start + k of ``out`` (3, cells); NaN where the image does not see it. Rows 0 and 1 of a
    cell's pixel Jacobians come from the reverse passes of :func:`pixel_ad_kernel` (``gx``
    by the object-frame point, ``gr`` by the rotation, ``gk`` by the camera).

    With a ``ce_table`` (not empty: CE90 / sigma_major against sigma_minor / sigma_major on a
    regular grid over [0, 1]), rows 0 and 1 are CE90 and LE90 (m) instead: the radius that
    holds 90 % of the horizontal error, from the east/north covariance's axes, and 1.6449
    sigma up; row 2 NaN."""
    k = wp.tid()
    p = pix[k]
    nan = wp.float32(wp.nan)
    zero = wp.float64(0.0)
    ok = wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(slope[k][0]) and wp.isfinite(slope[k][1])
    if not ok or p[0] < zero or p[1] < zero or p[0] > width or p[1] > height:
        out[0, start + k] = nan
        out[1, start + k] = nan
        out[2, start + k] = nan
        return
    g0 = gx0[k]
    g1 = gx1[k]
    j0 = raw_gradient(g0, gr0[k], gk0[k])
    j1 = raw_gradient(g1, gr1[k], gk1[k])
    # image side: S = J C_raw J^T + pixel_var I (pixels^2)
    s00 = pixel_var
    s01 = zero
    s11 = pixel_var
    for a in range(RAW):
        t0 = zero
        t1 = zero
        for b in range(RAW):
            c = c_raw[a, b]
            t0 += c * j0[b]
            t1 += c * j1[b]
        s00 += j0[a] * t0
        s01 += j0[a] * t1
        s11 += j1[a] * t1
    # F_X in east, north, up: pixel rows (dp/dx) E, height row (-s_e, -s_n, 1)
    e = basis[k]
    r0 = wp.transpose(e) * g0
    r1 = wp.transpose(e) * g1
    sl = slope[k]
    fx = wp.mat33d(r0[0], r0[1], r0[2], r1[0], r1[1], r1[2], -sl[0], -sl[1], wp.float64(1.0))
    fi = wp.inverse(fx)
    cl = wp.mat33d(s00, s01, zero, s01, s11, zero, zero, zero, dem_var)
    cx = fi * cl * wp.transpose(fi)
    ch = wp.mat22d(cx[0, 0], cx[0, 1], cx[1, 0], cx[1, 1])
    if ce_table.shape[0] > 0:
        out[0, start + k] = wp.float32(ce90(ce_table, ch))
        out[1, start + k] = wp.float32(LE90_FACTOR * wp.sqrt(wp.max(cx[2, 2], zero)))
        out[2, start + k] = nan
        return
    j = to_out[k]
    co = j * ch * wp.transpose(j)
    out[0, start + k] = wp.float32(wp.sqrt(wp.max(co[0, 0], zero)))
    out[1, start + k] = wp.float32(wp.sqrt(wp.max(co[1, 1], zero)))
    out[2, start + k] = wp.float32(wp.sqrt(wp.max(cx[2, 2], zero)))


@wp.kernel(enable_backward=False)
def hidden_facets_kernel(
    pose: FramePoseData,
    x: wp.array(dtype=wp.vec3d),
    gx0: wp.array(dtype=wp.vec3d),
    gx1: wp.array(dtype=wp.vec3d),
    basis: wp.array(dtype=wp.mat33d),
    slope: wp.array(dtype=wp.vec2d),
    start: wp.int32,
    out: wp.array2d(dtype=wp.float32),
):
    """NaN into columns start + k of ``out`` where the DEM's tangent plane at the cell's ground
    point x faces away from the camera (or contains the ray): the image does not see that
    ground, the terrain just in front of it along the ray stands above the ray (see
    :func:`orthowarp.pipeline.precision.facing`). The ray's direction at the point is the
    pixel's null direction, gx0 x gx1 (the gradients of the column and the row by the point:
    refraction included), turned toward the projection centre."""
    k = wp.tid()
    v = wp.cross(gx0[k], gx1[k])
    if wp.dot(v, pose.center - x[k]) < wp.float64(0.0):
        v = -v
    e = wp.transpose(basis[k]) * v  # east, north, up
    s = slope[k]
    if not (e[2] - s[0] * e[0] - s[1] * e[1] > wp.float64(0.0)):
        nan = wp.float32(wp.nan)
        out[0, start + k] = nan
        out[1, start + k] = nan
        out[2, start + k] = nan
