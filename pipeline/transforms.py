"""Coordinate transformers made once per process and shared.

Making a :class:`pyproj.Transformer` costs about a millisecond (PROJ looks the operation up in
its database); an image's tile functions made several for each image build, which a mosaic's
workers repeat for every image their tiles meet. :func:`transformer` keeps the ones made, by
their two CRSs. Since pyproj 3.1 a Transformer is safe to share between threads (each thread
gets its own PROJ object the first time it transforms), and the shared one transforms exactly
as a new one made from the same CRSs would.
"""

from __future__ import annotations

import collections
import threading

from pyproj import CRS, Transformer

__all__ = ["transformer", "is_identity"]

_MOST = 64  # transformers kept (the least recently used goes first)
_KEPT: collections.OrderedDict[tuple[str, str], Transformer] = collections.OrderedDict()
_LOCK = threading.Lock()


def transformer(src: CRS, dst: CRS) -> Transformer:
    """``Transformer.from_crs(src, dst, always_xy=True)``, made once per process for each
    pair of CRSs (by their WKT) and shared.

    Parameters
    ----------
    src, dst : pyproj.CRS

    Returns
    -------
    pyproj.Transformer
        x/y (easting/northing, longitude/latitude) in, x/y out.
    """
    key = (src.to_wkt(), dst.to_wkt())
    with _LOCK:
        got = _KEPT.get(key)
        if got is not None:
            _KEPT.move_to_end(key)
            return got
    made = Transformer.from_crs(src, dst, always_xy=True)  # (outside the lock: slow)
    with _LOCK:
        got = _KEPT.setdefault(key, made)
        _KEPT.move_to_end(key)
        while len(_KEPT) > _MOST:
            _KEPT.popitem(last=False)
    return got


def is_identity(t: Transformer) -> bool:
    """Whether ``t`` is PROJ's no-op (its two CRSs the same): it gives back what it is given,
    to the bit, so a caller may skip it (a forward map's few hundred thousand nodes, about
    2 ms on the 2-core machine, more in a thread's first call)."""
    return t.definition.split(" ", 1)[0] == "proj=noop"
