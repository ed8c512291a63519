"""A mosaic tile from its images: distance ranks, feathering, multi-band blending, the
backward method's fill.

In a tile, each image's signed distance from its region of the seams' labelling (bilinear
between reduced pixels) ranks the images; with feathering, those within a band of the nearest
share a pixel, their weights falling linearly across the band, and an image's weight falls to
zero towards its border over the same width; with multi-band blending, fine detail comes from
each pixel's own image and coarser detail and brightness are blended over wider bands
(:func:`_multiband`). Ground an image does not see (the forward method's holes behind relief)
comes from the next image, and where none sees it by the forward method, from the backward
method on the blocks that need it (:func:`_fallback_blocks`). :class:`TileBlending` is the
tile function of :class:`~orthowarp.pipeline.mosaic.plan.MosaicPlan`.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from ..._device import to_host, upload
from ...kernels import mosaic as mosaic_kernels
from ..ortho.tiles import COARSE_STEP, TOP, WP_TYPES, coarse_grid, coarse_struct
from ..tiles import Tile
from .seams import NO_SOURCE

if TYPE_CHECKING:
    from collections.abc import Iterator

    from warp.context import Device

    from ..reports.profile import StageTimer

__all__ = ["TileBlending", "multiband_halo", "FALLBACK_BLOCK"]

FALLBACK_BLOCK = 256  # blocks of a tile that the backward method fills where the forward one has no value


class TileBlending:
    """The tile function of :class:`~orthowarp.pipeline.mosaic.plan.MosaicPlan`: a tile from the
    images that meet it, blended across the seams (see the module doc).

    A base of the plan, whose attributes it reads: ``options`` (``blend``, ``feather``,
    ``method``), ``count``, ``dtype``, ``sources``, ``transform``, ``labels`` and ``seam_step``
    (the seams' labelling), ``gains`` and ``offsets``, and the plan's image cache
    (``_images_meeting``, ``_image``, ``_materialise``).
    """

    def _tile(self, r0: int, c0: int, th: int, tw: int, device: Device | None = None) -> tuple:
        """:meth:`~orthowarp.pipeline.mosaic.plan.MosaicPlan.tile`'s arrays; with ``device``, warp arrays there (valid as uint8) from a
        tile computed on that device. (The four numbers, not a :class:`~orthowarp.pipeline.tiles.Tile`:
        the hook that worker processes call and tests override.)"""
        st = self._materialise()
        tile = Tile(r0, c0, th, tw)
        out, source, has = self._select(st, "renderer", tile, device=device)
        if self.options["method"] == "forward" and any(s[1].forward_method for s in self.sources):
            # ground no image sees by the forward method (hidden, where it drops folded quads on
            # a rough DSM, or the half pixel along a footprint's edge): the backward method's
            # value, from the same rule, on the blocks of the tile that have such pixels
            blocks = _fallback_blocks(has if device is not None else ~has, self.labels, self.seam_step, r0, c0)
            for block, (out2, source2, has2) in self._fallback_parts(st, blocks, device):
                if device is not None:
                    wp.launch(mosaic_kernels.mosaic_fill_kernel, dim=block.shape, device=device,
                              inputs=[out, has, source, out2, has2, source2, block.row - r0, block.col - c0])
                    continue
                sl = block.within(tile)
                fill = has2 & ~has[sl]
                out[sl][fill], source[sl][fill] = out2[fill], source2[fill]
                has[sl] |= fill
        return out, has, source

    def _fallback_parts(self, st: dict, blocks: list[Tile], device: Device | None) -> Iterator[tuple[Tile, tuple]]:
        """Each fallback block with its backward method's (values, source, has) as
        :meth:`_select` gives them: block by block, or where :func:`_fallback_in_one` says so,
        views of one computation of their bounding box."""
        if blocks and _fallback_in_one(device, self.options["blend"]):
            box = _bounding_tile(blocks)
            got = self._select(st, "fallback", box, device=device)
            for block in blocks:
                rows, cols = block.within(box)
                yield block, tuple(a[rows, cols] for a in got)
            return
        for block in blocks:
            yield block, self._select(st, "fallback", block, device=device)

    def _select(self, st: dict, which: str, tile: Tile, *, device: Device | None = None) -> tuple:
        """(values of the output dtype (th, tw, bands), source index (th, tw), has a value
        (th, tw)) of a ``tile`` from the images' ``which`` tile functions ("renderer" or
        "fallback"; see :func:`~orthowarp.pipeline.mosaic.mosaic`): host arrays (has: bool), or with ``device`` warp
        arrays there (has: uint8)."""
        o, timer = self.options, st["timer"]
        count, feather = self.count, o["feather"]
        top = TOP[self.dtype]
        th, tw = tile.shape
        if o["blend"] == "multiband":
            halo = multiband_halo(feather)
            got = self._stack(st, which, tile.grown(halo), fade=False)
        else:
            got = self._stack(st, which, tile, fade=o["blend"] == "feather")
        if got is None:
            out = np.full((th, tw, count), np.nan if top == 0.0 else 0, self.dtype)
            source, has = np.full((th, tw), NO_SOURCE, np.uint16), np.zeros((th, tw), bool)
            return (out, source, has) if device is None else _to_device(device, out, source, has)
        ks, stack, rank, on = got
        t = time.perf_counter()
        n = len(ks)
        out = wp.empty((th, tw, count), dtype=WP_TYPES[self.dtype], device=on)
        has = wp.empty((th, tw), dtype=wp.uint8, device=on)
        source = wp.empty((th, tw), dtype=wp.uint16, device=on)
        images = upload(ks, dtype=wp.int32, device=on)
        if o["blend"] == "multiband":
            planes, mid, low, best = _multiband(stack, rank, feather, halo, on)
            wp.launch(mosaic_kernels.multiband_combine_kernel, dim=(th, tw), device=on,
                      inputs=[planes, mid, low, best, images, halo, top, out, has, source])
        else:
            wp.launch(mosaic_kernels.mosaic_blend_kernel, dim=(th, tw), device=on,
                      inputs=[stack, rank, images, n, float(feather), int(o["blend"] == "none"), top, out, has,
                              source])
        timer.span("kernel", t)
        if device is not None:
            return out, source, has
        t = time.perf_counter()
        out, source, has = to_host(out), to_host(source), to_host(has).view(bool)
        timer.span("d2h", t)
        return out, source, has

    def _stack(self, st: dict, which: str, tile: Tile, *, fade: bool) -> tuple | None:
        """The images that have pixels in the ``tile`` (th, tw): their positions, their
        balanced values (device, (n, th, tw, bands) float32) and ranks (device, (n, th, tw)
        float32: signed distance from the image's region of the seam labelling, plus with
        ``fade`` the fade towards the image's border; +inf without a value), and the device;
        None where no image has pixels there."""
        o, timer = self.options, st["timer"]
        count, feather = self.count, o["feather"]
        (r0, c0), (th, tw) = tile[:2], tile.shape
        rendered = []  # (k, values, valid, the node pixels for the fade or None, image size)
        device = None
        grids = {}  # coarse grids by transformer: images in one pose frame share the tile's nodes
        for k in self._images_meeting(tile):
            with self._image(k) as entry:
                # (a pushbroom scene has no forward method: its backward tile function serves both)
                values, valid = entry.get(which, entry["renderer"]).render(*tile)
                if values is None:
                    continue
                device = values.device
                pixels = None
                if fade:  # towards the image's border, over the blend's width: its nodes' pixels
                    pixels = self._node_pixels(entry, grids, tile, device, timer)
                rendered.append((k, values, valid, pixels, entry["geom"].image_size))
        if not rendered:
            return None
        t = time.perf_counter()
        ks = [r[0] for r in rendered]
        (wr0, wc0), windows = _distance_windows(self.labels, self.seam_step, tile, ks,
                                                clip=2.0 * feather + 4.0 * self.seam_step)
        timer.span("prepare", t)
        t = time.perf_counter()
        gains, offsets = self._balance_on(st, device)
        n = len(rendered)
        stack = wp.empty((n, th, tw, count), dtype=wp.float32, device=device)
        rank = wp.empty((n, th, tw), dtype=wp.float32, device=device)
        win = mosaic_kernels.ReducedWindow()
        win.f, win.r0, win.c0, win.wr0, win.wc0 = float(self.seam_step), r0, c0, wr0, wc0
        win.rows, win.cols = self.labels.shape
        win.field = upload(np.stack([windows[k] for k in ks]), dtype=wp.float32, device=device)  # one copy for all
        edges = wp.zeros((n, 2, 2), dtype=wp.float32, device=device)
        if fade:  # the edge distances (output pixels) at the nodes
            edges = wp.empty((n, *rendered[0][3].shape), dtype=wp.float32, device=device)
            for slot, (_, _, _, pixels, (w_img, h_img)) in enumerate(rendered):
                wp.launch(mosaic_kernels.edge_nodes_kernel, dim=pixels.shape, device=device,
                          inputs=[pixels, float(w_img), float(h_img), float(COARSE_STEP), slot, edges])
        for slot, (k, values, valid, _, _) in enumerate(rendered):
            wp.launch(mosaic_kernels.mosaic_candidate_kernel, dim=(th, tw), device=device,
                      inputs=[values, valid, gains, offsets, k, win, edges, float(COARSE_STEP), int(fade),
                              float(feather), slot, stack, rank])
        timer.span("kernel", t)
        return ks, stack, rank, device

    def _node_pixels(self, entry: dict, grids: dict, tile: Tile, device: Device, timer: StageTimer) -> wp.array:
        """The source pixels (device, nodes (rows, cols) of vec2d) of the ground points at the
        tile's coarse-grid nodes (see :func:`~orthowarp.pipeline.ortho.tiles.coarse_grid`) on the DEM,
        from an image (``entry``); ``grids`` caches the nodes per transformer for the tile."""
        geom = entry["geom"]
        t = time.perf_counter()
        key = (id(entry["to_frame"]), geom.geocentric)
        grid = grids.get(key)
        if grid is None:
            uv = coarse_grid(self.transform, entry["to_frame"], *tile)
            timer.span("prepare", t)
            t = time.perf_counter()
            grid = grids[key] = coarse_struct(uv, geom.geocentric, device)
            timer.span("h2d", t)
            t = time.perf_counter()
        pixels = wp.empty(grid.uv.shape, dtype=wp.vec2d, device=device)
        wp.launch(mosaic_kernels.edge_node_pixels_kernel, dim=pixels.shape, device=device,
                  inputs=[*geom.sensor_structs(), geom.dem_struct(), grid, pixels])
        timer.span("kernel", t)
        return pixels

    def _balance_on(self, st: dict, device: Device) -> tuple[wp.array, wp.array]:
        """The gains and offsets (images, bands) as float32 arrays on ``device``, copied once
        per process."""
        key = ("balance", str(device))
        got = st.get(key)
        if got is None:
            got = st[key] = (wp.array(self.gains.astype(np.float32), device=device),
                             wp.array(self.offsets.astype(np.float32), device=device))
        return got


def multiband_halo(feather: float) -> int:
    """Pixels around a tile that multi-band blending reads: three of its widest Gaussian's
    sigma (``feather`` / 2), plus one."""
    return int(np.ceil(3.0 * 0.5 * feather)) + 1


def _gaussian_weights(sigma: float, truncate: float = 3.0) -> np.ndarray:
    """The normalised Gaussian of ``sigma`` pixels out to ``truncate`` sigmas (float32, odd
    length), as SciPy's ``gaussian_filter`` builds it."""
    radius = int(truncate * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * x * x / (sigma * sigma))
    return (w / w.sum()).astype(np.float32)


def _multiband(stack: wp.array, rank: wp.array, feather: float, halo: int,
               device: Device) -> tuple[wp.array, wp.array, wp.array, wp.array]:
    """Multi-band blending of a tile grown by ``halo`` pixels, on ``device`` (Burt and
    Adelson's multiresolution spline, ACM ToG 1983, in the three-band form of Brown and Lowe,
    IJCV 2007; kernels in :mod:`orthowarp.kernels.mosaic`).

    Each image's balanced values (``stack`` (n, rows, cols, bands)) are split into a high band
    (values minus their blur at sigma ``feather`` / 8), a middle band (that blur minus the blur
    at ``feather`` / 2) and a low band (the latter blur), each blur normalised by the image's
    valid pixels. Each pixel's image is the one of smallest rank (``rank`` (n, rows, cols),
    +inf without a value); its one-hot weights, blurred like the band (not at all for the high
    band) and kept where the image has a value, blend each band; the bands add up. Fine
    detail thus changes sharply at the seam and brightness over the blend's width. Blurs reach
    three sigma, inside the halo: the inner tile is the same whichever tile computes it.

    Returns
    -------
    planes, mid, low : warp arrays (n (bands + 2), rows, cols) float32
        The images' masked values, valid pixels and one-hot weights, and their two blurs.
    best : warp array (rows, cols) int32
        The image of smallest rank (-1 where none).
    """
    n, rows, cols, nb = stack.shape
    planes = wp.empty((n * (nb + 2), rows, cols), dtype=wp.float32, device=device)
    best = wp.empty((rows, cols), dtype=wp.int32, device=device)
    wp.launch(mosaic_kernels.multiband_planes_kernel, dim=(rows, cols), device=device, inputs=[stack, rank],
              outputs=[planes, best])
    tmp = wp.empty_like(planes)
    blurred = []
    for sigma in (feather / 8.0, feather / 2.0):
        weights = wp.array(_gaussian_weights(sigma), dtype=wp.float32, device=device)
        out = wp.empty_like(planes)
        wp.launch(mosaic_kernels.blur_axis_kernel, dim=planes.shape, device=device, inputs=[planes, weights, 1],
                  outputs=[tmp])
        wp.launch(mosaic_kernels.blur_axis_kernel, dim=planes.shape, device=device, inputs=[tmp, weights, 2],
                  outputs=[out])
        blurred.append(out)
    return planes, blurred[0], blurred[1], best


def _to_device(device: Device, out: np.ndarray, source: np.ndarray,
               has: np.ndarray) -> tuple[wp.array, wp.array, wp.array]:
    """Host tile arrays as warp arrays on ``device`` (has as uint8)."""
    return (wp.array(out, dtype=WP_TYPES[out.dtype.name], device=device), wp.array(source, dtype=wp.uint16, device=device),
            wp.array(has.view(np.uint8), dtype=wp.uint8, device=device))


def _fallback_blocks(missing: np.ndarray | wp.array, labels: np.ndarray, f: int, r0: int, c0: int,
                     block: int = FALLBACK_BLOCK) -> list[Tile]:
    """The parts of a tile (r0, c0) that the backward method must fill: the ``block`` x
    ``block`` pixel blocks (from the tile's first pixel) holding pixels without a value where
    the reduced labelling (``f`` output pixels per reduced pixel) has cover within one reduced
    pixel, each block row's consecutive blocks merged. ``missing``: bool (th, tw), True where
    a pixel has no value; or the tile's device validity (warp uint8 (th, tw), 1 where it has
    one), whose blocks are then marked on its device (a few bytes read back, not the tile).
    Returns a list of tiles of the mosaic grid."""
    th, tw = missing.shape
    if not isinstance(missing, wp.array) and not missing.any():
        return []
    rr, cc, cover = _grown_cover(labels, f, r0, c0, th, tw)
    nb_r, nb_c = -(-th // block), -(-tw // block)
    if isinstance(missing, wp.array):
        d = missing.device
        marked = wp.zeros((nb_r, nb_c), dtype=wp.int32, device=d)
        wp.launch(mosaic_kernels.fallback_need_kernel, dim=(th, tw), device=d,
                  inputs=[missing, upload(cover.view(np.uint8), dtype=wp.uint8, device=d),
                          upload(rr, dtype=wp.int32, device=d), upload(cc, dtype=wp.int32, device=d), block, marked])
        marked = to_host(marked) != 0
    else:
        need = missing & cover[np.ix_(rr, cc)]
        pad = np.zeros((nb_r * block, nb_c * block), bool)
        pad[:th, :tw] = need
        marked = pad.reshape(nb_r, block, nb_c, block).any(axis=(1, 3))
    out = []
    for i in range(nb_r):
        j = 0
        while j < nb_c:
            if not marked[i, j]:
                j += 1
                continue
            k = j
            while k < nb_c and marked[i, k]:
                k += 1
            br, bc = i * block, j * block
            out.append(Tile(r0 + br, c0 + bc, min(block, th - br), min(k * block, tw) - bc))
            j = k
    return out


def _grown_cover(labels: np.ndarray, f: int, r0: int, c0: int, th: int,
                 tw: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a tile (r0, c0, th, tw) has cover in the reduced labelling (``f`` output pixels
    per reduced pixel) grown by one reduced pixel: (window row of each tile row (th,), window
    column of each tile column (tw,), int32; cover on the window, bool)."""
    from scipy import ndimage

    crows, ccols = labels.shape
    rr = np.clip(np.arange(r0, r0 + th) // f, 0, crows - 1)
    cc = np.clip(np.arange(c0, c0 + tw) // f, 0, ccols - 1)
    i0, i1, j0, j1 = rr[0], rr[-1] + 1, cc[0], cc[-1] + 1
    # cover on the tile's reduced window, grown by one reduced pixel (its rim from the grid)
    win = labels[max(i0 - 1, 0):i1 + 1, max(j0 - 1, 0):j1 + 1] != NO_SOURCE
    grown = ndimage.binary_dilation(win, structure=np.ones((3, 3), bool))
    return (rr - max(i0 - 1, 0)).astype(np.int32), (cc - max(j0 - 1, 0)).astype(np.int32), grown


def _fallback_in_one(device: Device | None, blend: str) -> bool:
    """Whether a tile's fallback blocks are computed together, as their bounding box, and
    then copied block by block: on a GPU, where a block's set-up (per image a coarse grid, a
    source window and a read-back that waits for the device) costs more than its kernels.
    With feathering or no blending each pixel's value is a function of its position alone
    (coarse-grid nodes on the same lattice, distance fields exact to their clip), so the box
    gives the blocks' pixels; with multi-band blending, whose pyramids span the block, it
    would not. Not on the CPU, whose refraction turn is interpolated over each block's own
    height range (see :class:`~orthowarp.kernels.ortho.CoarseGrid`)."""
    return device is not None and device.is_cuda and blend != "multiband"


def _bounding_tile(tiles: list[Tile]) -> Tile:
    """The smallest tile holding all of ``tiles``."""
    r0, c0 = min(t.row for t in tiles), min(t.col for t in tiles)
    r1, c1 = max(t.row + t.height for t in tiles), max(t.col + t.width for t in tiles)
    return Tile(r0, c0, r1 - r0, c1 - c0)


def _distance_windows(labels: np.ndarray, f: int, tile: Tile, ks: list[int], clip: float) -> tuple[tuple[int, int], dict[int, np.ndarray]]:
    """Per image of ``ks``, the signed distance (output pixels, negative inside) from the
    image's region of the reduced labelling (``f`` output pixels per reduced pixel), on the
    window of the reduced grid that the ``tile`` needs for bilinear sampling
    (:class:`~orthowarp.kernels.mosaic.ReducedWindow`), exact up to ``clip`` and clipped
    there, so that it is the same whichever tile computes it. Beyond the grid, its edge
    repeated.

    Returns
    -------
    (wr0, wc0) : the window's first reduced row and column
    dict of int -> ndarray float32 (rows, cols)
    """
    from scipy import ndimage

    crows, ccols = labels.shape
    r0, c0, th, tw = tile
    margin = int(np.ceil(clip / f)) + 2
    wr0 = int(np.floor((r0 + 0.5) / f - 0.5)) - margin
    wc0 = int(np.floor((c0 + 0.5) / f - 0.5)) - margin
    wr1 = int(np.floor((r0 + th - 0.5) / f - 0.5)) + 2 + margin
    wc1 = int(np.floor((c0 + tw - 0.5) / f - 0.5)) + 2 + margin
    win = labels[np.ix_(np.clip(np.arange(wr0, wr1), 0, crows - 1), np.clip(np.arange(wc0, wc1), 0, ccols - 1))]
    out = {}
    for k in ks:
        inside = win == k
        if not inside.any() or inside.all():
            out[k] = np.full(win.shape, clip if not inside.any() else -clip, np.float32)
            continue
        sd = (ndimage.distance_transform_edt(~inside) - ndimage.distance_transform_edt(inside)) * f
        out[k] = np.clip(sd, -clip, clip).astype(np.float32)
    return (wr0, wc0), out
