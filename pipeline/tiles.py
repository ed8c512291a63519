"""A tile of an output grid (:class:`Tile`): the box of whole pixels that an ortho, a mosaic or an
accuracy raster computes at once.

It lives among the flat modules of :mod:`orthowarp.pipeline` because all of ``ortho``,
``mosaic`` and :mod:`~orthowarp.pipeline.precision` pass tiles around (``precision`` must not
import ``ortho``); it imports nothing of the package.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["Tile"]


class Tile(NamedTuple):
    """A box of an output grid in whole pixels: its first ``row`` and ``col`` and its
    ``height`` and ``width``. A tuple ``(row, col, height, width)``: it unpacks, compares and
    pickles as one (the form that public calls such as ``MosaicPlan.tile(*tile)`` take).
    """

    row: int
    col: int
    height: int
    width: int

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width): the shape of the tile's arrays."""
        return self.height, self.width

    @property
    def slices(self) -> tuple[slice, slice]:
        """(rows, cols) slices of the tile in an array of the whole grid."""
        return slice(self.row, self.row + self.height), slice(self.col, self.col + self.width)

    def grown(self, margin: int) -> Tile:
        """This tile with ``margin`` pixels more on every side (a halo)."""
        return Tile(self.row - margin, self.col - margin, self.height + 2 * margin, self.width + 2 * margin)

    def within(self, outer: Tile) -> tuple[slice, slice]:
        """(rows, cols) slices of this tile in an array of the tile ``outer``."""
        r, c = self.row - outer.row, self.col - outer.col
        return slice(r, r + self.height), slice(c, c + self.width)
