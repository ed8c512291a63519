"""Reading TIFF structure: the header, IFDs and tags of little-endian TIFF and BigTIFF files,
and the check that a written TIFF holds every block it declares (:func:`verify_tiff`), with the
storage facts that explain a failed write (:func:`storage_facts`).

The COG writer (:mod:`orthowarp.pipeline.raster.cog`) takes GDAL's tags from a template read
here; the atomic outputs (:mod:`orthowarp.pipeline.raster.io`) verify GDAL-written files here.
Neither is imported by this module. TIFF 6.0 and BigTIFF structures: Adobe, "TIFF Revision 6.0"
(1992); the BigTIFF proposal (www.awaresystems.be/imaging/tiff/bigtiff.html).
"""

from __future__ import annotations

import io
import os
import resource
import struct
from typing import BinaryIO

from ...errors import ParamError, RasterIOError

__all__ = ["TYPE_SIZE", "SHORT", "LONG", "LONG8", "RATIONAL", "tiff_header", "read_ifd", "read_tiff_tags",
           "verify_tiff", "storage_facts"]

#: Bytes per value of each TIFF field type (type code -> bytes).
TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4, 16: 8, 17: 8, 18: 8}
#: The field types of block offsets and sizes.
SHORT, LONG, LONG8 = 3, 4, 16
#: Two LONGs, numerator and denominator.
RATIONAL = 5

#: A TIFF tag's value as read: (field type, count, raw value bytes).
Tag = tuple[int, int, bytes]


def tiff_header(f: BinaryIO) -> tuple[bool, int]:
    """(big, offset of the first IFD) of the little-endian TIFF or BigTIFF open in ``f``."""
    f.seek(0)
    head = f.read(16)
    if head[:2] != b"II" or len(head) < 8:
        raise ParamError("not a little-endian TIFF file")
    version = struct.unpack_from("<H", head, 2)[0]
    if version not in (42, 43):
        raise ParamError(f"not a TIFF file (version {version})")
    big = version == 43
    return big, struct.unpack_from("<Q", head, 8)[0] if big else struct.unpack_from("<I", head, 4)[0]


def read_ifd(f: BinaryIO, ifd: int, big: bool, size: int) -> tuple[dict[int, Tag], int]:
    """Tags of the IFD at ``ifd`` of the TIFF open in ``f`` (``size`` bytes long): (tags, next
    IFD offset), tags as tag -> (type, count, raw value bytes)."""
    fmt_n, entry, inline = ("<Q", 20, 8) if big else ("<H", 12, 4)
    if not 0 < ifd < size:
        raise ParamError(f"IFD offset {ifd} outside the file ({size} bytes)")
    f.seek(ifd)
    n = struct.unpack(fmt_n, f.read(struct.calcsize(fmt_n)))[0]
    if n * entry > size:
        raise ParamError(f"IFD at {ifd} claims {n} entries")
    table = f.read(n * entry + inline)
    if len(table) < n * entry + inline:
        raise ParamError(f"IFD at {ifd} is truncated")
    tags = {}
    for k in range(n):
        e = k * entry
        tag, typ = struct.unpack_from("<HH", table, e)
        count = struct.unpack_from("<Q" if big else "<I", table, e + 4)[0]
        nbytes = TYPE_SIZE.get(typ, 1) * count
        if nbytes <= inline:
            raw = table[e + 4 + inline: e + 4 + inline + nbytes]
        else:
            off = struct.unpack_from("<Q" if big else "<I", table, e + 4 + inline)[0]
            if off + nbytes > size:
                raise ParamError(f"tag {tag} at IFD {ifd} points past the end of the file")
            f.seek(off)
            raw = f.read(nbytes)
        tags[tag] = (typ, count, bytes(raw))
    nxt = struct.unpack_from("<Q" if big else "<I", table, n * entry)[0]
    return tags, nxt


def read_tiff_tags(data: bytes) -> dict[int, Tag]:
    """Tags of the first IFD of a little-endian TIFF or BigTIFF held in ``data`` (bytes).

    Returns
    -------
    dict
        tag -> (type, count, raw value bytes).
    """
    f = io.BytesIO(data)
    big, ifd = tiff_header(f)
    return read_ifd(f, ifd, big, len(data))[0]


def _values(typ: int, raw: bytes) -> tuple[int, ...]:
    fmt = {SHORT: "H", LONG: "I", LONG8: "Q"}.get(typ)
    if fmt is None:
        raise ParamError(f"unexpected TIFF field type {typ} for block offsets or sizes")
    return struct.unpack("<%d%s" % (len(raw) // struct.calcsize(fmt), fmt), raw)


def verify_tiff(path: str, *, name: str | None = None) -> None:
    """Check that every image of a written TIFF has all its blocks stored in the file: each
    block's offset and size are non-zero and within the file. GDAL's close does not report a
    failed flush (a full disk leaves blocks with zero offsets, which readers take for empty
    blocks); this structural check finds them.

    Parameters
    ----------
    path : str
    name : str, optional
        The file named in messages (the destination, where ``path`` is its temporary).

    Raises
    ------
    RasterIOError
        Naming the file and the first missing or truncated block.
    """
    name = path if name is None else name
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as f:
            big, ifd = tiff_header(f)
            seen, k = set(), 0
            while ifd:
                if ifd in seen or len(seen) > 10000:
                    raise ParamError("the IFD chain loops")
                seen.add(ifd)
                tags, nxt = read_ifd(f, ifd, big, size)
                off_tag, len_tag = (324, 325) if 324 in tags else (273, 279)
                if off_tag not in tags or len_tag not in tags:
                    raise ParamError(f"image {k} has no block offsets")
                offsets, lengths = _values(*tags[off_tag][::2]), _values(*tags[len_tag][::2])
                if len(offsets) != len(lengths):
                    raise ParamError(f"image {k} has {len(offsets)} block offsets but {len(lengths)} sizes")
                for b, (o, n) in enumerate(zip(offsets, lengths)):
                    if o == 0 or n == 0 or o + n > size:
                        raise ParamError(f"block {b} of image {k} is missing or truncated (offset {o}, "
                                         f"{n} bytes, file {size} bytes)")
                ifd, k = nxt, k + 1
    except (ParamError, struct.error) as e:
        raise RasterIOError(f"Could not write '{name}': the file is incomplete ({e}){storage_facts(path)}") from e
    except OSError as e:
        raise RasterIOError(f"Could not check '{name}': {e.strerror or e}") from e


def storage_facts(path: str) -> str:
    """What the system says about room for writing ``path``: "; the file reached the
    process's file-size limit (ulimit -f) of N bytes" or "; the file system has N bytes free",
    or "" when neither applies. For errors from GDAL, which reports a failed write without its
    cause (errno)."""
    facts = []
    try:
        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if soft != resource.RLIM_INFINITY and os.path.getsize(path) >= soft - (1 << 16):
            facts.append(f"the file reached the process's file-size limit (ulimit -f) of {soft} bytes")
    except OSError:
        pass
    try:
        st = os.statvfs(os.path.dirname(os.path.abspath(path)))
        free = st.f_bavail * st.f_frsize
        if free < (1 << 24):
            facts.append(f"the file system has {free} bytes free")
    except OSError:
        pass
    return "".join(f"; {f}" for f in facts)
