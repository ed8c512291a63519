"""``orthowarp adjust``: bundle adjustment of a block of frame images."""

from __future__ import annotations

import os
from types import SimpleNamespace
from typing import Any

import click

from . import options


@click.command()
@click.argument("block_file", required=False, type=click.Path(dir_okay=False))
@options.out_dir(required=True, legacy_out=True,
                 what="Output folder: the refined orientation (exterior.csv, cameras.yaml, pose_cov.json), the "
                      "points and the reports.")
@click.option("--write-example", is_flag=True,
              help="First write a synthetic example block (3 strips of 8 images, control at the corners and "
                   "centre, 0.5 px image noise) to BLOCK_FILE, which must not exist, then adjust it.")
@click.option("--cameras", type=click.Path(dir_okay=False),
              help="Instead of BLOCK_FILE: cameras (orthority/ODM camera file) ...")
@click.option("--exterior", type=click.Path(dir_okay=False),
              help="... initial exterior orientation (CSV + .prj, GeoJSON, reconstruction.json) ...")
@click.option("--image-points", type=click.Path(dir_okay=False),
              help="... image points CSV (image,point,col,row[,sigma]) ...")
@click.option("--ground-points", type=click.Path(dir_okay=False),
              help="... and ground points CSV (point,x,y,z[,sx,sy,sz][,role]).")
@click.option("--fix-control", is_flag=True, help="Hold control points fixed instead of weighting them.")
@click.option("--no-gnss", is_flag=True, help="Ignore the images' GNSS positions.")
@click.option("--no-ins", is_flag=True, help="Ignore the images' INS attitudes.")
@click.option("--snooping", is_flag=True, help="Baarda data snooping with iterative rejection.")
@click.option("--robust", type=click.Choice(["huber"]), default=None, help="Robust loss.")
@click.option("--covariance", type=click.Choice(["auto", "full", "poses", "none"]), default="auto", show_default=True,
              help="Which covariances to compute: auto, the full matrix, the poses' blocks only, or none.")
@click.option("--self-calibration", "self_cal", default=None,
              help="Camera parameters to estimate: 'all' (f,x0,y0,k1,k2,p1,p2) or a comma list of "
                   "f,x0,y0,k1,k2,k3,p1,p2.")
@options.no_plots
@click.option("--drop-outside-observations", "drop_outside", is_flag=True,
              help="Drop image observations outside their image (logged) instead of refusing the block.")
@click.pass_context
def adjust(ctx: click.Context, block_file: str | None, out_dir: str, **kwargs: Any) -> None:
    """Bundle-adjust the block in BLOCK_FILE (JSON; or from --cameras, --exterior, --image-points
    and --ground-points) and write the refined orientation, points and reports into --out-dir. A
    run that does not converge, or ends singular, writes nothing and exits with status 1. Try it:
    orthowarp adjust block.json --write-example --out-dir adjusted"""
    import numpy as np

    from ..adjust import bundle_adjust
    from ..errors import Cancelled, GeometryError
    from ..pipeline.reports.adjust import write_adjustment

    o = SimpleNamespace(**kwargs)
    block, block_file = _block(block_file, o, quiet=ctx.obj["quiet"])
    calib = None if not o.self_cal else \
        (True if o.self_cal == "all" else tuple(x.strip() for x in o.self_cal.split(",")))
    result = bundle_adjust(block, fix_control=o.fix_control, use_gnss=not o.no_gnss, use_ins=not o.no_ins,
                           snooping=o.snooping, robust=o.robust, covariance=o.covariance, self_calibration=calib)
    if not result.success:
        raise GeometryError(f"adjustment of '{block_file}' failed (status {result.status}): {result.message}; "
                            f"nothing written to '{out_dir}'")
    if ctx.meta["orthowarp.stop"].is_set():  # stopped by a signal while adjusting: publish nothing
        raise Cancelled(f"adjustment of '{block_file}' cancelled; nothing written to '{out_dir}'")
    paths = write_adjustment(result, block, out_dir, plots=not o.no_plots)
    if not ctx.obj["quiet"]:
        check = (f"check RMSE (m) {np.array2string(result.check_rmse, precision=4)}"
                 if np.all(np.isfinite(result.check_rmse)) else "no check points")
        click.echo(f"{result.message}; sigma0 {result.sigma0:.4f}, redundancy {result.redundancy}; {check}; outputs: "
                   + ", ".join(os.path.basename(p) for p in paths.values()))


def _block(block_file: str | None, o: SimpleNamespace, *, quiet: bool) -> tuple[Any, str]:
    """(the block, its name in messages): from BLOCK_FILE (written first with
    --write-example), or from the four files."""
    from ..errors import ParamError
    from ..pipeline.formats.block import read_block

    parts = (o.cameras, o.exterior, o.image_points, o.ground_points)
    if any(parts):
        if block_file or o.write_example:
            raise ParamError("Give BLOCK_FILE or --cameras/--exterior/--image-points/--ground-points, not both")
        if not all(parts):
            raise ParamError("A block from files needs all of --cameras, --exterior, --image-points, --ground-points")
        from ..pipeline.formats.block import block_from_files

        return block_from_files(*parts, drop_outside=o.drop_outside), o.exterior
    if not block_file:
        raise ParamError("Give BLOCK_FILE (a block JSON; --write-example writes one) or the four CSV/orientation "
                         "files")
    if o.write_example:
        from ..adjust import synthetic_block
        from ..pipeline.formats.block import write_block
        from ..pipeline.raster.io import check_destination

        check_destination(block_file, overwrite=False)
        write_block(synthetic_block()[0], block_file)
        if not quiet:
            click.echo(f"wrote the example block {block_file}")
    return read_block(block_file, drop_outside=o.drop_outside), block_file
