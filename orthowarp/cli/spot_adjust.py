"""``orthowarp spot-adjust``: adjustment of pushbroom (SPOT-5 level 1A) scenes with ground
control, and its simulated example."""

from __future__ import annotations

import os
from types import SimpleNamespace
from typing import Any

import click

from . import options

EXAMPLE_SQUARE = 100  # px: the checkerboard squares of the example's synthetic images


@click.command("spot-adjust")
@click.option("--scene", "scenes", multiple=True, nargs=2, metavar="ID FILE",
              help="A scene: its id in the points file and its DIMAP metadata (or scene JSON). Two or more.")
@click.option("--points", "points_file", type=click.Path(dir_okay=False),
              help="Measured points: JSON (orthowarp-scene-points) or CSV "
                   "(id,role,x,y,z,sx,sy,sz,scene,col,row,sigma).")
@click.option("--points-crs", default="EPSG:4979", show_default=True, help="CRS of a CSV's x, y (z: ellipsoidal).")
@click.option("--pixel-sigma", type=float, default=0.3, show_default=True,
              help="Standard deviation of an image position (px) in CSV rows that give none.")
@click.option("--groups", default="attitude0,attitude1", show_default=True,
              help="EO coefficient groups freed per scene: position|velocity|attitude + 0|1|2 (constant, linear, "
                   "quadratic in line time), comma-separated; 'none' for none; 'look' estimates the look-angle "
                   "corrections in the same adjustment instead of a pre-adjustment (e.g. look,attitude1: their "
                   "uncertainty then enters the points' covariances).")
@click.option("--eo-sigma", default=None,
              help="Priors on the freed groups, e.g. 'position=10,attitude=5e-5' (m, m/s, rad); default: none.")
@click.option("--look-degree", type=click.IntRange(0, 4), default=2, show_default=True,
              help="Degree of the look-angle correction polynomials along the detector line.")
@click.option("--no-preadjust", is_flag=True, help="Skip the look-angle pre-adjustment.")
@click.option("--max-rounds", type=click.IntRange(1, 100), default=20, show_default=True,
              help="Rounds of the two steps: the pre-adjustment is redone with the bundle's attitude drifts (the "
                   "freed time-dependent groups), the bundle with the new look angles, until the points settle; 1 is "
                   "[P1]'s single pass, which keeps what the pre-adjustment absorbed of the exterior orientation's "
                   "errors.")
@options.attitude_model
@options.out_dir(required=True, legacy_out=True,
                 what="Output folder: the adjusted scenes (<id>_ADJUSTED.json), the points and the reports.")
@click.option("--write-example", type=click.Path(file_okay=False), default=None,
              help="First write a simulated SPOT-like stereo pair with attitude and look-angle errors into this "
                   "folder, which must not exist: two scene JSON files (left.json, right.json), a synthetic "
                   "checkerboard image of each scene's size to orthorectify (left.tif, right.tif) and 47 points, 20 "
                   "of them check points; then adjust it (--scene and --points are then not given).")
@options.no_plots
@click.pass_context
def spot_adjust(ctx: click.Context, **kwargs: Any) -> None:
    """Adjust pushbroom (SPOT-5 level 1A) scenes with ground control: the look angles first
    (EO fixed), then the chosen exterior-orientation groups of all scenes together, the two
    repeated until they settle (--max-rounds), with check points intersected from the adjusted
    scenes. Writes the adjusted scenes (for
    'orthowarp ortho --dimap'), the points and reports into --out-dir; a failed adjustment
    writes nothing and exits with status 1. Try it:
    orthowarp spot-adjust --write-example spot-example --out-dir spot-adjusted"""
    import numpy as np

    from ..adjust import adjust_scenes, preadjust_look_angles
    from ..errors import Cancelled, GeometryError
    from ..pipeline.reports.spot import write_scene_adjustment

    o = SimpleNamespace(**kwargs)
    models, points = _inputs(o, quiet=ctx.obj["quiet"])
    freed = () if o.groups.strip().lower() == "none" else tuple(g.strip() for g in o.groups.split(",") if g.strip())
    priors = _eo_sigma(o.eo_sigma) if o.eo_sigma else None
    before = adjust_scenes(models, points, groups=())
    pre = None
    if not o.no_preadjust and "look" not in freed:
        pre = preadjust_look_angles(models, points, degree=o.look_degree)
        if not pre.success:
            raise GeometryError(f"look-angle pre-adjustment of '{o.points_file}' failed: {pre.message}; nothing "
                                f"written to '{o.out_dir}'")
        models = {**models, **pre.scenes}
    # the two steps repeated until they settle (--max-rounds), the pre-adjustments' own
    # uncertainty carried into the bundle's sigmas (their look angles are estimates, not exact)
    result = adjust_scenes(models, points, groups=freed, eo_sigma=priors, look_degree=o.look_degree,
                           preadjustment=pre, max_rounds=o.max_rounds)
    if not result.success:
        raise GeometryError(f"adjustment of '{o.points_file}' failed (status {result.status}): {result.message}; "
                            f"nothing written to '{o.out_dir}'")
    if ctx.meta["orthowarp.stop"].is_set():
        raise Cancelled(f"adjustment of '{o.points_file}' cancelled; nothing written to '{o.out_dir}'")
    paths = write_scene_adjustment(result, points, o.out_dir, preadjustment=result.preadjustment, before=before,
                                   plots=not o.no_plots)
    if not ctx.obj["quiet"]:
        click.echo(f"{result.message}; check RMSE east/north/up (m) {np.array2string(result.check_rmse, precision=3)} "
                   f"(uncorrected {np.array2string(before.check_rmse, precision=3)}); outputs: "
                   + ", ".join(os.path.basename(p) for p in paths.values()))


def _inputs(o: SimpleNamespace, *, quiet: bool) -> tuple[dict[str, Any], Any]:
    """(scene id -> scene, measured points) of the --scene and --points options, or of the
    example written first (--write-example); ``o.points_file`` set to the points' file."""
    from ..errors import ParamError
    from ..pipeline.formats.dimap import read_scene
    from ..pipeline.formats.scene_points import read_scene_points, read_scene_points_csv

    scenes = o.scenes
    if o.write_example:
        if scenes or o.points_file:
            raise ParamError("--write-example writes its own scenes and points: give neither --scene nor --points")
        scenes, o.points_file, size = _write_spot_example(o.write_example)
        if not quiet:
            click.echo(f"wrote the example stereo pair (scene JSON files, and {size[0]} x {size[1]} px checkerboard "
                       f"images to orthorectify with 'orthowarp ortho --dimap') and points into {o.write_example}")
    if len(scenes) < 2 or not o.points_file:
        raise ParamError("Give two or more --scene ID FILE and --points FILE (or --write-example DIR)")
    ids = [s for s, _ in scenes]
    dup = next((s for s in ids if ids.count(s) > 1), None)
    if dup is not None:
        raise ParamError(f"--scene id '{dup}' is given twice")
    models = {sid: read_scene(path, attitude_model=o.attitude_model) for sid, path in scenes}
    if o.points_file.lower().endswith(".csv"):
        points = read_scene_points_csv(o.points_file, crs=o.points_crs, sigma=o.pixel_sigma)
    else:
        points = read_scene_points(o.points_file)
    unknown = [s for s in points.scene_ids if s not in models]
    if unknown:
        raise ParamError(f"'{o.points_file}' measures points in scene(s) {unknown}, which no --scene gives")
    return models, points


def _eo_sigma(text: str) -> dict[str, float]:
    """--eo-sigma "position=10,attitude=5e-5" -> dict."""
    from ..errors import ParamError

    out = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, _, value = part.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            raise ParamError(f"--eo-sigma: {part!r} is not quantity=sigma (position m, velocity m/s, attitude rad)") \
                from None
    return out


def _write_spot_example(folder: str) -> tuple[tuple[tuple[str, str], ...], str, tuple[int, int]]:
    """A simulated stereo pair with errors (see orthowarp.adjust.spot_synthetic) written into a
    new folder: ((id, scene JSON) x 2, points JSON, the scenes' (width, height) in pixels),
    with a checkerboard image of each scene's size beside its JSON (<id>.tif)."""
    import numpy as np

    from ..adjust.spot_synthetic import perturbed, simulate_points, stereo_pair
    from ..pipeline.formats.dimap import write_scene
    from ..pipeline.formats.scene_points import write_scene_points
    from ..pipeline.raster.io import check_destination, ensure_folder, write_raster

    check_destination(folder, overwrite=False)
    a, b = stereo_pair()
    eo = np.zeros((3, 3, 3))
    eo[2, :, 0] = [2e-5, -3e-5, 4e-5]  # attitude biases (rad)
    eo[2, :, 1] = [0.0, 1e-6, -2e-6]  # and drifts (rad/s)
    look = np.array([[1e-5, 5e-6, -4e-6], [-8e-6, 3e-6, 2e-6]])  # look-angle biases and trends (rad)
    truth = {"left": perturbed(a, look=look, eo=eo), "right": perturbed(b, look=-look, eo=-eo)}
    points, _ = simulate_points(truth, layout="H-20", seed=7)
    ensure_folder(folder)
    out = []
    for sid, scene in (("left", a), ("right", b)):
        path = os.path.join(folder, f"{sid}.json")
        write_scene(scene, path)
        out.append((sid, path))
        width, height = (int(v) for v in scene.image_size)
        rows, cols = np.arange(height)[:, None] // EXAMPLE_SQUARE, np.arange(width)[None, :] // EXAMPLE_SQUARE
        write_raster(os.path.join(folder, f"{sid}.tif"), (((rows + cols) % 2) * 120 + 60).astype(np.uint8))
    write_scene_points(points, os.path.join(folder, "points.json"))
    return tuple(out), os.path.join(folder, "points.json"), (width, height)
