"""Argument validation helpers shared by the host classes."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from pyproj import CRS
from pyproj.exceptions import CRSError

from .errors import CrsError, ParamError

if TYPE_CHECKING:  # annotations only
    from numpy.typing import ArrayLike


def finite(name: str, value: Any) -> float:
    """``float(value)``, or ParamError naming ``name`` if it is not a finite number."""
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be a number, got {value!r}") from e
    if not math.isfinite(v):
        raise ParamError(f"{name} must be finite, got {value!r}")
    return v


def image_size(value: Any, name: str = "image_size") -> tuple[int, int]:
    """``(width, height)`` as two whole numbers >= 1 (pixels), or ParamError naming ``name``."""
    try:
        w, h = (int(v) for v in value)
        exact = all(float(v) == int(v) for v in value)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be (width, height) in pixels, got {value!r}") from e
    if not exact or w < 1 or h < 1:
        raise ParamError(f"{name} must be two whole numbers >= 1, got {value!r}")
    return w, h


def finite_vector(name: str, value: ArrayLike, n: int) -> np.ndarray:
    """A finite float64 vector of length n, or ParamError naming ``name``."""
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be {n} numbers, got {value!r}") from e
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ParamError(f"{name} must be {n} finite numbers, got {value!r}")
    return arr


def points(values: ArrayLike, ncol: int, name: str) -> np.ndarray:
    """A C-contiguous float64 array of shape (N, ncol); a single point (ncol,) becomes (1, ncol).

    The mask of a NumPy masked array is honoured: a row with any masked value becomes a NaN
    row (its fill values are never used). NaN marks a missing row. Complex and boolean arrays
    are refused rather than cast.
    """
    mask = None
    if np.ma.isMaskedArray(values):
        mask = np.ma.getmaskarray(values)
        values = np.ma.getdata(values)
    try:
        raw = np.asarray(values)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be a numeric array of shape (N, {ncol}): {e}") from e
    if raw.dtype.kind in "cb":
        kind = "complex" if raw.dtype.kind == "c" else "boolean"
        raise ParamError(f"{name} must be real numbers of shape (N, {ncol}), got a {kind} array")
    try:
        arr = np.array(raw, dtype=np.float64) if mask is not None else np.ascontiguousarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be a numeric array of shape (N, {ncol}): {e}") from e
    if arr.ndim == 1 and arr.shape[0] == ncol:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != ncol:
        raise ParamError(f"{name} must have shape (N, {ncol}), got {arr.shape}")
    if mask is not None and np.any(mask):
        arr[mask.reshape(arr.shape).any(axis=1)] = np.nan
    return arr


def no_infinite_rows(name: str, arr: np.ndarray) -> None:
    """ParamError naming ``name`` and the first row holding +-inf (NaN rows are missing rows)."""
    bad = np.isinf(arr).any(axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ParamError(f"{name} row {i} is not finite: {arr[i].tolist()}")


def as_crs(value: Any, name: str = "crs") -> CRS:
    """A pyproj CRS from anything pyproj accepts, or CrsError naming ``name``."""
    if value is None:
        raise CrsError(f"{name} is required")
    try:
        return CRS.from_user_input(value)
    except CRSError as e:
        raise CrsError(f"{name}: unknown coordinate reference system {value!r}: {e}") from e


def integer(name: str, value: Any, *, low: int | None = None, high: int | None = None,
            none: bool = False) -> int | None:
    """``int(value)`` for an integer (an integral float such as 512.0 too) within [low, high],
    or ParamError naming ``name``; None passes through where ``none``."""
    import numbers

    if value is None and none:
        return None
    ok = not isinstance(value, (bool, np.bool_)) and isinstance(value, numbers.Real)
    if ok and not isinstance(value, numbers.Integral):
        ok = math.isfinite(float(value)) and float(value).is_integer()
    if ok:
        n = int(value)
        ok = (low is None or n >= low) and (high is None or n <= high)
    if not ok:
        span = (f" {low}-{high}" if high is not None else f" >= {low}") if low is not None else \
            (f" <= {high}" if high is not None else "")
        raise ParamError(f"{name} must be an integer{span}, got {value!r}")
    return n


def positive(name: str, value: Any, *, zero: bool = False, none: bool = False) -> float | None:
    """A finite number > 0 (>= 0 where ``zero``) as a float, or ParamError naming ``name``;
    None passes through where ``none``. Booleans and strings are refused, not converted."""
    import numbers

    if value is None and none:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ParamError(f"{name} must be a number, got {value!r}")
    v = finite(name, value)
    if v < 0 or (v == 0 and not zero):
        raise ParamError(f"{name} must be {'>= 0' if zero else '> 0'}, got {value!r}")
    return v


def flag(name: str, value: Any) -> bool:
    """``bool(value)`` for True or False (NumPy's too), or ParamError naming ``name``: 0, 1 and
    strings such as "no" are refused, not converted."""
    if not isinstance(value, (bool, np.bool_)):
        raise ParamError(f"{name} must be True or False, got {value!r}")
    return bool(value)
