"""The parsing helpers the file readers share: bounded one-line reprs of file values, one style
of error naming the file, and the checked reads of text, JSON, YAML and CSV documents.

Every reader of this package reports a problem with a file's content as a
:class:`~orthowarp.errors.ParamError` made by :func:`fail`: one line, ``Could not parse
[kind ]'<path>': <what and where>``, the values in it shown by :func:`show` (bounded however
large or deeply nested they are). Messages never hold a line break, whatever the file holds.

- orientation files (:mod:`~orthowarp.pipeline.formats.cameras`,
  :mod:`~orthowarp.pipeline.formats.exterior`): :func:`check_exists`, :func:`read_text`,
  :func:`load_structured` (JSON or YAML), the lenient :func:`number` and :func:`numbers` (YAML
  gives numbers as strings too) raising ValueError for the caller to name the file and item;
- JSON documents (:mod:`~orthowarp.pipeline.formats.block`,
  :mod:`~orthowarp.pipeline.formats.scene_points`, scene JSON in
  :mod:`~orthowarp.pipeline.formats.dimap`): :func:`read_utf8`, :func:`load_json` (duplicate keys
  refused) and the strict JSON-type checks :func:`obj`, :func:`jlist`, :func:`num`,
  :func:`nums`, :func:`ident`, raising :func:`fail`'s error;
- CSV imports: :func:`csv_records` with :func:`csv_id` and :func:`csv_num`.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import reprlib
import unicodedata
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar

from ...errors import ParamError, RasterIOError

__all__ = ["one_line", "show", "quote", "names", "fail", "got", "check_exists", "read_text", "looks_like_json",
           "yaml", "load_structured", "number", "numbers", "identifier", "osfm_camera_id", "read_utf8",
           "load_json", "obj", "jlist", "num", "nums", "ident", "has_control", "first_duplicate", "csv_records",
           "csv_id", "csv_num"]

T = TypeVar("T")

_SHOW = reprlib.Repr()
_SHOW.maxlevel, _SHOW.maxstring, _SHOW.maxother, _SHOW.maxlong = 2, 60, 60, 40
_SHOW.maxlist = _SHOW.maxtuple = _SHOW.maxdict = _SHOW.maxset = 4


# -- messages ---------------------------------------------------------------------------------------

def one_line(text: object, limit: int | None = 300) -> str:
    """``text`` (any object, as ``str``) on one line: every run of white space (line breaks
    included) one space, cut to ``limit`` characters with "..." (None: no limit)."""
    text = " ".join(str(text).split())
    return text if limit is None or len(text) <= limit else text[:limit] + "..."


def show(value: object) -> str:
    """A short, one-line repr of a file value, bounded however large or deep the value is
    (strings and numbers cut to about 60 characters, containers to 4 items and 2 levels);
    never fails."""
    try:
        return one_line(_SHOW.repr(value))
    except Exception:  # noqa: BLE001 - a message must never fail
        return f"<{type(value).__name__}>"


def quote(name: object) -> str:
    """A camera id or image name quoted for a message: as it is when short and printable, else
    its repr, shortened (ids may hold line breaks or run to megabytes)."""
    name = str(name)
    return f"'{name}'" if len(name) <= 80 and name.isprintable() else show(name)


def names(items: Sequence[object], limit: int = 8) -> str:
    """The first ``limit`` of ``items``, each :func:`quote`\\ d, comma-separated, with the count
    where there are more."""
    quoted = [quote(n) for n in items]
    return ", ".join(quoted[:limit]) + (f", ... ({len(quoted)} in all)" if len(quoted) > limit else "")


def fail(path: str | os.PathLike, msg: object, cause: BaseException | None = None, *, kind: str = "") -> ParamError:
    """The error of a file whose content cannot be used: ``Could not parse [kind ]'<path>':
    <msg>``, ``msg`` on one line (:func:`one_line`, uncut).

    Parameters
    ----------
    path : str or os.PathLike
        The file (or, for a block assembled from several, their names), as the caller names it.
    msg : str
        What is wrong, and where (line, item).
    cause : BaseException, optional
        Set as the error's ``__cause__``.
    kind : str, optional
        The kind of file, with a trailing space ("DIMAP file ", "block file ").

    Returns
    -------
    ParamError
        To be raised by the caller.
    """
    err = ParamError(f"Could not parse {kind}'{os.fspath(path)}': {one_line(msg, None)}")
    if cause is not None:
        err.__cause__ = cause
    return err


def got(value: object) -> str:
    """'got ...' for messages: the JSON type and a short repr of a value."""
    if value is None:
        return "got null"
    if isinstance(value, bool):
        return f"got the boolean {str(value).lower()}"
    kind = {dict: "an object", list: "a list", str: "a string", int: "the number", float: "the number"}.get(
        type(value), type(value).__name__)
    return f"got {kind} {show(value)}"


# -- orientation files: text, JSON or YAML, lenient numbers ----------------------------------------

def check_exists(path: str | os.PathLike) -> Path:
    """``path`` as a Path; ParamError where it does not exist or is not a file."""
    path = Path(os.fspath(path))
    if not path.exists():
        raise ParamError(f"'{path}' does not exist")
    if not path.is_file():
        raise ParamError(f"'{path}' is not a file")
    return path


def read_text(path: Path) -> str:
    """The UTF-8 text of an orientation file (a byte-order mark allowed); ParamError where it
    cannot be read or decoded."""
    try:
        return path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise ParamError(f"Could not read '{path}': {e}") from e


def looks_like_json(path: Path, text: str) -> bool:
    """Whether a document is JSON (by its suffix or its first character) rather than YAML or CSV."""
    return path.suffix.lower() in (".json", ".geojson") or text.lstrip()[:1] in ("{", "[")


def yaml() -> ModuleType:
    """PyYAML, imported on first use (JSON-only jobs, e.g. ODM datasets, never load it)."""
    import yaml as module

    return module


def load_structured(path: Path, text: str) -> Any:
    """Parse a JSON or YAML document (:func:`looks_like_json` decides); :func:`fail`'s error
    naming the file and the line."""
    if looks_like_json(path, text):
        try:
            return json.loads(text)
        except json.JSONDecodeError as e:
            raise fail(path, f"invalid JSON at line {e.lineno}, column {e.colno}: {one_line(e.msg)}", e) from e
        except RecursionError as e:
            raise fail(path, "invalid JSON: nested too deeply", e) from None
        except ValueError as e:  # e.g. an integer of more than 4300 digits
            raise fail(path, f"invalid JSON: {one_line(e)}", e) from e
    module = yaml()
    try:
        # PyYAML's pure-Python safe loader: libyaml's (CSafeLoader) is faster but overflows the C
        # stack (a crash, not an exception) on a document nested 100 000 deep
        return module.load(text, Loader=module.SafeLoader)  # noqa: S506 - a safe loader
    except module.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        raise fail(path, f"invalid YAML{where}: {one_line(problem)}", e) from e
    except RecursionError as e:
        raise fail(path, "invalid YAML: nested too deeply", e) from None
    except Exception as e:  # noqa: BLE001 - a value PyYAML resolves but cannot build: 2001-02-30 (ValueError),
        # !!bool maybe (KeyError), ...: whatever the constructor raises, the document is unreadable
        raise fail(path, f"invalid YAML: {type(e).__name__}: {one_line(e)}", e) from e


def number(value: object, what: str) -> float:
    """A finite float from a file value (numbers, or strings such as PyYAML's '1.2e2');
    ValueError naming ``what`` else."""
    if not isinstance(value, (int, float, str)) or isinstance(value, bool):
        raise ValueError(f"{what} must be a number, got {show(value)}")
    try:
        v = float(value)
    except ValueError:
        raise ValueError(f"{what} must be a number, got {show(value)}") from None
    except OverflowError:  # an integer beyond the float range
        raise ValueError(f"{what} must be finite, got {show(value)}") from None
    if not math.isfinite(v):
        raise ValueError(f"{what} must be finite, got {show(value)}")
    return v


def numbers(value: object, n: int, what: str) -> list[float]:
    """``n`` finite floats (:func:`number`) from a file's list; ValueError naming ``what`` else."""
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ValueError(f"{what} must be a list of {n} numbers, got {show(value)}")
    return [number(v, f"{what}[{i}]") for i, v in enumerate(value)]


def identifier(value: object, what: str) -> str:
    """A camera id or image name from a file: a non-empty string (numbers are taken as text);
    ValueError naming ``what`` else."""
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ValueError(f"{what} must be a string, got {show(value)}")
    text = str(value)
    if not text.strip():
        raise ValueError(f"{what} is empty")
    return text


def osfm_camera_id(cam_id: T) -> T:
    """OpenSfM/ODM camera ids carry a 'v2 ' version prefix that other files omit: drop it
    (other values are returned as they are, for the caller to check)."""
    return cam_id[3:] if isinstance(cam_id, str) and cam_id.startswith("v2 ") else cam_id


# -- JSON documents: strict JSON types --------------------------------------------------------------

class _Duplicate(Exception):
    pass


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    out = {}
    for k, v in pairs:
        if k in out:
            raise _Duplicate(k)
        out[k] = v
    return out


def read_utf8(path: str, what: str) -> str:
    """The text of the UTF-8 file ``path`` (a byte-order mark allowed); ``what`` names it in
    messages ("block file ", or "").

    Raises
    ------
    RasterIOError
        The file cannot be read.
    ParamError
        It is not UTF-8 text.
    """
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise RasterIOError(f"Cannot read {what}'{path}': {e.strerror or e}") from e
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise fail(path, f"not UTF-8 text ({e.reason} at byte {e.start})", e, kind=what) from e


def read_small_text(path: str | os.PathLike, limit: int, *, kind: str = "", noun: str = "this file") -> str:
    """The text of a small UTF-8 text file (an RPC or GCP file): it must exist (:func:`check_exists`),
    hold at most ``limit`` bytes (``noun`` names what it is in that message: "a GCP list"), be UTF-8
    (:func:`read_utf8`; ``kind`` as there) and hold no NUL.

    Raises
    ------
    RasterIOError
        The file cannot be read.
    ParamError
        It does not exist, is too large, or is not UTF-8 text.
    """
    p = check_exists(path)
    name = os.fspath(path)
    try:
        size = p.stat().st_size
    except OSError as e:
        raise RasterIOError(f"Cannot read {kind}'{name}': {e.strerror or e}") from e
    if size > limit:
        raise fail(name, f"{size} bytes is too large for {noun} (at most {limit})", kind=kind)
    text = read_utf8(name, kind)
    if "\x00" in text:
        raise fail(name, "not a text file (it holds NUL characters)", kind=kind)
    return text


def load_json(path: str, what: str = "block file ") -> Any:
    """The parsed JSON document of ``path`` (duplicate keys refused); ``what`` names the kind
    of file in messages (:func:`read_utf8`'s errors, and :func:`fail`'s)."""
    text = read_utf8(path, what)
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as e:
        raise fail(path, e, kind=what) from e
    except _Duplicate as e:
        raise fail(path, f"key {show(e.args[0])} appears twice in one object", kind=what) from None
    except RecursionError:
        raise fail(path, "nested too deeply", kind=what) from None
    except ValueError as e:  # e.g. integers beyond Python's digit limit
        raise fail(path, e, kind=what) from e


def obj(path: str, value: object, what: str) -> dict:
    """``value`` if it is a JSON object; :func:`fail`'s error naming ``what`` else."""
    if not isinstance(value, dict):
        raise fail(path, f"{what} must be a JSON object, {got(value)}")
    return value


def jlist(path: str, value: object, what: str) -> list:
    """``value`` if it is a JSON list; :func:`fail`'s error naming ``what`` else."""
    if not isinstance(value, list):
        raise fail(path, f"{what} must be a list, {got(value)}")
    return value


def num(path: str, value: object, what: str) -> float:
    """A finite float from a JSON number (not a string, a boolean or null)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise fail(path, f"{what} must be a number, {got(value)}")
    try:
        v = float(value)
    except OverflowError:
        raise fail(path, f"{what} is too large for a float ({len(str(abs(value)))} digits)") from None
    if not math.isfinite(v):
        raise fail(path, f"{what} must be a finite number, got {show(value)}")
    return v


def nums(path: str, value: object, n: int, what: str) -> list[float]:
    """``n`` finite floats (:func:`num`) from a JSON list."""
    if not isinstance(value, list) or len(value) != n:
        raise fail(path, f"{what} must be a list of {n} numbers, {got(value)}")
    return [num(path, v, f"{what}[{i}]") for i, v in enumerate(value)]


def ident(path: str, value: object, what: str) -> str:
    """An id: a non-empty string (or an integer, kept as its decimal string) without control
    characters."""
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise fail(path, f"{what} must be a string, {got(value)}")
    v = str(value)
    if not v.strip():
        raise fail(path, f"{what} is empty")
    if has_control(v):
        raise fail(path, f"{what} {show(v)} holds control characters (line breaks, tabs, NUL...)")
    return v


def has_control(text: str) -> bool:
    """Whether ``text`` holds a control character (Unicode category Cc: line breaks, tabs, NUL...)."""
    return any(unicodedata.category(c) == "Cc" for c in text)


def first_duplicate(ids: Sequence[T]) -> T | None:
    """The first item of ``ids`` that appeared before it, or None."""
    seen = set()
    for i in ids:
        if i in seen:
            return i
        seen.add(i)
    return None


# -- CSV imports ------------------------------------------------------------------------------------

def _csv_rows(path: str) -> tuple[list[str], list[list[str]]]:
    """(header in lower case, data rows) of a CSV file, blank rows dropped."""
    text = read_utf8(path, "")
    if "\0" in text:
        raise fail(path, "holds NUL bytes: not a text CSV file")
    try:
        rows = [r for r in csv.reader(io.StringIO(text, newline="")) if r and any(c.strip() for c in r)]
    except csv.Error as e:
        raise fail(path, f"not a readable CSV file: {e}") from e
    if not rows:
        raise fail(path, "empty file")
    return [c.strip().lower() for c in rows[0]], rows[1:]


def csv_records(path: str | os.PathLike, need: Sequence[str], optional: Sequence[str],
                make: Callable[[dict[str, str], str], T]) -> list[T]:
    """``make(cells by column name, what)`` for every data row of a CSV whose header names
    ``need`` (and maybe ``optional``); other columns are refused. ``what`` is "line N"; a
    ValueError from ``make`` becomes :func:`fail`'s error."""
    path = os.fspath(path)
    head, rows = _csv_rows(path)
    if any(h not in head for h in need):
        raise fail(path, f"the header must name {', '.join(need)} (got {', '.join(map(show, head))})")
    dup = first_duplicate(head)
    if dup is not None:
        raise fail(path, f"the header names column {show(dup)} twice")
    unknown = [h for h in head if h not in need and h not in optional]
    if unknown:
        raise fail(path, f"unknown column(s) {', '.join(map(show, unknown))} (known: "
                         f"{', '.join([*need, *optional])})")
    out = []
    for n, r in enumerate(rows, start=2):
        if len(r) != len(head):
            raise fail(path, f"line {n}: {len(r)} fields, the header names {len(head)}")
        cells = {h: c.strip() for h, c in zip(head, r)}
        try:
            out.append(make(cells, f"line {n}"))
        except ValueError as e:
            raise fail(path, str(e)) from None
    return out


def csv_id(cells: dict[str, str], key: str, what: str) -> str:
    """The id in column ``key``: non-empty, without control characters; ValueError else."""
    v = cells[key]
    if not v:
        raise ValueError(f"{what}: {key} is empty")
    if has_control(v):
        raise ValueError(f"{what}: {key} {show(v)} holds control characters (line breaks, tabs, NUL...)")
    return v


def csv_num(cells: dict[str, str], key: str, what: str, *, low: float | None = None, high: float | None = None,
            positive: bool = False, nonneg: bool = False) -> float:
    """The finite number in column ``key``, within [``low``, ``high``] where given, > 0 with
    ``positive``, >= 0 with ``nonneg``; ValueError else."""
    text = cells[key]
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{what}: {key} {show(text)} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"{what}: {key} {show(text)} is not a finite number")
    if positive and not v > 0:
        raise ValueError(f"{what}: {key} must be > 0, got {show(text)}")
    if nonneg and v < 0:
        raise ValueError(f"{what}: {key} must be >= 0, got {show(text)}")
    if (low is not None and v < low) or (high is not None and v > high):
        raise ValueError(f"{what}: {key} = {v:g} is not plausible (expected {low:g} .. {high:g})")
    return v
