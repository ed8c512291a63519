"""Area-based image matching, device code ([P2]): normalised cross-correlation search and
least-squares matching, one thread per point.

Pixel coordinates follow docs/design.md: (col, row) with the centre of pixel (i, j) at
(j + 0.5, i + 0.5); images are sampled bilinearly (NaN where the 2 x 2 neighbourhood leaves
the image).

- :func:`ncc_search_kernel`: for each point, the template of (2 half + 1)^2 pixels around its
  position in the left image is correlated with the right image, resampled through the point's
  predicted affine map (rotation, scale and shear between the views), at every whole-pixel
  offset within ``radius`` of the predicted position; the best offset is refined by a parabola
  through its neighbours on each axis.
- :func:`lsm_kernel`: least-squares matching (Gruen 1985): the right window mapped by an affine
  transformation (6 parameters) with a linear radiometric correction (2: offset, gain) is fitted
  to the template by Gauss-Newton in float64; returns the position, its standard deviations from
  sigma0^2 N^-1, sigma0 and the iteration count.

Reference: A. Gruen, "Adaptive least squares correlation: a powerful image matching technique",
South African Journal of Photogrammetry 14(3), 1985.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

mat88 = wp.types.matrix(shape=(8, 8), dtype=wp.float64)
vec8 = wp.types.vector(length=8, dtype=wp.float64)


@wp.func
def sample(img: wp.array2d(dtype=wp.float32), x: wp.float64, y: wp.float64):
    """Bilinear value at pixel coordinates (x, y) = (col, row); NaN off the image."""
    fx = x - wp.float64(0.5)
    fy = y - wp.float64(0.5)
    j0 = wp.int32(wp.floor(fx))
    i0 = wp.int32(wp.floor(fy))
    if j0 < 0 or i0 < 0 or j0 + 1 >= img.shape[1] or i0 + 1 >= img.shape[0]:
        return wp.float64(wp.nan)
    ax = fx - wp.float64(j0)
    ay = fy - wp.float64(i0)
    one = wp.float64(1.0)
    top = (one - ax) * wp.float64(img[i0, j0]) + ax * wp.float64(img[i0, j0 + 1])
    bottom = (one - ax) * wp.float64(img[i0 + 1, j0]) + ax * wp.float64(img[i0 + 1, j0 + 1])
    return (one - ay) * top + ay * bottom


@wp.func
def ncc_at(left: wp.array2d(dtype=wp.float32), right: wp.array2d(dtype=wp.float32), xl: wp.float64, yl: wp.float64,
           xr: wp.float64, yr: wp.float64, half: wp.int32, a: wp.mat22d):
    """Normalised cross-correlation of the window centred at (xl, yl) left and its image under
    the affine map ``a`` (right offset = a @ left offset) centred at (xr, yr) right; NaN where a
    window leaves its image or has no texture."""
    st = wp.float64(0.0)
    ss = wp.float64(0.0)
    stt = wp.float64(0.0)
    sss = wp.float64(0.0)
    sts = wp.float64(0.0)
    for dy in range(-half, half + 1):
        for dx in range(-half, half + 1):
            fdx = wp.float64(dx)
            fdy = wp.float64(dy)
            t = sample(left, xl + fdx, yl + fdy)
            s = sample(right, xr + a[0, 0] * fdx + a[0, 1] * fdy, yr + a[1, 0] * fdx + a[1, 1] * fdy)
            st += t
            ss += s
            stt += t * t
            sss += s * s
            sts += t * s
    n = wp.float64((2 * half + 1) * (2 * half + 1))
    vt = stt - st * st / n
    vs = sss - ss * ss / n
    if not (vt > wp.float64(1e-12) and vs > wp.float64(1e-12)):
        return wp.float64(wp.nan)
    return (sts - st * ss / n) / wp.sqrt(vt * vs)


@wp.func
def parabola_peak(cm: wp.float64, c0: wp.float64, cp: wp.float64):
    """Offset (-0.5 .. 0.5) of the vertex of the parabola through (-1, cm), (0, c0), (1, cp)."""
    d = cm - wp.float64(2.0) * c0 + cp
    if not (d < wp.float64(0.0)) or not wp.isfinite(cm + cp):
        return wp.float64(0.0)
    return wp.clamp(wp.float64(0.5) * (cm - cp) / d, wp.float64(-0.5), wp.float64(0.5))


@wp.kernel
def ncc_search_kernel(
    left: wp.array2d(dtype=wp.float32),
    right: wp.array2d(dtype=wp.float32),
    points: wp.array(dtype=wp.vec2d),
    predicted: wp.array(dtype=wp.vec2d),
    affine: wp.array(dtype=wp.mat22d),
    half: wp.int32,
    radius: wp.int32,
    out: wp.array(dtype=wp.vec2d),
    score: wp.array(dtype=wp.float64),
):
    """Best NCC position (N,) of each point's template within ``radius`` px of its prediction,
    to a fraction of a pixel, the right window resampled by each point's predicted affine map
    (N,) (rotation, scale and shear between the images); NaN and score NaN where no offset
    correlates."""
    k = wp.tid()
    p = points[k]
    q = predicted[k]
    a = affine[k]
    best = wp.float64(-2.0)
    bu = int(0)
    bv = int(0)
    for v in range(-radius, radius + 1):
        for u in range(-radius, radius + 1):
            c = ncc_at(left, right, p[0], p[1], q[0] + wp.float64(u), q[1] + wp.float64(v), half, a)
            if c > best:
                best = c
                bu = u
                bv = v
    nan = wp.float64(wp.nan)
    if best < wp.float64(-1.5):
        out[k] = wp.vec2d(nan, nan)
        score[k] = nan
        return
    x = q[0] + wp.float64(bu)
    y = q[1] + wp.float64(bv)
    dx = parabola_peak(ncc_at(left, right, p[0], p[1], x - wp.float64(1.0), y, half, a), best,
                       ncc_at(left, right, p[0], p[1], x + wp.float64(1.0), y, half, a))
    dy = parabola_peak(ncc_at(left, right, p[0], p[1], x, y - wp.float64(1.0), half, a), best,
                       ncc_at(left, right, p[0], p[1], x, y + wp.float64(1.0), half, a))
    out[k] = wp.vec2d(x + dx, y + dy)
    score[k] = best


@wp.func
def solve8(a: mat88, b: vec8):
    """x with a x = b (8 x 8, Gaussian elimination with partial pivoting); NaN if singular."""
    m = a
    r = b
    for c in range(8):
        piv = c
        for i in range(c + 1, 8):
            if wp.abs(m[i, c]) > wp.abs(m[piv, c]):
                piv = i
        if wp.abs(m[piv, c]) < wp.float64(1e-300):
            return vec8(wp.float64(wp.nan))
        if piv != c:
            for j in range(8):
                tmp = m[c, j]
                m[c, j] = m[piv, j]
                m[piv, j] = tmp
            tmp = r[c]
            r[c] = r[piv]
            r[piv] = tmp
        for i in range(c + 1, 8):
            f = m[i, c] / m[c, c]
            for j in range(c, 8):
                m[i, j] = m[i, j] - f * m[c, j]
            r[i] = r[i] - f * r[c]
    x = vec8(wp.float64(0.0))
    for ii in range(8):
        i = 7 - ii
        acc = r[i]
        for j in range(i + 1, 8):
            acc = acc - m[i, j] * x[j]
        x[i] = acc / m[i, i]
    return x


@wp.kernel
def lsm_kernel(
    left: wp.array2d(dtype=wp.float32),
    right: wp.array2d(dtype=wp.float32),
    points: wp.array(dtype=wp.vec2d),
    start: wp.array(dtype=wp.vec2d),
    affine: wp.array(dtype=wp.mat22d),
    half: wp.int32,
    max_iter: wp.int32,
    tol: wp.float64,
    out: wp.array(dtype=wp.vec2d),
    sigma: wp.array(dtype=wp.vec2d),
    sigma0: wp.array(dtype=wp.float64),
    iterations: wp.array(dtype=wp.int32),
):
    """Least-squares matching of each point's template from ``start`` (N,) and the affine map
    ``affine`` (N,): position, its sigmas (px), sigma0 (grey values) and iterations (0:
    diverged, left its window or singular; the position is then NaN)."""
    k = wp.tid()
    p = points[k]
    q = start[k]
    a0 = affine[k]
    nan = wp.float64(wp.nan)
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    # x' = q + a0 + a1 dx + a2 dy, y' = q + b0 + b1 dx + b2 dy; template = r0 + r1 right(x', y')
    prm = vec8(zero, a0[0, 0], a0[0, 1], zero, a0[1, 0], a0[1, 1], zero, one)
    n_pix = (2 * half + 1) * (2 * half + 1)
    done = int(0)
    nmat = mat88()
    vtv = zero
    for it in range(max_iter):
        nmat = mat88()
        rhs = vec8(zero)
        vtv = zero
        bad = int(0)
        for dy in range(-half, half + 1):
            for dx in range(-half, half + 1):
                fdx = wp.float64(dx)
                fdy = wp.float64(dy)
                t = sample(left, p[0] + fdx, p[1] + fdy)
                xr = q[0] + prm[0] + prm[1] * fdx + prm[2] * fdy
                yr = q[1] + prm[3] + prm[4] * fdx + prm[5] * fdy
                s = sample(right, xr, yr)
                gx = sample(right, xr + wp.float64(0.5), yr) - sample(right, xr - wp.float64(0.5), yr)
                gy = sample(right, xr, yr + wp.float64(0.5)) - sample(right, xr, yr - wp.float64(0.5))
                if not (wp.isfinite(t) and wp.isfinite(s) and wp.isfinite(gx) and wp.isfinite(gy)):
                    bad = 1
                    continue
                e = t - (prm[6] + prm[7] * s)
                gx = prm[7] * gx
                gy = prm[7] * gy
                jac = vec8(gx, gx * fdx, gx * fdy, gy, gy * fdx, gy * fdy, one, s)
                nmat = nmat + wp.outer(jac, jac)
                rhs = rhs + e * jac
                vtv += e * e
        if bad != 0:
            break
        d = solve8(nmat, rhs)
        if not wp.isfinite(d[0]):
            break
        prm = prm + d
        if wp.abs(d[0]) < tol and wp.abs(d[3]) < tol:
            done = it + 1
            break
    iterations[k] = done
    if done == 0 or wp.abs(prm[0]) > wp.float64(half) or wp.abs(prm[3]) > wp.float64(half):
        iterations[k] = 0
        out[k] = wp.vec2d(nan, nan)
        sigma[k] = wp.vec2d(nan, nan)
        sigma0[k] = nan
        return
    s0 = wp.sqrt(vtv / wp.float64(n_pix - 8))
    ex = solve8(nmat, vec8(one, zero, zero, zero, zero, zero, zero, zero))
    ey = solve8(nmat, vec8(zero, zero, zero, one, zero, zero, zero, zero))
    out[k] = wp.vec2d(q[0] + prm[0], q[1] + prm[3])
    sigma[k] = wp.vec2d(s0 * wp.sqrt(wp.abs(ex[0])), s0 * wp.sqrt(wp.abs(ey[3])))
    sigma0[k] = s0
