"""The forward method's maps ([P3]'s direct method): source pixels geolocated, then inverted
quad by quad into source coordinates per output pixel.

Once per image, :func:`forward_coords` geolocates a coarse grid of source pixels and maps them
to output pixels, keeping them in blocks (:class:`_NodeBlocks`); per output tile it then finds
the source window whose nodes land near the tile, geolocates every pixel of it on the device
(:func:`~orthowarp.kernels.ortho.forward_nodes_kernel`) and scatters the quads into the tile's
source coordinates (:func:`~orthowarp.kernels.ortho.forward_scatter_kernel`); ground hidden from
the camera stays without coordinates. The resampling is the backward method's
(:class:`~orthowarp.pipeline.ortho.tiles.ImageTiles`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from pyproj import CRS

from ..._device import upload
from ...kernels import ortho as ortho_kernels
from ..transforms import is_identity, transformer

if TYPE_CHECKING:
    from affine import Affine

    from ..geometry import SensorGeometry
    from ..reports.profile import StageTimer
    from ..tiles import Tile

__all__ = ["forward_coords"]


class _NodeBlocks:
    """Bounds of the nodes of a grid that fall in a box, found by blocks.

    ``fields``: per node its position (x, y) and m more values, NaN where the node has none,
    as an array (rows, cols, 2 + m) or as 2 + m arrays (rows, cols), one per value. The grid is
    cut into ``block`` x ``block`` node blocks with the bounding box of their positions and
    the range of their values (float64): a query tests the blocks, takes whole the ones inside
    the box and tests node by node only those across its edge. Each node is kept as its offset
    from its block's lower bounds in float32 (half the grid in float64: an image's forward map
    is held while its tiles run), so a node's values come back within 2**-24 of its block's
    spread (a block of the forward map spans about 128 output pixels, so within 1e-5 px;
    values that are multiples of 0.5 below 2**23 of the lower bound, such as source pixel
    centres, exactly). Built one value at a time, each in its blocks' order (a block's nodes
    contiguous), whose bounds are then reductions along contiguous memory.
    """

    def __init__(self, fields: np.ndarray | Sequence[np.ndarray], block: int = 8) -> None:
        values = [fields[..., c] for c in range(fields.shape[-1])] if isinstance(fields, np.ndarray) else list(fields)
        rows, cols = values[0].shape
        self.block = block
        nb_r, nb_c = -(-rows // block), -(-cols // block)
        n, m = nb_r * nb_c, len(values)
        self.lo, self.hi = np.empty((n, m)), np.empty((n, m))
        self.offsets = np.empty((m, n, block * block), np.float32)  # (each value's contiguous)
        pad = np.full((nb_r * block, nb_c * block), np.nan)
        blocks = np.empty((nb_r, nb_c, block, block))
        flat = blocks.reshape(n, block * block)
        for c, v in enumerate(values):
            pad[:rows, :cols] = v
            blocks[...] = pad.reshape(nb_r, block, nb_c, block).transpose(0, 2, 1, 3)
            # (fmin / fmax skip NaN, as nanmin / nanmax do; a block with no node: NaN bounds,
            # never selected)
            lo = self.lo[:, c] = np.fmin.reduce(flat, axis=1)
            self.hi[:, c] = np.fmax.reduce(flat, axis=1)
            # (the difference in float64, rounded to float32 as astype rounds)
            np.subtract(flat, lo[:, None], out=self.offsets[c], casting="same_kind")

    def bounds(self, x0: float, y0: float, x1: float, y1: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(lo, hi): the smallest and largest values (m each) of the nodes with x0 <= x <= x1
        and y0 <= y <= y1, or None where there is none."""
        lo, hi = self.lo, self.hi
        meets = (hi[:, 0] >= x0) & (lo[:, 0] <= x1) & (hi[:, 1] >= y0) & (lo[:, 1] <= y1)
        inside = meets & (lo[:, 0] >= x0) & (hi[:, 0] <= x1) & (lo[:, 1] >= y0) & (hi[:, 1] <= y1)
        parts_lo, parts_hi = [lo[inside, 2:]], [hi[inside, 2:]]
        across = meets & ~inside
        if across.any():
            edge = (lo[across][:, None, :] + self.offsets[:, across].transpose(1, 2, 0)).reshape(-1, lo.shape[1])
            sel = (edge[:, 0] >= x0) & (edge[:, 0] <= x1) & (edge[:, 1] >= y0) & (edge[:, 1] <= y1)
            parts_lo.append(edge[sel, 2:])
            parts_hi.append(edge[sel, 2:])
        lo_all, hi_all = np.concatenate(parts_lo), np.concatenate(parts_hi)
        if not len(lo_all):
            return None
        return lo_all.min(axis=0), hi_all.max(axis=0)


def forward_coords(geom: SensorGeometry, transform: Affine, out_crs: CRS, frame_crs: CRS, device: wp.context.Device,
                   timer: StageTimer, radius: int, step: int = 16,
                   margin: int = 32) -> Callable[[int, int, int, int], tuple[wp.array, tuple | None]]:
    """The forward method's per-tile source coordinates (see
    :func:`~orthowarp.pipeline.ortho.orthorectify`'s ``method``).

    Once per image, a coarse grid of source pixels (every ``step``) is geolocated and mapped to
    output pixels; a tile's source window is then the bounding box of the coarse nodes that
    land within ``margin`` output pixels of it, grown by ``step + margin`` source pixels.

    Parameters
    ----------
    geom : SensorGeometry
        A frame image's geometry.
    transform : affine.Affine
        The output grid's.
    out_crs, frame_crs : pyproj.CRS
        The output CRS and the poses' horizontal CRS.
    device : warp.context.Device
    timer : StageTimer
        Gets the tiles' ``prepare``, ``h2d`` and ``kernel`` spans (unless a call gives its own).
    radius : int
        The resampling's reach (source pixels) beyond a coordinate.
    step : int, optional
        Source pixels between the coarse grid's nodes.
    margin : int, optional
        Output pixels around a tile whose nodes count.

    Returns
    -------
    callable
        ``coords_for(tile, timer=timer)`` (a :class:`~orthowarp.pipeline.tiles.Tile`) -> (source (col, row)
        per tile pixel: a warp array (th, tw) of vec2d, NaN where none; the source window (col0, row0, col1, row1, read
        reduction factor), or None where the tile sees nothing of the image).
    """
    w_img, h_img = geom.image_size
    arg, refr, dem, search = geom.structs()
    sc = np.unique(np.append(np.arange(0, w_img, step), w_img - 1)) + 0.5
    sr = np.unique(np.append(np.arange(0, h_img, step), h_img - 1)) + 0.5
    cc, rr = np.meshgrid(sc, sr)
    g = geom.geolocate_frame(np.stack([cc.ravel(), rr.ravel()], 1))
    ok = np.isfinite(g[:, 0]) & np.isfinite(g[:, 1]) & np.isfinite(g[:, 2])
    all_ok = bool(ok.all())
    to_out = transformer(frame_crs, out_crs)
    same = is_identity(to_out)  # (the poses' CRS the output's: no transformation)
    x, y = (g[ok, 0], g[ok, 1]) if same else to_out.transform(g[ok, 0], g[ok, 1])
    oc, orow = ~transform @ (np.asarray(x), np.asarray(y))
    # output pixels per source pixel, for rejecting quads that span occlusions
    scale = float(np.median(np.hypot(np.diff(oc), np.diff(orow)))) / step if len(oc) > 1 else 1.0
    max_edge = 4.0 * max(scale, 1.0)
    factor = max(int(np.floor(1.0 / scale)), 1) if scale > 0 else 1  # reduced reads: see tiles._rows_decimation

    def on_grid(v: np.ndarray, of_ok: bool) -> np.ndarray:
        """Values of the geolocated nodes (``of_ok``) or of all nodes on the node grid, NaN
        where a node was not geolocated."""
        if all_ok:
            return v.reshape(cc.shape)
        if of_ok:
            out = np.full(ok.size, np.nan)
            out[ok] = v
            return out.reshape(cc.shape)
        return np.where(ok, v, np.nan).reshape(cc.shape)

    # per node: output column and row, source column and row, frame u and v
    node_blocks = _NodeBlocks([on_grid(oc, True), on_grid(orow, True), on_grid(cc.ravel(), False),
                               on_grid(rr.ravel(), False), on_grid(g[:, 0], False), on_grid(g[:, 1], False)])

    def coords_for(tile: Tile, timer: StageTimer = timer) -> tuple[wp.array, tuple | None]:
        t = time.perf_counter()
        r0, c0, th, tw = tile
        coords = wp.full((th, tw), wp.vec2d(np.nan, np.nan), dtype=wp.vec2d, device=device)
        # the nodes within margin of the tile: bounds of their source and frame coordinates
        bounds = node_blocks.bounds(c0 - margin, r0 - margin, c0 + tw + margin, r0 + th + margin)
        if bounds is None:
            timer.span("prepare", t)
            return coords, None
        lo, hi = bounds
        grow = step + margin
        wc0 = max(int(lo[0]) - grow, 0)
        wr0 = max(int(lo[1]) - grow, 0)
        wc1 = min(int(hi[0]) + grow, w_img)
        wr1 = min(int(hi[1]) + grow, h_img)
        # frame -> output-tile pixel lookup grid over the selected ground
        lo, hi = lo[2:], hi[2:]
        pad = 0.25 * (hi - lo) + 1e-6
        gu = np.linspace(lo[0] - pad[0], hi[0] + pad[0], 33)
        gv = np.linspace(lo[1] - pad[1], hi[1] + pad[1], 33)
        uu, vv = np.meshgrid(gu, gv)
        x, y = (uu, vv) if same else to_out.transform(uu, vv)
        pc, pr = ~transform @ (np.asarray(x), np.asarray(y))
        timer.span("prepare", t)
        t = time.perf_counter()
        f2o = ortho_kernels.FrameToOutput()
        f2o.grid = upload(np.stack([pc - c0, pr - r0], -1), dtype=wp.vec2d, device=device)
        f2o.x0, f2o.dx, f2o.y0, f2o.dy = float(gu[0]), float(gu[1] - gu[0]), float(gv[0]), float(gv[1] - gv[0])
        nodes = wp.empty((wr1 - wr0, wc1 - wc0), dtype=wp.vec2d, device=device)
        timer.span("h2d", t)
        t = time.perf_counter()
        wp.launch(ortho_kernels.forward_nodes_kernel, dim=nodes.shape, device=device,
                  inputs=[arg, refr, dem, search, f2o, wp.int32(wc0), wp.int32(wr0), nodes])
        wp.launch(ortho_kernels.forward_scatter_kernel, dim=(nodes.shape[0] - 1, nodes.shape[1] - 1), device=device,
                  inputs=[nodes, wc0, wr0, max_edge, coords])
        timer.span("kernel", t)
        # the resampling window must hold the kernel's support around every coordinate
        reach = (radius + 1) * factor
        return coords, (max(wc0 - reach, 0), max(wr0 - reach, 0), min(wc1 + reach, w_img), min(wr1 + reach, h_img),
                        factor)

    return coords_for
