"""``orthowarp match``: tie points between frame images by area-based matching, written as a
block for ``orthowarp adjust``."""

from __future__ import annotations

import os
from types import SimpleNamespace
from typing import Any

import click

from . import options
from .warm import warm_up


@click.command()
@click.argument("images", nargs=-1, type=click.Path(dir_okay=False))
@options.orientation
@options.crs
@options.terrain
@options.out_file("The block file to write (JSON, for 'orthowarp adjust').")
@click.option("--zones", default="4x3", show_default=True,
              help="Interest-point zones per image, across x down; each at least --window pixels each way.")
@click.option("--per-zone", type=click.IntRange(1, 100), default=2, show_default=True, help="Points per zone.")
@click.option("--window", type=int, default=21, show_default=True, help="Matching window side (px, odd).")
@click.option("--radius", type=click.IntRange(0, 256), default=8, show_default=True,
              help="NCC search radius (px) around the predicted position (at the top of the --pyramid): with it the "
                   "search reaches RADIUS x 2^PYRAMID pixels, which must cover the orientation's error.")
@click.option("--pyramid", type=click.IntRange(0, 6), default=0, show_default=True,
              help="Image-pyramid levels (2 x 2 means) above the full resolution for the NCC search.")
@click.option("--control", "control_csv", type=click.Path(dir_okay=False),
              help="Control points CSV (point,x,y,z[,sx,sy,sz]; in the poses' CRS, or latitude, longitude, height "
                   "for GNSS/INS poses). With --reference they are matched against its chips and added to the "
                   "block as control; without, their predicted image positions are written to "
                   "<OUT>_control.csv (image,point,col,row, the image-points CSV of 'orthowarp adjust') to confirm.")
@click.option("--reference", type=click.Path(dir_okay=False),
              help="Reference orthoimage for --control (its first band; any CRS: the points and chips are "
                   "carried into it).")
@click.option("--control-sigma", type=float, default=0.05, show_default=True,
              help="Sigma (m) of control points whose CSV row gives none.")
@click.option("--min-score", type=float, default=0.7, show_default=True, help="Smallest NCC accepted.")
@click.option("--gnss-sigma", type=float, default=None,
              help="Sigma (m) of the given projection centres as observations in the block (default: none).")
@click.option("--ins-sigma", type=float, default=None,
              help="Sigma (deg) of the given omega, phi, kappa (or roll, pitch, yaw) as observations in the block "
                   "(default: none).")
@options.no_refraction
@options.overwrite
@options.device
@click.pass_context
def match(ctx: click.Context, images: tuple[str, ...], **kwargs: Any) -> None:
    """Find tie points between frame IMAGES by area-based matching (interest points, NCC,
    least-squares matching, back-matching, a check across images), predicted through their
    approximate orientation (--ext-param) and the DEM, and write them as a block for
    'orthowarp adjust' (add control with --control and --reference, or to its 'points' before
    adjusting, or give --gnss-sigma/--ins-sigma). The first band of each image is matched; the
    poses are all omega-phi-kappa ones in one projected CRS, or all GNSS/INS ones without
    boresight and lever arm."""
    warm_up(kwargs["device"], more=("orthowarp.kernels.matching",))
    from ..errors import ParamError
    from ..pipeline.dem import Dem
    from ..pipeline.formats.block import write_block
    from ..pipeline.formats.sensors import expand_images, frame_sensors, image_key
    from ..pipeline.matching import match_block
    from ..pipeline.raster.io import check_destination

    o = SimpleNamespace(**kwargs)
    images = expand_images(images)
    if len(images) < 2 or not (o.int_param or o.ext_param) or (o.dem is None) == (o.height is None):
        raise ParamError("Give two or more IMAGES, --ext-param (and --int-param) and one of --dem or --height")
    zones = _zones(o.zones)
    check_destination(o.out_path, overwrite=o.overwrite)
    jobs = frame_sensors(images, o.int_param, o.ext_param, crs=o.crs)
    pixels = _first_bands(jobs, zones, o.window)
    terrain = Dem.from_file(o.dem) if o.dem is not None else o.height
    ids = [image_key(image) for image, _ in jobs]
    sensors = [sensor for _, sensor in jobs]
    block, stats = match_block(pixels, sensors, terrain, ids=ids, zones=zones, per_zone=o.per_zone, window=o.window,
                               radius=o.radius, levels=o.pyramid, min_score=o.min_score, gnss_sigma=o.gnss_sigma,
                               ins_sigma=o.ins_sigma, refraction=not o.no_refraction, device=o.device)
    if not block.n_points and stats.get("no_ground"):
        off = stats["no_ground"]
        raise ParamError(f"No tie point matched: {f'the DEM {o.dem!r}' if o.dem else f'--height {o.height:g}'} does "
                         f"not cover {'the images' if len(off) == len(ids) else 'image(s) ' + ', '.join(off)} (none "
                         f"of {'their' if len(off) > 1 else 'its'} interest points meets it): check the DEM and the "
                         "poses' CRS (--crs, .prj)")
    if not block.n_points:
        raise ParamError(f"No tie point matched between the {len(images)} images ({stats['interest']} interest "
                         "points): no texture, no overlap, or the orientation is further off than the search "
                         "reaches (--radius, --pyramid)")
    if o.control_csv is not None:
        block = _match_control(block, pixels, sensors, terrain, o.control_csv, o.reference, o.control_sigma,
                               o.out_path, overwrite=o.overwrite, quiet=ctx.obj["quiet"], window=o.window,
                               radius=o.radius, levels=o.pyramid, min_score=o.min_score,
                               refraction=not o.no_refraction, device=o.device)
    write_block(block, o.out_path)
    if not ctx.obj["quiet"]:
        pairs = ", ".join(f"{k} {v['accepted']}/{v['predicted']}" for k, v in stats["pairs"].items())
        click.echo(f"{o.out_path}: {stats['points']} tie points, {stats['observations']} observations "
                   f"({stats['interest']} interest points; matched/predicted per pair: {pairs})")


def _zones(text: str) -> tuple[int, int]:
    """``--zones COLSxROWS`` as (cols, rows) (ParamError if it is not that)."""
    from ..errors import ParamError

    try:
        zx, zy = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ParamError(f"--zones must be COLSxROWS such as 4x3, got {text!r}") from None
    if zx < 1 or zy < 1:
        raise ParamError(f"--zones must be COLSxROWS of at least 1x1, got {text!r}")
    return zx, zy


def _first_bands(jobs: list[tuple[str, Any]], zones: tuple[int, int], window: int) -> list[Any]:
    """The first band (float32) of each image, each checked to hold ``zones`` zones of at
    least ``window`` pixels."""
    import numpy as np
    import rasterio

    from ..adjust.matching import zones_allowed
    from ..errors import ParamError, RasterIOError

    zx, zy = zones
    pixels = []
    for image, _ in jobs:
        try:
            with rasterio.open(image) as ds:
                pixels.append(ds.read(1).astype(np.float32))
        except rasterio.errors.RasterioIOError as e:
            raise RasterIOError(f"Could not read image '{image}': {e}") from e
        rows, cols = pixels[-1].shape
        most = zones_allowed((rows, cols), window) if window > 0 else (zx, zy)
        if zx > most[0] or zy > most[1]:
            raise ParamError(f"--zones {zx}x{zy} is too fine for image '{image}' ({cols} x {rows} px): a zone must be "
                             f"at least the --window of {window} px each way, so at most {most[0]}x{most[1]} zones")
    return pixels


def _match_control(block: Any, pixels: list[Any], sensors: list[Any], terrain: Any, control_csv: str,
                   reference: str | None, sigma: float, out_path: str, *, overwrite: bool, quiet: bool,
                   **kw: Any) -> Any:
    """``orthowarp match --control``: the block with the control points matched against the
    reference's chips; without a reference the block as it is, and the points' predicted
    image positions written to <OUT>_control.csv."""
    import numpy as np

    from ..errors import ParamError
    from ..pipeline.formats.block import read_ground_points_csv
    from ..pipeline.matching import control_observations
    from ..pipeline.raster.io import check_destination, write_text

    gcps = read_ground_points_csv(control_csv, sigma=sigma)
    if not gcps:
        raise ParamError(f"Control points file '{control_csv}' holds no point")
    geo = block.mode == "geocentric"
    xyz = np.array([g["xyz"] for g in gcps], dtype=np.float64)  # the block's form: lat, lon, h if geocentric
    pts = xyz[:, [1, 0, 2]] if geo else xyz  # the sensors' frame: lon, lat, h or x, y, z
    ref = _reference(reference) if reference is not None else None
    obs = control_observations(pixels, sensors, terrain, pts, reference=ref, **kw)
    names = [g["id"] for g in gcps]
    if ref is None:
        dst = os.path.splitext(out_path)[0] + "_control.csv"
        check_destination(dst, overwrite=overwrite)
        rows = ["image,point,col,row"] + [f"{block.image_ids[i]},{names[p]},{c:.3f},{r:.3f}"
                                          for p, i, (c, r) in zip(obs.point, obs.image, obs.xy)]
        write_text(dst, "\n".join(rows) + "\n")
        if not quiet:
            click.echo(f"{dst}: predicted image positions of {len(set(obs.point.tolist()))} of {len(gcps)} control "
                       "points, to confirm (then 'orthowarp adjust --image-points')")
        return block
    seen = sorted(set(obs.point.tolist()))
    missed = [names[p] for p in range(len(gcps)) if p not in seen]
    if missed:
        click.echo(f"warning: control points not matched in any image: {', '.join(missed)}", err=True)
    index = {p: n for n, p in enumerate(seen)}
    sig = np.array([g.get("sigma", [sigma] * 3) for g in gcps], dtype=np.float64)
    out = block.with_points([names[p] for p in seen], ["control"] * len(seen), xyz[seen], sig[seen], obs.image,
                            [index[p] for p in obs.point], obs.xy, np.maximum(obs.sigma, 0.02))
    if not quiet:
        click.echo(f"control: {len(seen)} of {len(gcps)} points matched against '{reference}' "
                   f"({len(obs.point)} observations)")
    return out


def _reference(path: str) -> tuple[Any, Any, Any]:
    """(first band float32, transform, CRS) of the reference orthoimage of ``--control``."""
    import numpy as np
    import rasterio
    from pyproj import CRS

    from ..errors import ParamError, RasterIOError

    try:
        with rasterio.open(path) as ds:
            if ds.crs is None:
                raise ParamError(f"Reference '{path}' has no CRS")
            return ds.read(1).astype(np.float32), ds.transform, CRS.from_wkt(ds.crs.to_wkt())
    except rasterio.errors.RasterioIOError as e:
        raise RasterIOError(f"Could not read reference '{path}': {e}") from e
