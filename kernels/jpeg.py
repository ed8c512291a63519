"""Baseline JPEG (ITU-T T.81) on the device: many blocks encoded at once, each its own scan.

Each uint8 block of B x B pixels (pixel-interleaved, 1 or 3 bands; B a multiple of 16) becomes
the entropy-coded data of one sequential-DCT scan without restart intervals:

- three bands: JFIF's YCbCr (BT.601, full range), each pixel converted in 16-bit fixed point
  (the coefficients times 65536, rounded; Cb and Cr offset by 128 and rounded half down, as
  libjpeg does), the chroma then averaged over 2 x 2 pixels (the sum plus 1 or 2 in alternate
  columns, divided by 4), in interleaved MCUs of four luminance units (two rows of two) and
  one unit each of Cb and Cr (T.81 A.2.3);
- one band: grey, units in raster order.

The steps, each over many threads (a *unit* is one component's 8 x 8 samples):

- :func:`dct_kernel` (a thread per unit): the samples, level-shifted by 128, the 2-D DCT-II
  of T.81 A.3.3 by the scaled integer algorithm of Loeffler, Ligtenberg and Moschytz ("Practical
  fast 1-D DCT algorithms with 11 multiplications", ICASSP 1989) with the constants and
  rounding of the IJG's "slow integer" method (13-bit cosines, 2 extra bits between the row
  and column passes, coefficients 8 times the standard's), divided by 8 times the quantization
  table and rounded half away from zero, stored in zigzag order (T.81 A.3.6): what libjpeg's
  default path computes, so the streams are its own;
- :func:`size_kernel` (a thread per unit): the bits of its Huffman codes and amplitudes
  (:func:`code_unit` without emission; T.81 F.1.2: the DC difference from the previous unit of
  its component, the AC coefficients as run/size symbols with ZRL and EOB);
- :func:`offsets_kernel` (a thread per block): those sizes summed in the scan's order;
- :func:`emit_kernel` (a thread per unit): the same walk (:func:`code_unit`) emitting its bits,
  most significant first, into 32-bit words at its offset. Every bit is written by one unit
  only and the words start at zero, so the words two units share are completed by adding their
  bit patterns atomically (no lock);
- :func:`pad_kernel`: the last byte filled with 1 bits (T.81 F.1.2.3);
- :func:`ff_count_kernel`, :func:`ff_offsets_kernel` and :func:`stuff_kernel`: the bytes out
  of the words, each 0xFF followed by a stuffed 0x00 (T.81 B.1.1.5), by chunks of
  :data:`STUFF_CHUNK` bytes placed by a prefix sum of their 0xFF counts.

The tables (quantization, Huffman codes) come from the host in a :class:`JpegTables`; the
marker segments around the data are the host's too (:mod:`orthowarp.pipeline.raster.jpeg`).
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

STUFF_CHUNK = wp.constant(1024)  # bytes per thread of the byte-stuffing kernels

mat88i = wp.types.matrix(shape=(8, 8), dtype=wp.int32)

# The integer DCT's constants (Loeffler, Ligtenberg and Moschytz 1989, as the IJG's "slow
# integer" method scales them): cosine products times 2**CONST_BITS, rounded
CONST_BITS = wp.constant(13)
PASS1_BITS = wp.constant(2)
FIX_0_298631336 = wp.constant(2446)
FIX_0_390180644 = wp.constant(3196)
FIX_0_541196100 = wp.constant(4433)
FIX_0_765366865 = wp.constant(6270)
FIX_0_899976223 = wp.constant(7373)
FIX_1_175875602 = wp.constant(9633)
FIX_1_501321110 = wp.constant(12299)
FIX_1_847759065 = wp.constant(15137)
FIX_1_961570560 = wp.constant(16069)
FIX_2_053119869 = wp.constant(16819)
FIX_2_562915447 = wp.constant(20995)
FIX_3_072711026 = wp.constant(25172)


@wp.struct
class JpegTables:
    """One file's coding tables (index 0: luminance / grey, 1: chroma).

    quant : (2, 64) int32, the quantization tables in natural (row-major) order
    zigzag : (64,) int32, the natural index of the k-th coefficient in zigzag order
    dc_code, dc_size : (2, 16) int32, the DC tables' code and length per category (0 length: absent)
    ac_code, ac_size : (2, 256) int32, the AC tables' code and length per run/size symbol
    """

    quant: wp.array2d(dtype=wp.int32)
    zigzag: wp.array(dtype=wp.int32)
    dc_code: wp.array2d(dtype=wp.int32)
    dc_size: wp.array2d(dtype=wp.int32)
    ac_code: wp.array2d(dtype=wp.int32)
    ac_size: wp.array2d(dtype=wp.int32)


@wp.func
def unit_table(u: wp.int32, bands: wp.int32) -> wp.int32:
    """The table (0 luminance or grey, 1 chroma) of unit ``u`` of a block."""
    if bands == 3 and u % 6 >= 4:
        return 1
    return 0


@wp.func
def previous_unit(u: wp.int32, bands: wp.int32) -> wp.int32:
    """The unit before ``u`` in the scan of the same component (its DC predictor), or -1."""
    if bands != 3:
        return u - 1
    j = u % 6
    if j == 1 or j == 2 or j == 3:
        return u - 1
    if u < 6:
        return -1
    if j == 0:
        return u - 3  # the last luminance unit of the MCU before
    return u - 6


@wp.func
def magnitude_bits(v: wp.int32) -> wp.int32:
    """The size category of ``v`` (T.81 F.1.2.1): bits of |v|."""
    a = wp.abs(v)
    n = wp.int32(0)
    while a > 0:
        n += 1
        a = a >> 1
    return n


@wp.func
def pixel(buf: wp.array(dtype=wp.uint8), base: wp.int32, block: wp.int32, bands: wp.int32, r: wp.int32,
          c: wp.int32, band: wp.int32) -> wp.int32:
    return wp.int32(buf[base + (r * block + c) * bands + band])


@wp.func
def luma(buf: wp.array(dtype=wp.uint8), base: wp.int32, block: wp.int32, r: wp.int32, c: wp.int32) -> wp.int32:
    """Y of a three-band pixel, 0-255."""
    at = base + (r * block + c) * 3
    return (19595 * wp.int32(buf[at]) + 38470 * wp.int32(buf[at + 1]) + 7471 * wp.int32(buf[at + 2]) + 32768) >> 16


@wp.func
def chroma(buf: wp.array(dtype=wp.uint8), base: wp.int32, block: wp.int32, r: wp.int32, c: wp.int32,
           cr: wp.int32) -> wp.int32:
    """Cb (``cr`` 0) or Cr (1) of a three-band pixel, 0-255."""
    at = base + (r * block + c) * 3
    red = wp.int32(buf[at])
    green = wp.int32(buf[at + 1])
    blue = wp.int32(buf[at + 2])
    if cr == 0:
        return (-11059 * red - 21709 * green + 32768 * blue + 8388608 + 32767) >> 16
    return (32768 * red - 27439 * green - 5329 * blue + 8388608 + 32767) >> 16


@wp.func
def descale(x: wp.int32, n: wp.int32) -> wp.int32:
    """x / 2**n rounded half up (an arithmetic shift)."""
    return (x + (1 << (n - 1))) >> n


@wp.func
def fdct_rows(f: mat88i, last: wp.int32) -> mat88i:
    """One pass of the scaled integer DCT over the rows of ``f``, as a new matrix: the first
    pass (``last`` 0), whose outputs keep PASS1_BITS more bits, or the second (1), run on the
    transposed first pass's output. After both the coefficients are 8 times T.81 A.3.3's."""
    out = mat88i()
    shift = CONST_BITS - PASS1_BITS
    if last != 0:
        shift = CONST_BITS + PASS1_BITS
    for k in range(8):
        tmp0 = f[k, 0] + f[k, 7]
        tmp7 = f[k, 0] - f[k, 7]
        tmp1 = f[k, 1] + f[k, 6]
        tmp6 = f[k, 1] - f[k, 6]
        tmp2 = f[k, 2] + f[k, 5]
        tmp5 = f[k, 2] - f[k, 5]
        tmp3 = f[k, 3] + f[k, 4]
        tmp4 = f[k, 3] - f[k, 4]
        # even part
        tmp10 = tmp0 + tmp3
        tmp13 = tmp0 - tmp3
        tmp11 = tmp1 + tmp2
        tmp12 = tmp1 - tmp2
        if last != 0:
            out[k, 0] = descale(tmp10 + tmp11, PASS1_BITS)
            out[k, 4] = descale(tmp10 - tmp11, PASS1_BITS)
        else:
            out[k, 0] = (tmp10 + tmp11) << PASS1_BITS
            out[k, 4] = (tmp10 - tmp11) << PASS1_BITS
        z1 = (tmp12 + tmp13) * FIX_0_541196100
        out[k, 2] = descale(z1 + tmp13 * FIX_0_765366865, shift)
        out[k, 6] = descale(z1 - tmp12 * FIX_1_847759065, shift)
        # odd part
        z1 = tmp4 + tmp7
        z2 = tmp5 + tmp6
        z3 = tmp4 + tmp6
        z4 = tmp5 + tmp7
        z5 = (z3 + z4) * FIX_1_175875602
        tmp4 = tmp4 * FIX_0_298631336
        tmp5 = tmp5 * FIX_2_053119869
        tmp6 = tmp6 * FIX_3_072711026
        tmp7 = tmp7 * FIX_1_501321110
        z1 = -z1 * FIX_0_899976223
        z2 = -z2 * FIX_2_562915447
        z3 = -z3 * FIX_1_961570560 + z5
        z4 = -z4 * FIX_0_390180644 + z5
        out[k, 7] = descale(tmp4 + z1 + z3, shift)
        out[k, 5] = descale(tmp5 + z2 + z4, shift)
        out[k, 3] = descale(tmp6 + z2 + z3, shift)
        out[k, 1] = descale(tmp7 + z1 + z4, shift)
    return out


@wp.kernel
def dct_kernel(buf: wp.array(dtype=wp.uint8), offsets: wp.array(dtype=wp.int32), block: wp.int32,
               bands: wp.int32, units: wp.int32, tables: JpegTables, coef: wp.array2d(dtype=wp.int16)):
    """Quantized DCT coefficients, zigzag order, of unit ``u`` of block ``s``: ``coef[s * units
    + u]``. dim = (blocks, units)."""
    s, u = wp.tid()
    base = offsets[s]
    f = mat88i()
    table = unit_table(u, bands)
    if bands == 3:
        per_row = block / 16
        mcu = u / 6
        j = u % 6
        r0 = (mcu / per_row) * 16
        c0 = (mcu % per_row) * 16
        if j < 4:
            r0 += (j / 2) * 8
            c0 += (j % 2) * 8
            for r in range(8):
                for c in range(8):
                    f[r, c] = luma(buf, base, block, r0 + r, c0 + c) - 128
        else:
            cr = j - 4
            for r in range(8):
                for c in range(8):
                    rr = r0 + 2 * r
                    cc = c0 + 2 * c
                    total = (chroma(buf, base, block, rr, cc, cr) + chroma(buf, base, block, rr, cc + 1, cr)
                             + chroma(buf, base, block, rr + 1, cc, cr) + chroma(buf, base, block, rr + 1, cc + 1, cr))
                    f[r, c] = ((total + 1 + (c % 2)) >> 2) - 128
    else:
        per_row = block / 8
        r0 = (u / per_row) * 8
        c0 = (u % per_row) * 8
        for r in range(8):
            for c in range(8):
                f[r, c] = pixel(buf, base, block, bands, r0 + r, c0 + c, 0) - 128
    d = wp.transpose(fdct_rows(wp.transpose(fdct_rows(f, 0)), 1))
    t = s * units + u
    for k in range(64):
        nat = tables.zigzag[k]
        div = tables.quant[table, nat] * 8  # (the coefficients are 8 times the standard's)
        v = d[nat / 8, nat % 8]
        q = (wp.abs(v) + div / 2) / div  # rounded half away from zero
        if v < 0:
            q = -q
        coef[t, k] = wp.int16(q)


@wp.func
def put(words: wp.array(dtype=wp.uint32), emit: wp.int32, acc: wp.uint64, fill: wp.int32, w: wp.int32,
        code: wp.int32, size: wp.int32):
    """``size`` bits of ``code`` appended to the bit buffer ``acc`` (``fill`` bits used, its
    first bit word ``w``'s first); with ``emit``, the words it completes added to ``words``."""
    if size > 0:
        acc = acc | (wp.uint64(code) << wp.uint64(64 - fill - size))
        fill += size
    while fill >= 32:
        if emit != 0:
            wp.atomic_add(words, w, wp.uint32(acc >> wp.uint64(32)))
        acc = acc << wp.uint64(32)
        fill -= 32
        w += 1
    return acc, fill, w


@wp.func
def amplitude(v: wp.int32, n: wp.int32) -> wp.int32:
    """The ``n`` low bits that code ``v`` (T.81 F.1.2.1: v, or v - 1 for negative values)."""
    if v < 0:
        return (v - 1) & ((1 << n) - 1)
    return v


@wp.func
def code_unit(coef: wp.array2d(dtype=wp.int16), t: wp.int32, u: wp.int32, bands: wp.int32, tables: JpegTables,
              words: wp.array(dtype=wp.uint32), first: wp.int32, at: wp.int32, emit: wp.int32) -> wp.int32:
    """Unit ``u`` (row ``t`` of ``coef``) Huffman-coded (T.81 F.1.2: the DC difference from the
    previous unit of its component, the AC coefficients as run/size symbols with ZRL and EOB):
    its bits; with ``emit``, also added into ``words`` from bit ``at`` of the data whose first
    word is ``first`` (bit 31 of a word first). The size pass and the emission are this one
    walk, so they cannot disagree."""
    table = unit_table(u, bands)
    w = first + at / 32
    fill = at % 32
    acc = wp.uint64(0)
    prev = previous_unit(u, bands)
    pred = wp.int32(0)
    if prev >= 0:
        pred = wp.int32(coef[t - u + prev, 0])
    diff = wp.int32(coef[t, 0]) - pred
    n = magnitude_bits(diff)
    acc, fill, w = put(words, emit, acc, fill, w, tables.dc_code[table, n], tables.dc_size[table, n])
    acc, fill, w = put(words, emit, acc, fill, w, amplitude(diff, n), n)
    run = wp.int32(0)
    for k in range(1, 64):
        v = wp.int32(coef[t, k])
        if v == 0:
            run += 1
        else:
            while run > 15:
                acc, fill, w = put(words, emit, acc, fill, w, tables.ac_code[table, 0xF0], tables.ac_size[table, 0xF0])
                run -= 16
            n = magnitude_bits(v)
            sym = run * 16 + n
            acc, fill, w = put(words, emit, acc, fill, w, tables.ac_code[table, sym], tables.ac_size[table, sym])
            acc, fill, w = put(words, emit, acc, fill, w, amplitude(v, n), n)
            run = 0
    if run > 0:
        acc, fill, w = put(words, emit, acc, fill, w, tables.ac_code[table, 0], tables.ac_size[table, 0])
    if emit != 0 and fill > 0:
        wp.atomic_add(words, w, wp.uint32(acc >> wp.uint64(32)))
    return (w - first) * 32 + fill - at


@wp.kernel
def size_kernel(coef: wp.array2d(dtype=wp.int16), bands: wp.int32, units: wp.int32, tables: JpegTables,
                no_words: wp.array(dtype=wp.uint32), bits: wp.array(dtype=wp.int32)):
    """The entropy-coded bits of each unit (:func:`code_unit` without emission; ``no_words``
    is not written). dim = blocks * units."""
    t = wp.tid()
    bits[t] = code_unit(coef, t, t % units, bands, tables, no_words, 0, 0, 0)


@wp.kernel
def offsets_kernel(bits: wp.array(dtype=wp.int32), units: wp.int32, start: wp.array(dtype=wp.int32),
                   total: wp.array(dtype=wp.int32)):
    """Each unit's first bit in its block's data, and each block's bits. dim = blocks."""
    s = wp.tid()
    acc = wp.int32(0)
    for u in range(units):
        start[s * units + u] = acc
        acc += bits[s * units + u]
    total[s] = acc


@wp.kernel
def emit_kernel(coef: wp.array2d(dtype=wp.int16), bands: wp.int32, units: wp.int32, tables: JpegTables,
                start: wp.array(dtype=wp.int32), word_base: wp.array(dtype=wp.int32),
                words: wp.array(dtype=wp.uint32)):
    """Each unit's codes into ``words`` (zeroed; block ``s``'s first word ``word_base[s]``,
    bit 31 of a word first; :func:`code_unit`). dim = blocks * units."""
    t = wp.tid()
    code_unit(coef, t, t % units, bands, tables, words, word_base[t / units], start[t], 1)


@wp.kernel
def pad_kernel(total: wp.array(dtype=wp.int32), word_base: wp.array(dtype=wp.int32),
               words: wp.array(dtype=wp.uint32)):
    """Each block's last byte filled with 1 bits. dim = blocks."""
    s = wp.tid()
    end = total[s]
    pad = (8 - end % 8) % 8
    if pad > 0:
        o = end % 32
        ones = (wp.uint32(1) << wp.uint32(pad)) - wp.uint32(1)
        wp.atomic_add(words, word_base[s] + end / 32, ones << wp.uint32(32 - o - pad))


@wp.func
def data_byte(words: wp.array(dtype=wp.uint32), first: wp.int32, j: wp.int32) -> wp.int32:
    """Byte ``j`` of the data whose first word is ``first`` (most significant byte first)."""
    return wp.int32((words[first + j / 4] >> wp.uint32(24 - 8 * (j % 4))) & wp.uint32(255))


@wp.kernel
def ff_count_kernel(words: wp.array(dtype=wp.uint32), word_base: wp.array(dtype=wp.int32),
                    total: wp.array(dtype=wp.int32), count: wp.array2d(dtype=wp.int32)):
    """0xFF bytes per chunk of each block's data. dim = (blocks, chunks)."""
    s, ch = wp.tid()
    nbytes = (total[s] + 7) / 8
    n = wp.int32(0)
    for j in range(ch * STUFF_CHUNK, wp.min(nbytes, (ch + 1) * STUFF_CHUNK)):
        if data_byte(words, word_base[s], j) == 255:
            n += 1
    count[s, ch] = n


@wp.kernel
def ff_offsets_kernel(count: wp.array2d(dtype=wp.int32), total: wp.array(dtype=wp.int32),
                      chunk_at: wp.array2d(dtype=wp.int32), stuffed: wp.array(dtype=wp.int32)):
    """Each chunk's first byte in its block's stuffed data, and each block's stuffed bytes.
    dim = blocks."""
    s = wp.tid()
    acc = wp.int32(0)
    for ch in range(count.shape[1]):
        chunk_at[s, ch] = ch * STUFF_CHUNK + acc
        acc += count[s, ch]
    stuffed[s] = (total[s] + 7) / 8 + acc


@wp.kernel
def stuff_kernel(words: wp.array(dtype=wp.uint32), word_base: wp.array(dtype=wp.int32),
                 total: wp.array(dtype=wp.int32), chunk_at: wp.array2d(dtype=wp.int32),
                 out_base: wp.array(dtype=wp.int64), out: wp.array(dtype=wp.uint8)):
    """The stuffed bytes of each chunk at their place in ``out`` (block ``s`` from
    ``out_base[s]``). dim = (blocks, chunks)."""
    s, ch = wp.tid()
    nbytes = (total[s] + 7) / 8
    at = out_base[s] + wp.int64(chunk_at[s, ch])
    for j in range(ch * STUFF_CHUNK, wp.min(nbytes, (ch + 1) * STUFF_CHUNK)):
        b = data_byte(words, word_base[s], j)
        out[at] = wp.uint8(b)
        at += wp.int64(1)
        if b == 255:
            out[at] = wp.uint8(0)
            at += wp.int64(1)


@wp.kernel
def zero_kernel(words: wp.array(dtype=wp.uint32)):
    """Clear ``words`` (on the codec's own stream, where ``wp.zeros`` would use the device's)."""
    words[wp.tid()] = wp.uint32(0)
