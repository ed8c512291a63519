"""Cloud-optimized GeoTIFF blocks on the device: predictor, masks, overviews, checksums.

The COG writer's per-block work, for tiles that are already on the device (see
:mod:`orthowarp.pipeline.raster.device`):

- :func:`encode_blocks_kernel`: cut a level's piece (rows, cols, bands) into the file's
  B x B blocks, pixel-interleaved; integer pixels outside the mask set to 0 and TIFF
  predictor 2 applied (horizontal differencing per sample, modulo the type's range; not for
  JPEG blocks); float
  pixels copied (no predictor, NaN stays nodata); blocks past the raster's edge padded with
  0 / NaN;
- :func:`mask_bits_kernel`: the blocks of the per-dataset mask, 1 bit per pixel, rows padded
  to bytes, most significant bit first (TIFF's FillOrder 1);
- :func:`reduce_kernel`: the next overview level, 2 x 2 mean of the valid pixels (rounded
  half up for integers), valid where any of the four is;
- :func:`adler_partials_kernel` and :func:`adler_finish_kernel`: the Adler-32 of each
  uncompressed block (RFC 1950), which a zlib stream carries after its raw deflate data;
- :func:`gather_kernel`: pack variable-length compressed streams into one buffer.

All of these reproduce, bit for bit, what :class:`orthowarp.pipeline.raster.cog.CogWriter` computes
on the host for the same pixels.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

ADLER_MOD = wp.constant(wp.int64(65521))


@wp.func
def predicted(v: wp.int32, ok: wp.int32, prev: wp.int32, prev_ok: wp.int32, first: wp.int32, top: wp.int32) -> wp.int32:
    """TIFF predictor 2 of an integer sample: the pixel zeroed where invalid or past the edge,
    minus its left neighbour likewise, modulo top + 1 (the first column as it is)."""
    a = v * ok
    if first != 0:
        return a
    return (a - prev * prev_ok) & top


@wp.func
def stored_value(v: wp.uint8, ok: wp.int32, prev: wp.uint8, prev_ok: wp.int32, first: wp.int32, inside: wp.int32) -> wp.uint8:
    return wp.uint8(predicted(wp.int32(v), ok, wp.int32(prev), prev_ok, first, 255))


@wp.func
def stored_value(v: wp.uint16, ok: wp.int32, prev: wp.uint16, prev_ok: wp.int32, first: wp.int32, inside: wp.int32) -> wp.uint16:
    return wp.uint16(predicted(wp.int32(v), ok, wp.int32(prev), prev_ok, first, 65535))


@wp.func
def stored_value(v: wp.float32, ok: wp.int32, prev: wp.float32, prev_ok: wp.int32, first: wp.int32, inside: wp.int32) -> wp.float32:
    # floats: nodata is NaN, no predictor; NaN past the edge
    if inside != 0:
        return v
    return wp.nan


@wp.kernel
def encode_blocks_kernel(
    piece: wp.array3d(dtype=Any),
    valid: wp.array2d(dtype=wp.uint8),
    nbx: wp.int32,
    predict: wp.int32,
    out: wp.array4d(dtype=Any),
):
    """Blocks (nb, B, B, bands) of a piece (rows, cols, bands) whose top-left pixel is a block
    corner: block k covers rows (k // nbx) B ... and columns (k % nbx) B ... of the piece.
    ``valid`` (rows, cols): 1 where the pixel is valid (integer types: others stored as 0);
    ``predict`` 1: integer samples with TIFF predictor 2, 0: as they are (JPEG blocks)."""
    k, y, x = wp.tid()
    bsize = out.shape[1]
    py = (k // nbx) * bsize + y
    px = (k % nbx) * bsize + x
    row_in = py < piece.shape[0]
    inside = wp.int32(row_in and px < piece.shape[1])
    prev_in = wp.int32(row_in and x > 0 and px - 1 < piece.shape[1])
    ok = wp.int32(0)
    prev_ok = wp.int32(0)
    qy = wp.min(py, piece.shape[0] - 1)  # clamped reads; their values are then not used
    qx = wp.min(px, piece.shape[1] - 1)
    rx = wp.min(wp.max(px - 1, 0), piece.shape[1] - 1)
    if inside != 0:
        ok = wp.int32(valid[qy, qx] != wp.uint8(0))
    if prev_in != 0:
        prev_ok = wp.int32(valid[qy, rx] != wp.uint8(0))
    first = wp.int32(x == 0 or predict == 0)  # (the first column is stored as it is)
    for c in range(out.shape[3]):
        out[k, y, x, c] = stored_value(piece[qy, qx, c], ok, piece[qy, rx, c], prev_ok, first, inside)


@wp.kernel
def mask_bits_kernel(valid: wp.array2d(dtype=wp.uint8), nbx: wp.int32, out: wp.array3d(dtype=wp.uint8)):
    """Mask blocks (nb, B, B / 8): bit 7 - m of byte j of row y is pixel 8 j + m of that row."""
    k, y, j = wp.tid()
    bsize = out.shape[1]
    py = (k // nbx) * bsize + y
    px0 = (k % nbx) * bsize + 8 * j
    byte = wp.int32(0)
    if py < valid.shape[0]:
        for m in range(8):
            px = px0 + m
            if px < valid.shape[1]:
                if valid[py, px] != wp.uint8(0):
                    byte = byte | (1 << (7 - m))
    out[k, y, j] = wp.uint8(byte)


@wp.func
def rounded_mean(total: wp.float64, n: wp.int32) -> wp.int64:
    """Mean of n integer samples summing to ``total``, rounded half up (0 where n is 0)."""
    return (wp.int64(total) + wp.int64(n // 2)) / wp.int64(wp.max(n, 1))


@wp.func
def mean_of(total: wp.float64, n: wp.int32, like: wp.uint8) -> wp.uint8:
    return wp.uint8(rounded_mean(total, n))


@wp.func
def mean_of(total: wp.float64, n: wp.int32, like: wp.uint16) -> wp.uint16:
    return wp.uint16(rounded_mean(total, n))


@wp.func
def mean_of(total: wp.float64, n: wp.int32, like: wp.float32) -> wp.float32:
    if n == 0:
        return wp.nan
    return wp.float32(total / wp.float64(n))


@wp.kernel
def reduce_kernel(
    piece: wp.array3d(dtype=Any),
    valid: wp.array2d(dtype=wp.uint8),
    out: wp.array3d(dtype=Any),
    out_valid: wp.array2d(dtype=wp.uint8),
):
    """Next overview level of a piece: pixel (i, j) from the valid ones of the piece's pixels
    (2i .. 2i+1, 2j .. 2j+1) that exist (odd edges use what exists)."""
    i, j = wp.tid()
    n = wp.int32(0)
    for a in range(2):
        for b in range(2):
            y = 2 * i + a
            x = 2 * j + b
            if y < piece.shape[0] and x < piece.shape[1]:
                if valid[y, x] != wp.uint8(0):
                    n += 1
    for c in range(out.shape[2]):
        total = wp.float64(0.0)
        for a in range(2):
            for b in range(2):
                y = 2 * i + a
                x = 2 * j + b
                if y < piece.shape[0] and x < piece.shape[1]:
                    if valid[y, x] != wp.uint8(0):
                        total += wp.float64(piece[y, x, c])
        out[i, j, c] = mean_of(total, n, out[i, j, c])
    out_valid[i, j] = wp.uint8(n > 0)


for _t in (wp.uint8, wp.uint16, wp.float32):
    wp.overload(encode_blocks_kernel, {"piece": wp.array3d(dtype=_t), "out": wp.array4d(dtype=_t)})
    wp.overload(reduce_kernel, {"piece": wp.array3d(dtype=_t), "out": wp.array3d(dtype=_t)})


@wp.kernel
def adler_partials_kernel(
    data: wp.array(dtype=wp.uint8),
    offsets: wp.array(dtype=wp.int32),
    sizes: wp.array(dtype=wp.int32),
    chunk: wp.int32,
    s1: wp.array2d(dtype=wp.int64),
    s2: wp.array2d(dtype=wp.int64),
):
    """Per buffer and chunk of ``chunk`` bytes: the sum of the bytes d_i and of (L - i) d_i,
    i the byte's index in its buffer of L bytes (exact in int64 for L up to 2^26)."""
    k, c = wp.tid()
    size = sizes[k]
    start = c * chunk
    a = wp.int64(0)
    b = wp.int64(0)
    if start < size:
        end = wp.min(start + chunk, size)
        base = offsets[k]
        for i in range(start, end):
            d = wp.int64(data[base + i])
            a += d
            b += wp.int64(size - i) * d
    s1[k, c] = a
    s2[k, c] = b


@wp.kernel
def adler_finish_kernel(s1: wp.array2d(dtype=wp.int64), s2: wp.array2d(dtype=wp.int64),
                        sizes: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int64),
                        fill: wp.array(dtype=wp.int32)):
    """Adler-32 of each buffer: A = 1 + sum d_i, B = L + sum (L - i) d_i, both mod 65521,
    packed as B * 65536 + A (RFC 1950); and the byte that fills it whole: 0 where all its
    bytes are 0, 255 where all are 255 (the partial sums of bytes are exact, so they sum to
    0 or 255 L only then), else -1."""
    k = wp.tid()
    a = wp.int64(1)
    b = wp.int64(sizes[k]) % ADLER_MOD
    total = wp.int64(0)
    for c in range(s1.shape[1]):
        a = (a + s1[k, c] % ADLER_MOD) % ADLER_MOD
        b = (b + s2[k, c] % ADLER_MOD) % ADLER_MOD
        total += s1[k, c]
    out[k] = b * wp.int64(65536) + a
    f = -1
    if total == wp.int64(0):
        f = 0
    elif total == wp.int64(255) * wp.int64(sizes[k]):
        f = 255
    fill[k] = f


@wp.kernel
def gather_kernel(src: wp.array(dtype=wp.uint8), src_offsets: wp.array(dtype=wp.int32),
                  dst: wp.array(dtype=wp.uint8), dst_offsets: wp.array(dtype=wp.int32),
                  sizes: wp.array(dtype=wp.int32), chunk: wp.int32):
    """Copy buffer k (``sizes[k]`` bytes at ``src_offsets[k]``) to ``dst_offsets[k]``, one
    chunk of ``chunk`` bytes per thread."""
    k, c = wp.tid()
    start = c * chunk
    end = wp.min(start + chunk, sizes[k])
    for i in range(start, end):
        dst[dst_offsets[k] + i] = src[src_offsets[k] + i]
