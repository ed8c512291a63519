"""Deflate (RFC 1951) on the device: LZ77 with hash chains and lazy matching, dynamic Huffman.

Each stream is cut into *chunks* (at most 65535 bytes), each of which becomes a self-contained
piece of deflate data ending on a byte boundary, so that the pieces of a stream concatenate
into the stream without any bit shifting.

LZ77 in steps that each keep many threads busy:

- :func:`chain_part_kernel` (a few threads per chunk, each over a part of it, in order) and
  :func:`chain_link_kernel` (a thread per chunk and hash value): the hash chains over 3- or
  4-byte prefixes (a link per position), including the ``prime`` bytes before the chunk (the
  end of the same stream's previous chunk, which a decoder has already produced); the parts'
  chains joined into exactly those of one pass over the chunk;
- :func:`match_kernel` (a thread per run of consecutive positions, one candidate per loop
  step): the longest match along each position's chain, at most ``depth`` candidates,
  compared over at most ``nice`` bytes (the first to reach them ends the search), ending
  inside the position's parse part and reaching at most 32768 back; and the chunk's byte
  histogram;
- :func:`parse_kernel` (a thread per 4 KiB part of a chunk, in order) and
  :func:`parse_sum_kernel`: tokens from those matches with one-step lazy evaluation as in
  zlib's ``deflate_slow`` (a match is deferred by one byte when the next position matches
  longer), a match of ``nice`` bytes grown to its full length; the parts' symbol frequencies
  summed per chunk.

Then:

- :func:`huffman_kernel`: per chunk, the cheaper of the tokens and the bytes as literals (as
  libdeflate avoids short matches on data with few distinct literals; chosen here by the
  exact sizes of both blocks), length-limited Huffman code lengths for the literal/length
  (15 bits), distance (15 bits) and code-length (7 bits) alphabets, from a two-queue Huffman tree
  (van Leeuwen 1976) whose depth histogram is brought under the limit by the adjustment of
  ITU-T T.81 (JPEG) Annex K.3; the run-length coding of the code lengths (symbols 16, 17, 18);
  the exact size of the piece in bytes; a stored block instead where that is not larger.
- :func:`emit_kernel`: canonical codes (RFC 1951 section 3.2.2) and the piece's bits at the
  offset a prefix sum of the sizes gives it. A piece that does not end its stream is a dynamic
  block followed by an empty stored block (``BFINAL`` 0: the same byte alignment as zlib's
  ``Z_SYNC_FLUSH``); the last piece of a stream is a final block padded to a byte.

Chunk-local tables live in scratch arrays, one row per chunk (the tokens of a part from the
part's first byte's index on). Match finding independent per position followed by a
sequential parse is the usual arrangement of GPU LZ77 encoders. The host side is
:class:`orthowarp.pipeline.raster.device.WarpDeflate`.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

GOLDEN = wp.constant(wp.uint32(2654435761))  # Knuth's multiplicative hash
HASH_SIZE = wp.constant(1 << 13)  # head table entries per chunk (13-bit hash of 3 or 4 bytes)
PARSE_PART = wp.constant(4096)  # bytes of a chunk parsed by one thread (matches end inside the part)
MAX_CHUNK = 65535  # bytes per chunk: what one stored block holds
MAX_DIST = wp.constant(32768)  # the farthest a match reaches back
NSYM = wp.constant(336)  # per-chunk symbol row: literal/length 0-285, distance 286-315, code length 316-334
DIST0 = wp.constant(286)
CL0 = wp.constant(316)
CL_ROW = 320  # run-length coded code lengths per chunk: at most 286 + 30 entries


@wp.func
def hash_at(buf: wp.array(dtype=wp.uint8), p: wp.int32, hlen: wp.int32) -> wp.int32:
    """13-bit multiplicative hash of the hlen (3 or 4) bytes at p."""
    v = (wp.uint32(buf[p]) << wp.uint32(16)) | (wp.uint32(buf[p + 1]) << wp.uint32(8)) | wp.uint32(buf[p + 2])
    if hlen == 4:
        v = (v << wp.uint32(8)) | wp.uint32(buf[p + 3])
    return wp.int32((v * GOLDEN) >> wp.uint32(32 - 13))


@wp.func
def dist_code(d: wp.int32) -> wp.vec3i:
    """(code, extra bits, extra value) of a match distance 1-32768."""
    code = d - 1
    nx = int(0)
    xv = int(0)
    if d > 4:
        t = d - 1
        nb = int(0)
        v = t
        while v > 1:
            v = v >> 1
            nb = nb + 1
        code = 2 * nb + ((t >> (nb - 1)) & 1)
        nx = nb - 1
        xv = t & ((1 << nx) - 1)
    return wp.vec3i(code, nx, xv)


@wp.func
def parse_parts(n: wp.int32) -> wp.int32:
    """Parse parts of a chunk of n bytes (see :func:`parse_kernel`)."""
    return (n + PARSE_PART - 1) // PARSE_PART


@wp.func
def walk_start(buf: wp.array(dtype=wp.uint8), base: wp.int32, prev: wp.array2d(dtype=wp.int32), c: wp.int32,
               i: wp.int32, n: wp.int32, pr: wp.int32, hlen: wp.int32, depth: wp.int32, nice: wp.int32):
    """The start of position i's chain walk in :func:`match_kernel`: (first candidate,
    candidates left, longest match to look for, the byte a match longer than 2 must match
    first); no walk (no candidate, none left) where fewer than ``hlen`` bytes are left."""
    if i + hlen - 1 >= n:
        return -pr - 1, 0, 0, wp.uint8(0)
    cap = wp.min(wp.min(258, wp.min(n, (i // PARSE_PART + 1) * PARSE_PART) - i), nice)
    return prev[c, i + pr] - 1 - pr, depth, cap, buf[base + i + 2]


@wp.func
def chain_span(total: wp.int32, parts: wp.int32) -> wp.int32:
    """Positions per part of a chunk's ``total`` hashed positions (see chain_part_kernel)."""
    return (total + parts - 1) // parts


@wp.kernel
def chain_part_kernel(buf: wp.array(dtype=wp.uint8), chunk_off: wp.array(dtype=wp.int32),
                      chunk_len: wp.array(dtype=wp.int32), prime: wp.array(dtype=wp.int32), hlen: wp.int32,
                      first: wp.array3d(dtype=wp.uint16), last: wp.array3d(dtype=wp.uint16),
                      prev: wp.array2d(dtype=wp.int32)):
    """Hash chains of part s of chunk c (one thread, in position order). The positions j of
    the chunk that have ``hlen`` bytes left, from -pr (the window before the chunk, pr =
    prime[c]) on, indexed k = j + pr, are cut into as many equal parts of q positions as
    ``first`` has rows per chunk (at most 65535 positions each);
    within part s, prev[c, k] = 1 + the part's previous position k' with the same hash (0:
    none). The first and the last position of each hash in the part go to first[c, s, h]
    and last[c, s, h] as 1 + their offset in the part (0: none), which :func:`chain_link_kernel`
    joins across the parts (both tables must be zero on entry)."""
    c, s = wp.tid()
    pr = prime[c]
    total = pr + chunk_len[c] - hlen + 1
    if total <= 0:
        return
    q = chain_span(total, first.shape[1])
    k0 = s * q
    k1 = wp.min(k0 + q, total)
    start = chunk_off[c] - pr
    for k in range(k0, k1):
        h = hash_at(buf, start + k, hlen)
        l = wp.int32(last[c, s, h])
        if l == 0:
            first[c, s, h] = wp.uint16(k - k0 + 1)
        else:
            prev[c, k] = k0 + l
        last[c, s, h] = wp.uint16(k - k0 + 1)


@wp.kernel
def chain_link_kernel(chunk_len: wp.array(dtype=wp.int32), prime: wp.array(dtype=wp.int32), hlen: wp.int32,
                      first: wp.array3d(dtype=wp.uint16), last: wp.array3d(dtype=wp.uint16),
                      prev: wp.array2d(dtype=wp.int32), hist: wp.array2d(dtype=wp.int32)):
    """The chains across parts, for hash h of chunk c (a thread each): the first position of
    h in a part links to its last position in the nearest earlier part that holds h, so the
    chains are exactly those of one pass over the chunk. The tables are left zero for the
    next call; the chunk's byte histogram is cleared for :func:`match_kernel`."""
    c, h = wp.tid()
    if h < 256:
        hist[c, h] = 0
    total = prime[c] + chunk_len[c] - hlen + 1
    if total <= 0:
        return
    parts = first.shape[1]
    q = chain_span(total, parts)
    run = int(0)
    for s in range(parts):
        f = wp.int32(first[c, s, h])
        if f != 0:
            prev[c, s * q + f - 1] = run
            first[c, s, h] = wp.uint16(0)
        l = wp.int32(last[c, s, h])
        if l != 0:
            run = s * q + l
            last[c, s, h] = wp.uint16(0)


@wp.kernel
def match_kernel(buf: wp.array(dtype=wp.uint8), chunk_off: wp.array(dtype=wp.int32),
                 chunk_len: wp.array(dtype=wp.int32), prime: wp.array(dtype=wp.int32), hlen: wp.int32,
                 depth: wp.int32, nice: wp.int32, good: wp.int32, max_lazy: wp.int32, run: wp.int32,
                 prev: wp.array2d(dtype=wp.int32), best: wp.array2d(dtype=wp.int32), hist: wp.array2d(dtype=wp.int32)):
    """The longest match at each of ``run`` positions of chunk c, from g * run on (one
    thread per run of positions): best[c, i] = length << 16 | (distance - 1), 0 for none.

    The chain of a position is walked from the nearest earlier position, at most ``depth``
    candidates (once a match reaches ``good`` bytes, good > 0, only a quarter of those left:
    zlib's ``good_length``), stopping at ``nice`` bytes; of equal lengths the nearest wins; a
    match ends inside its parse part (see :func:`parse_kernel`) and reaches at most 32768
    back. One loop step is one candidate or the move to the next position, so the threads
    of a warp stay in step (walks differ in length; a thread per position left most lanes
    of a warp idle). A match of length L at position i, distance d, means L - 1 bytes at
    i + 1 match d back: those are not compared again (long runs cost a compare per byte,
    not one per byte and candidate). Where L >= ``max_lazy`` (> 0), position i + 1 is not
    searched at all: its match is at the same distance, the L - 1 bytes known and any more up
    to the cap (zlib's ``max_lazy_match``: after a match that long the parse takes it without
    looking one byte further, so the positions it covers need no search). Also the chunk's
    byte histogram."""
    c, g = wp.tid()
    n = chunk_len[c]
    i = g * run
    if i >= n:
        return
    iend = wp.min(i + run, n)
    base = chunk_off[c]
    pr = prime[c]
    # the walk of position i: next candidate, candidates left, longest match to look for, the
    # byte a longer match must match first; best length, found
    cand, left, cap, tail = walk_start(buf, base, prev, c, i, n, pr, hlen, depth, nice)
    bl = int(2)
    found = int(0)
    quartered = int(0)
    known_d = int(0)  # from the previous position's match: at this distance, known_l bytes match
    known_l = int(0)
    while i < iend:
        if cand >= -pr and left > 0 and bl < cap and i - cand <= MAX_DIST:
            if buf[base + cand + bl] == tail:
                m = int(0)
                if i - cand == known_d:  # the bytes the previous position's match verified
                    m = wp.min(known_l, cap)
                while m < cap:
                    if buf[base + cand + m] != buf[base + i + m]:
                        break
                    m = m + 1
                if m > bl:
                    bl = m
                    found = (m << 16) | (i - cand - 1)
                    if m < cap:
                        tail = buf[base + i + bl]
                    if good > 0 and m >= good and quartered == 0:
                        left = left // 4
                        quartered = 1
            cand = prev[c, cand + pr] - 1 - pr
            left = left - 1
        else:
            best[c, i] = found
            wp.atomic_add(hist, c, wp.int32(buf[base + i]), 1)
            known_d = (found & 65535) + 1
            known_l = wp.max((found >> 16) - 1, 0)
            i = i + 1
            bl = 2
            found = 0
            quartered = 0
            if i < iend:
                cand, left, cap, tail = walk_start(buf, base, prev, c, i, n, pr, hlen, depth, nice)
                if max_lazy > 0 and known_l + 1 >= max_lazy and left > 0:
                    # no search: the same distance, its known bytes and any more up to the cap
                    m = wp.min(known_l, cap)
                    while m < cap:
                        if buf[base + i - known_d + m] != buf[base + i + m]:
                            break
                        m = m + 1
                    if m >= 3:  # (cap < 3 near a part's end: no match)
                        found = (m << 16) | (known_d - 1)
                    left = 0


@wp.func
def add_literal(v: wp.int32, nt: wp.int32, c: wp.int32, p: wp.int32, tokens: wp.array2d(dtype=wp.uint32),
                freq: wp.array3d(dtype=wp.int32)):
    tokens[c, nt] = wp.uint32(v)
    freq[c, p, v] = freq[c, p, v] + 1


@wp.func
def extended(buf: wp.array(dtype=wp.uint8), base: wp.int32, pos: wp.int32, dist: wp.int32, length: wp.int32,
             n: wp.int32) -> wp.int32:
    """A match at pos of at least ``length`` bytes, ``dist`` back, grown to its full length
    (at most 258, ending at or before n)."""
    m = length
    top = wp.min(258, n - pos)
    while m < top:
        if buf[base + pos + m] != buf[base + pos - dist + m]:
            break
        m = m + 1
    return m


@wp.func
def add_match(length: wp.int32, dist: wp.int32, nt: wp.int32, c: wp.int32, p: wp.int32,
              tokens: wp.array2d(dtype=wp.uint32), freq: wp.array3d(dtype=wp.int32),
              len_sym: wp.array(dtype=wp.int32), len_xbits: wp.array(dtype=wp.int32)) -> wp.int32:
    """Store a match token; its extra bits returned."""
    tokens[c, nt] = (wp.uint32(length - 2) << wp.uint32(16)) | wp.uint32(dist - 1)
    s = len_sym[length]
    freq[c, p, s] = freq[c, p, s] + 1
    dc = dist_code(dist)
    freq[c, p, DIST0 + dc[0]] = freq[c, p, DIST0 + dc[0]] + 1
    return len_xbits[length] + dc[1]


@wp.kernel
def parse_kernel(buf: wp.array(dtype=wp.uint8), chunk_off: wp.array(dtype=wp.int32),
                 chunk_len: wp.array(dtype=wp.int32), nice: wp.int32, lazy: wp.int32,
                 len_sym: wp.array(dtype=wp.int32), len_xbits: wp.array(dtype=wp.int32),
                 best: wp.array2d(dtype=wp.int32), tokens: wp.array2d(dtype=wp.uint32),
                 ntok: wp.array2d(dtype=wp.int32), freq: wp.array3d(dtype=wp.int32),
                 extra: wp.array2d(dtype=wp.int32)):
    """Tokens of part p (bytes p * PARSE_PART onwards, PARSE_PART of them at most) of chunk c
    from the matches found at each position (one thread, in order; a match ends inside its
    part): a match is deferred by one byte when the next position matches longer (zlib's
    ``deflate_slow``). Tokens, from tokens[c, p * PARSE_PART] on (ntok[c, p] of them):
    (length - 2) << 16 | (distance - 1) for a match, the byte for a literal; the part's
    literal/length and distance frequencies in freq[c, p] and its extra bits in extra[c, p]."""
    c, p = wp.tid()
    n = chunk_len[c]
    for s in range(DIST0 + 30):
        freq[c, p, s] = 0
    a = p * PARSE_PART
    if a >= n:
        ntok[c, p] = 0
        extra[c, p] = 0
        return
    b = wp.min(a + PARSE_PART, n)
    base = chunk_off[c]
    i = a
    nt = a
    xb = int(0)
    pl = int(0)  # length of the match deferred from position i - 1
    pd = int(0)
    while i < b:
        e = best[c, i]
        ml = wp.min(e >> 16, b - i)
        md = (e & 65535) + 1
        if pl >= 3:
            if ml > pl:  # the match one byte later is longer: the byte before it goes literal
                add_literal(wp.int32(buf[base + i - 1]), nt, c, p, tokens, freq)
                nt = nt + 1
                pl = ml
                pd = md
                i = i + 1
            else:
                if pl >= nice:
                    pl = extended(buf, base, i - 1, pd, pl, b)
                xb = xb + add_match(pl, pd, nt, c, p, tokens, freq, len_sym, len_xbits)
                nt = nt + 1
                i = i - 1 + pl
                pl = 0
        elif ml >= 3:
            if lazy == 0 or ml >= nice:
                if ml >= nice:
                    ml = extended(buf, base, i, md, ml, b)
                xb = xb + add_match(ml, md, nt, c, p, tokens, freq, len_sym, len_xbits)
                nt = nt + 1
                i = i + ml
            else:
                pl = ml
                pd = md
                i = i + 1
        else:
            add_literal(wp.int32(buf[base + i]), nt, c, p, tokens, freq)
            nt = nt + 1
            i = i + 1
    if pl >= 3:
        if pl >= nice:
            pl = extended(buf, base, b - 1, pd, pl, b)
        xb = xb + add_match(pl, pd, nt, c, p, tokens, freq, len_sym, len_xbits)
        nt = nt + 1
    ntok[c, p] = nt - a
    extra[c, p] = xb


@wp.kernel
def parse_sum_kernel(chunk_len: wp.array(dtype=wp.int32), part_freq: wp.array3d(dtype=wp.int32),
                     part_extra: wp.array2d(dtype=wp.int32), hist: wp.array2d(dtype=wp.int32),
                     freq: wp.array2d(dtype=wp.int32), extra: wp.array(dtype=wp.int32),
                     entropy: wp.array(dtype=wp.float32)):
    """Chunk c's symbol frequencies (thread (c, s) for symbol s; end of block counted) from
    its parts'; thread (c, 0) also sums the extra bits and computes the bytes' order-0 entropy
    (bits per byte) for huffman_kernel's choice between tokens and literals."""
    c, s = wp.tid()
    n = chunk_len[c]
    nparts = parse_parts(n)
    f = int(0)
    if s < DIST0 + 30:
        for p in range(nparts):
            f = f + part_freq[c, p, s]
    if s == 256:
        f = f + 1
    freq[c, s] = f
    if s == 0:
        xb = int(0)
        for p in range(nparts):
            xb = xb + part_extra[c, p]
        extra[c] = xb
        ent = float(0.0)
        for v in range(256):
            h = hist[c, v]
            if h > 0:
                q = float(h) / float(n)
                ent = ent - q * wp.log2(q)
        entropy[c] = ent


@wp.func
def sift_down(srt: wp.array2d(dtype=wp.int32), c: wp.int32, root: wp.int32, size: wp.int32):
    """Restore the max-heap property of srt[c, 0:size] below ``root``."""
    r = root
    while 2 * r + 1 < size:
        ch = 2 * r + 1
        if ch + 1 < size:
            if srt[c, ch + 1] > srt[c, ch]:
                ch = ch + 1
        if srt[c, r] >= srt[c, ch]:
            break
        v = srt[c, r]
        srt[c, r] = srt[c, ch]
        srt[c, ch] = v
        r = ch


@wp.func
def code_lengths(freq: wp.array2d(dtype=wp.int32), lens: wp.array2d(dtype=wp.int32), c: wp.int32,
                 first: wp.int32, nsym: wp.int32, limit: wp.int32, srt: wp.array2d(dtype=wp.int32),
                 node: wp.array2d(dtype=wp.int32), pleaf: wp.array2d(dtype=wp.int32),
                 pnode: wp.array2d(dtype=wp.int32), bits: wp.array2d(dtype=wp.int32)):
    """Huffman code lengths, at most ``limit`` bits, of symbols first .. first + nsym - 1 of
    row ``c`` of ``freq`` into the same places of ``lens`` (0 for unused symbols; with fewer
    than two used symbols, the first unused ones get a code too, as a decoder needs a complete
    code)."""
    n = int(0)
    for s in range(nsym):
        lens[c, first + s] = 0
        f = freq[c, first + s]
        if f > 0:
            srt[c, n] = f * 512 + s  # key: weight, then symbol
            n = n + 1
    s = int(0)
    while n < 2:
        if freq[c, first + s] == 0:
            srt[c, n] = 512 + s
            n = n + 1
        s = s + 1
    # heapsort, ascending (the keys are distinct)
    k = n // 2 - 1
    while k >= 0:
        sift_down(srt, c, k, n)
        k = k - 1
    e = n - 1
    while e > 0:
        top = srt[c, 0]
        srt[c, 0] = srt[c, e]
        srt[c, e] = top
        sift_down(srt, c, 0, e)
        e = e - 1
    # two-queue Huffman tree: leaves in weight order, internal nodes in creation order
    li = int(0)
    qi = int(0)
    for m in range(n - 1):
        w = int(0)
        for t in range(2):
            take_leaf = int(0)
            if li < n:
                if qi >= m:
                    take_leaf = int(1)
                elif (srt[c, li] >> 9) <= node[c, qi]:
                    take_leaf = int(1)
            if take_leaf != 0:
                w = w + (srt[c, li] >> 9)
                pleaf[c, li] = m
                li = li + 1
            else:
                w = w + node[c, qi]
                pnode[c, qi] = m
                qi = qi + 1
        node[c, m] = w
    # depths (node[] reused): the root, created last, at 0
    node[c, n - 2] = 0
    q = n - 3
    while q >= 0:
        node[c, q] = node[c, pnode[c, q]] + 1
        q = q - 1
    for z in range(32):
        bits[c, z] = 0
    maxd = int(0)
    for k in range(n):
        dk = node[c, pleaf[c, k]] + 1
        bits[c, dk] = bits[c, dk] + 1
        maxd = wp.max(maxd, dk)
    # ITU-T T.81 Annex K.3: move pairs of the deepest leaves up until no code is too long
    d = maxd
    while d > limit:
        while bits[c, d] > 0:
            j = d - 2
            while bits[c, j] == 0:
                j = j - 1
            bits[c, d] = bits[c, d] - 2
            bits[c, d - 1] = bits[c, d - 1] + 1
            bits[c, j + 1] = bits[c, j + 1] + 2
            bits[c, j] = bits[c, j] - 1
        d = d - 1
    # the rarest symbols get the longest codes
    k = int(0)
    d = wp.min(maxd, limit)
    while d >= 1:
        for t in range(bits[c, d]):
            lens[c, first + (srt[c, k] & 511)] = d
            k = k + 1
        d = d - 1


@wp.func
def seq_len(lens: wp.array2d(dtype=wp.int32), c: wp.int32, k: wp.int32, hlit: wp.int32) -> wp.int32:
    """Entry k of the code-length sequence: hlit literal/length lengths, then the distances'."""
    if k < hlit:
        return lens[c, k]
    return lens[c, DIST0 + k - hlit]


@wp.func
def add_cl(sym: wp.int32, xv: wp.int32, k: wp.int32, c: wp.int32, clsym: wp.array2d(dtype=wp.int32),
           freq: wp.array2d(dtype=wp.int32)):
    clsym[c, k] = sym | (xv << 8)
    freq[c, CL0 + sym] = freq[c, CL0 + sym] + 1


@wp.func
def plan_block(c: wp.int32, xbits: wp.int32, cl_order: wp.array(dtype=wp.int32), freq: wp.array2d(dtype=wp.int32),
               lens: wp.array2d(dtype=wp.int32), clsym: wp.array2d(dtype=wp.int32), srt: wp.array2d(dtype=wp.int32),
               node: wp.array2d(dtype=wp.int32), pleaf: wp.array2d(dtype=wp.int32),
               pnode: wp.array2d(dtype=wp.int32), bits: wp.array2d(dtype=wp.int32),
               header: wp.array2d(dtype=wp.int32)) -> wp.int64:
    """Code lengths of a dynamic block for the frequencies in row c (literal/length and
    distance symbols; ``xbits`` extra bits in all), the run-length coded code lengths and
    header[c, 0:4] = (hlit, hdist, hclen, number of coded code lengths). Returns the block's
    size in bits."""
    code_lengths(freq, lens, c, 0, 286, 15, srt, node, pleaf, pnode, bits)
    code_lengths(freq, lens, c, DIST0, 30, 15, srt, node, pleaf, pnode, bits)
    hlit = int(286)
    while hlit > 257 and lens[c, hlit - 1] == 0:
        hlit = hlit - 1
    hdist = int(30)
    while hdist > 1 and lens[c, DIST0 + hdist - 1] == 0:
        hdist = hdist - 1
    # run-length coding of the hlit + hdist code lengths (RFC 1951 3.2.7)
    for s in range(19):
        freq[c, CL0 + s] = 0
    total = hlit + hdist
    k = int(0)
    ncl = int(0)
    while k < total:
        v = seq_len(lens, c, k, hlit)
        run = int(1)
        while k + run < total:
            if seq_len(lens, c, k + run, hlit) != v:
                break
            run = run + 1
        r = run
        if v == 0:
            while r >= 11:
                m = wp.min(r, 138)
                add_cl(18, m - 11, ncl, c, clsym, freq)
                ncl = ncl + 1
                r = r - m
            if r >= 3:
                add_cl(17, r - 3, ncl, c, clsym, freq)
                ncl = ncl + 1
                r = 0
        else:
            add_cl(v, 0, ncl, c, clsym, freq)
            ncl = ncl + 1
            r = r - 1
            while r >= 3:
                m = wp.min(r, 6)
                add_cl(16, m - 3, ncl, c, clsym, freq)
                ncl = ncl + 1
                r = r - m
        while r > 0:
            add_cl(v, 0, ncl, c, clsym, freq)
            ncl = ncl + 1
            r = r - 1
        k = k + run
    code_lengths(freq, lens, c, CL0, 19, 7, srt, node, pleaf, pnode, bits)
    hclen = int(19)
    while hclen > 4 and lens[c, CL0 + cl_order[hclen - 1]] == 0:
        hclen = hclen - 1
    nbits = wp.int64(3 + 14 + 3 * hclen)
    for s in range(19):
        nbits = nbits + wp.int64(freq[c, CL0 + s] * lens[c, CL0 + s])
    nbits = nbits + wp.int64(2 * freq[c, CL0 + 16] + 3 * freq[c, CL0 + 17] + 7 * freq[c, CL0 + 18])
    for s in range(286):
        nbits = nbits + wp.int64(freq[c, s] * lens[c, s])
    for s in range(30):
        nbits = nbits + wp.int64(freq[c, DIST0 + s] * lens[c, DIST0 + s])
    header[c, 0] = hlit
    header[c, 1] = hdist
    header[c, 2] = hclen
    header[c, 3] = ncl
    return nbits + wp.int64(xbits)


@wp.kernel
def huffman_kernel(buf: wp.array(dtype=wp.uint8), chunk_off: wp.array(dtype=wp.int32),
                   chunk_len: wp.array(dtype=wp.int32), last: wp.array(dtype=wp.int32),
                   entropy: wp.array(dtype=wp.float32), hist: wp.array2d(dtype=wp.int32),
                   cl_order: wp.array(dtype=wp.int32), tokens: wp.array2d(dtype=wp.uint32),
                   ntok: wp.array2d(dtype=wp.int32), extra: wp.array(dtype=wp.int32),
                   freq: wp.array2d(dtype=wp.int32), lens: wp.array2d(dtype=wp.int32),
                   clsym: wp.array2d(dtype=wp.int32), srt: wp.array2d(dtype=wp.int32),
                   node: wp.array2d(dtype=wp.int32), pleaf: wp.array2d(dtype=wp.int32),
                   pnode: wp.array2d(dtype=wp.int32), bits: wp.array2d(dtype=wp.int32),
                   header: wp.array2d(dtype=wp.int32), size: wp.array(dtype=wp.int32),
                   lens_keep: wp.array2d(dtype=wp.int32), clsym_keep: wp.array2d(dtype=wp.int32)):
    """Code lengths and the piece's size in bytes; header[c] = (hlit, hdist, hclen, number of
    run-length coded code lengths, stored).

    Where the chunk's bytes coded one by one could be smaller than its LZ77 tokens (noisy
    data: short matches cost more than the literals they replace; the bytes' entropy bounds
    the literals' size from below), the literal-only block is planned too and the smaller
    one kept, the tokens rewritten as literals if that is the one."""
    c = wp.tid()
    n = chunk_len[c]
    nbits = plan_block(c, extra[c], cl_order, freq, lens, clsym, srt, node, pleaf, pnode, bits, header)
    if n > 0 and wp.float64(n) * wp.float64(entropy[c]) < wp.float64(nbits):
        # keep the tokens' plan aside
        for s in range(NSYM):
            lens_keep[c, s] = lens[c, s]
        for k in range(header[c, 3]):
            clsym_keep[c, k] = clsym[c, k]
        h0 = header[c, 0]
        h1 = header[c, 1]
        h2 = header[c, 2]
        h3 = header[c, 3]
        base = chunk_off[c]
        for s in range(CL0):
            freq[c, s] = 0
        for s in range(256):
            freq[c, s] = hist[c, s]
        freq[c, 256] = 1
        lit_bits = plan_block(c, 0, cl_order, freq, lens, clsym, srt, node, pleaf, pnode, bits, header)
        if lit_bits < nbits:
            for k in range(n):
                tokens[c, k] = wp.uint32(buf[base + k])
            for p in range(parse_parts(n)):
                ntok[c, p] = wp.min(PARSE_PART, n - p * PARSE_PART)
            extra[c] = 0
            nbits = lit_bits
        else:  # back to the tokens' plan
            for s in range(NSYM):
                lens[c, s] = lens_keep[c, s]
            for k in range(h3):
                clsym[c, k] = clsym_keep[c, k]
            header[c, 0] = h0
            header[c, 1] = h1
            header[c, 2] = h2
            header[c, 3] = h3
    dyn = int(0)
    if last[c] != 0:
        dyn = wp.int32((nbits + wp.int64(7)) >> wp.int64(3))
    else:  # then an empty stored block: 3 bits, pad, LEN and NLEN
        dyn = wp.int32((nbits + wp.int64(3 + 7)) >> wp.int64(3)) + 4
    stored = int(0)
    if n == 0 or n + 5 <= dyn:
        stored = 1
        size[c] = n + 5
    else:
        size[c] = dyn
    header[c, 4] = stored


@wp.func
def put(out: wp.array(dtype=wp.uint8), pos: wp.int32, acc: wp.uint64, nb: wp.int32, v: wp.int32,
        n: wp.int32):
    """Append the n low bits of v (least significant first) to the bit buffer ``acc`` holding
    ``nb`` bits; whole bytes go to out[pos...]. Returns (pos, acc, nb)."""
    a = acc | (wp.uint64(v) << wp.uint64(nb))
    k = nb + n
    p = pos
    while k >= 8:
        out[p] = wp.uint8(a & wp.uint64(255))
        a = a >> wp.uint64(8)
        k = k - 8
        p = p + 1
    return p, a, k


@wp.func
def canonical(lens: wp.array2d(dtype=wp.int32), codes: wp.array2d(dtype=wp.int32), c: wp.int32,
              first: wp.int32, nsym: wp.int32, bits: wp.array2d(dtype=wp.int32)):
    """Canonical Huffman codes (RFC 1951 3.2.2) of the lengths, bit-reversed for output least
    significant bit first."""
    for z in range(32):
        bits[c, z] = 0
    for s in range(nsym):
        ls = lens[c, first + s]
        if ls > 0:
            bits[c, ls] = bits[c, ls] + 1
    code = int(0)
    for z in range(1, 16):
        code = (code + bits[c, z - 1]) << 1
        bits[c, 16 + z] = code
    for s in range(nsym):
        d = lens[c, first + s]
        if d > 0:
            v = bits[c, 16 + d]
            bits[c, 16 + d] = v + 1
            r = int(0)
            for t in range(d):
                r = (r << 1) | (v & 1)
                v = v >> 1
            codes[c, first + s] = r


@wp.kernel
def emit_kernel(buf: wp.array(dtype=wp.uint8), chunk_off: wp.array(dtype=wp.int32),
                chunk_len: wp.array(dtype=wp.int32), last: wp.array(dtype=wp.int32),
                out_off: wp.array(dtype=wp.int32), cl_order: wp.array(dtype=wp.int32),
                len_sym: wp.array(dtype=wp.int32), len_xbits: wp.array(dtype=wp.int32),
                len_xval: wp.array(dtype=wp.int32), tokens: wp.array2d(dtype=wp.uint32),
                ntok: wp.array2d(dtype=wp.int32), lens: wp.array2d(dtype=wp.int32),
                codes: wp.array2d(dtype=wp.int32), clsym: wp.array2d(dtype=wp.int32),
                bits: wp.array2d(dtype=wp.int32), header: wp.array2d(dtype=wp.int32),
                out: wp.array(dtype=wp.uint8), end: wp.array(dtype=wp.int32)):
    """Write chunk c's piece at out[out_off[c]:]; end[c] = the offset after its last byte."""
    c = wp.tid()
    p = out_off[c]
    n = chunk_len[c]
    fin = last[c]
    if header[c, 4] != 0:  # stored block
        out[p] = wp.uint8(fin)
        out[p + 1] = wp.uint8(n & 255)
        out[p + 2] = wp.uint8(n >> 8)
        out[p + 3] = wp.uint8((n & 255) ^ 255)
        out[p + 4] = wp.uint8((n >> 8) ^ 255)
        base = chunk_off[c]
        for k in range(n):
            out[p + 5 + k] = buf[base + k]
        end[c] = p + 5 + n
        return
    canonical(lens, codes, c, 0, 286, bits)
    canonical(lens, codes, c, DIST0, 30, bits)
    canonical(lens, codes, c, CL0, 19, bits)
    hlit = header[c, 0]
    hdist = header[c, 1]
    hclen = header[c, 2]
    acc = wp.uint64(0)
    nb = int(0)
    p, acc, nb = put(out, p, acc, nb, fin | (2 << 1), 3)
    p, acc, nb = put(out, p, acc, nb, (hlit - 257) | ((hdist - 1) << 5) | ((hclen - 4) << 10), 14)
    for k in range(hclen):
        p, acc, nb = put(out, p, acc, nb, lens[c, CL0 + cl_order[k]], 3)
    for k in range(header[c, 3]):
        e = clsym[c, k]
        sym = e & 255
        p, acc, nb = put(out, p, acc, nb, codes[c, CL0 + sym], lens[c, CL0 + sym])
        if sym == 16:
            p, acc, nb = put(out, p, acc, nb, e >> 8, 2)
        elif sym == 17:
            p, acc, nb = put(out, p, acc, nb, e >> 8, 3)
        elif sym == 18:
            p, acc, nb = put(out, p, acc, nb, e >> 8, 7)
    for part in range(parse_parts(n)):
        a = part * PARSE_PART
        for k in range(a, a + ntok[c, part]):
            t = tokens[c, k]
            top = wp.int32(t >> wp.uint32(16))
            if top == 0:
                v = wp.int32(t)
                p, acc, nb = put(out, p, acc, nb, codes[c, v], lens[c, v])
            else:
                length = top + 2
                ls = len_sym[length]
                p, acc, nb = put(out, p, acc, nb, codes[c, ls], lens[c, ls])
                if len_xbits[length] > 0:
                    p, acc, nb = put(out, p, acc, nb, len_xval[length], len_xbits[length])
                dc = dist_code(wp.int32(t & wp.uint32(65535)) + 1)
                p, acc, nb = put(out, p, acc, nb, codes[c, DIST0 + dc[0]], lens[c, DIST0 + dc[0]])
                if dc[1] > 0:
                    p, acc, nb = put(out, p, acc, nb, dc[2], dc[1])
    p, acc, nb = put(out, p, acc, nb, codes[c, 256], lens[c, 256])
    if fin == 0:  # an empty stored block brings the piece to a byte boundary
        p, acc, nb = put(out, p, acc, nb, 0, 3)
    if nb > 0:
        p, acc, nb = put(out, p, acc, nb, 0, 8 - nb)
    q = p
    if fin == 0:
        out[q] = wp.uint8(0)
        out[q + 1] = wp.uint8(0)
        out[q + 2] = wp.uint8(255)
        out[q + 3] = wp.uint8(255)
        q = q + 4
    end[c] = q
