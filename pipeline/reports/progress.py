"""Progress of a long call, for the callers that ask for it: a tqdm bar or a callable.

The library reports progress only where a call is given ``progress`` (it never prints
otherwise): ``True`` draws a tqdm bar on stderr, a callable receives ``(done, total, rate)``
after each step.
"""

from __future__ import annotations

import time
from typing import Any

from ...errors import ParamError

__all__ = ["Progress"]


class Progress:
    """Items done / total and their rate, to a tqdm bar (``progress=True``) or a callable
    ``progress(done, total, rate)`` (rate: items per second since the start); nothing where
    ``progress`` is None or False.

    Parameters
    ----------
    progress : bool, callable or None
    total : int
        Items in all.
    done : int, optional
        Items already done (a restarted job's).
    desc, unit : str, optional
        The bar's label and its items' name.

    Raises
    ------
    ParamError
        ``progress`` is none of these.
    """

    def __init__(self, progress: Any, total: int, done: int = 0, desc: str = "tiles", unit: str = "tile") -> None:
        self.total, self.done, self.t0, self.bar, self.call = total, done, time.perf_counter(), None, None
        if progress is True:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, unit=unit, desc=desc, leave=False)
        elif callable(progress):
            self.call = progress
        elif progress not in (None, False):
            raise ParamError(f"progress must be True, False, None or a callable, got {progress!r}")

    def step(self, n: int = 1) -> None:
        """``n`` more items done."""
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
        if self.call is not None:
            dt = time.perf_counter() - self.t0
            self.call(self.done, self.total, self.done / dt if dt > 0 else 0.0)

    def close(self) -> None:
        """Close the bar (if any)."""
        if self.bar is not None:
            self.bar.close()
