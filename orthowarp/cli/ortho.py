"""``orthowarp ortho``: frame images or one pushbroom scene into orthos, by
:func:`~orthowarp.pipeline.ortho.batch.orthorectify_many`."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from types import SimpleNamespace
from typing import Any

import click

from ..options import Method, SourceReads, values
from . import options
from .report import crs_label
from .warm import warm_up

_DEFAULT_SOURCES = (None, click.core.ParameterSource.DEFAULT, click.core.ParameterSource.DEFAULT_MAP)


@click.command()
@click.argument("images", nargs=-1, type=click.Path())
@options.odm_dataset
@options.orientation
@options.exif_options
@options.adjust_options
@click.option("--dimap", type=click.Path(dir_okay=False),
              help="SPOT level-1A DIMAP metadata of a pushbroom scene, or a scene JSON from 'orthowarp spot-adjust' "
                   "(instead of --int-param/--ext-param; one image).")
@options.attitude_model
@click.option("--rpc", "rpc", is_flag=False, flag_value="", default=None, type=click.Path(dir_okay=False),
              metavar="[FILE]",
              help="One RPC image (rational polynomial coefficients of a satellite image; instead of --int-param/"
                   "--ext-param): its RPCs from its own metadata (GeoTIFF RPC tags, NITF, an .RPB or _RPC.TXT beside it) "
                   "when FILE is omitted, else from FILE: .RPB, _RPC.TXT or orthority's RPC parameter file. Give the "
                   "image before --rpc. Heights are ellipsoidal (a DEM of orthometric heights takes --geoid or "
                   "--same-vertical-datum).")
@options.gcps
@click.option("--bias", type=click.Choice(["shift", "affine"]), default="shift", show_default=True,
              help="With --gcps: the compensation's model: a shift of the image, or an affine map (3 points at least).")
@options.check_points
@options.gcp_sigma
@options.gcp_pixel_sigma
@options.surface_length
@options.densify
@options.terrain
@options.crs
@options.resolution
@options.resampling
@click.option("--method", type=click.Choice(values(Method)), default="backward", show_default=True,
              help="backward: project each output pixel into the source; forward: the direct method "
                   "(geolocate each source pixel; hidden ground stays nodata).")
@click.option("--driver", type=click.Choice(["cog", "gtiff"], case_sensitive=False), default="cog", show_default=True,
              help="Cloud-optimized GeoTIFF or tiled GeoTIFF.")
@options.compress
@options.quality
@options.compress_level
@options.block_codec
@click.option("--source-reads", type=click.Choice(values(SourceReads)), default="auto", show_default=True,
              help="How the image reaches the device: whole (read once, by strips on several threads, into device "
                   "memory), tiles (each output tile reads its own window); auto: whole on a GPU where the image takes "
                   "at most a quarter of its free memory, else tiles. The pixels written are the same.")
@options.creation
@options.dtype
@options.out_dir(default=".", what="Output folder: <image>_ORTHO.tif for each image.")
@options.overwrite
@options.no_refraction
@options.vertical
@options.device
@options.tile_size
@options.cluster
@click.option("--export-params", is_flag=True,
              help="Write the frame IMAGES' orientation in orthority's formats (int_param.yaml, ext_param.csv "
                   "and .prj) into --out-dir, and stop (no orthos).")
@options.accuracy_options
@click.option("--pose-cov", "pose_cov_file", type=click.Path(dir_okay=False),
              help="With --accuracy: each image's pose covariance from 'orthowarp adjust' (its pose_cov.json, "
                   "the exterior file's parameters), instead of --pose-sigma.")
@options.profiling
@click.pass_context
def ortho(ctx: click.Context, images: tuple[str, ...], **kwargs: Any) -> None:
    """Orthorectify frame IMAGES, one pushbroom scene (--dimap) or one RPC image (--rpc), into
    (cloud-optimized) GeoTIFFs named <image>_ORTHO.tif; drone images' cameras and poses may come
    from their tags (--exif), refined first by tie points and a bundle adjustment (--adjust)."""
    t_command = time.perf_counter()
    _spare_final_collection()
    if not kwargs["export_params"]:
        warm_up(kwargs["device"], accuracy=kwargs["accuracy"])
    from ..errors import ParamError
    from ..pipeline.formats.sensors import odm_dataset
    from ..pipeline.ortho.batch import orthorectify_many

    t_imported = time.perf_counter()
    o = SimpleNamespace(**kwargs)
    if o.odm_dataset is not None:
        images, o.int_param, o.ext_param, o.dem = odm_dataset(o.odm_dataset, images=images, int_param=o.int_param,
                                                              ext_param=o.ext_param, dem=o.dem, height=o.height)
    from .exif import chain_terrain, check_chain_options, check_exif_options

    if o.gcps is not None and o.rpc is None and not o.adjust_chain:
        raise ParamError("--gcps goes with --rpc (an RPC image's bias compensation) or with --exif --adjust (ground "
                         "control of the drone chain)")
    check_chain_options(o, chain_gcps=o.rpc is None)
    check_exif_options(images, o)
    if not images:
        if o.dimap is not None:
            raise ParamError(f"--dimap '{o.dimap}' describes a scene: give its image as IMAGES")
        if o.rpc:
            raise ParamError(f"--rpc took '{o.rpc}' as its RPC file and no image is left: give the image before --rpc "
                             "(orthowarp ortho IMAGE --rpc [FILE])")
        raise ParamError("Give IMAGES (or --odm-dataset DIR)")
    if o.export_params:
        if o.adjust_chain:
            raise ParamError("--export-params writes the tags' orientation and stops; --adjust writes the adjusted "
                             "one (exterior.csv, cameras.yaml in --adjust-dir) with the orthos: give one or the other")
        _export_params(images, o, quiet=ctx.obj["quiet"])
        return
    if o.rpc is not None and o.accuracy:
        raise ParamError("--accuracy is not available for RPC images (--rpc): RPCs carry no orientation to propagate")
    pose_cov, orientation_cov = _covariances(ctx, o)
    tie_terrain = chain_terrain(o)
    compress, compress_level, quality, creation_options = options.creation_args(o.creation, o.compress,
                                                                                o.compress_level, o.quality)
    ortho_options = dict(crs=o.crs, resolution=o.resolution, resampling=o.resampling, method=o.method,
                         refraction=not o.no_refraction, dtype=o.dtype,
                         driver="COG" if o.driver.lower() == "cog" else "GTiff", compress=compress,
                         compress_level=compress_level, quality=quality, block_codec=o.block_codec,
                         source_reads=o.source_reads, creation_options=creation_options, device=o.device,
                         tile_size=o.tile_size, geoid=o.geoid, same_vertical_datum=o.same_vertical_datum)
    same_datum_given = o.same_vertical_datum  # (--exif may set it for the DEM)
    jobs = _jobs(images, o, quiet=ctx.obj["quiet"])
    ortho_options["same_vertical_datum"] = o.same_vertical_datum  # (--exif may take the DEM in the GPS's datum)
    quiet, profiles = ctx.obj["quiet"], []
    terrain = o.dem if o.dem is not None else o.height
    if o.adjust_chain:
        jobs, terrain = _adjusted(jobs, None if tie_terrain else terrain, o, quiet=quiet,
                                  same_vertical_datum=same_datum_given)

    def report(dst: str, r: Any) -> None:
        if not quiet:
            click.echo(f"{dst}: {r.shape[1]} x {r.shape[0]} px at {r.resolution:.4g} ({crs_label(r.crs)}), "
                       f"{r.timings['wall']:.2f} s")
        profiles.append((dst, r.profile))
        if o.show_profile:
            from ..pipeline.reports.profile import format_profile

            click.echo(format_profile(r.profile, dst), err=True)

    from tqdm import tqdm

    # one bar for the batch (the tiles of every image, as each starts), on a terminal only
    show = not quiet and sys.stderr.isatty()
    t_first = time.perf_counter()
    with options.cluster_client(o, quiet=quiet) as client:
        # one bar for the batch: the tiles of every image as each starts, or on a cluster the images
        bar = tqdm(total=0, unit="tile", leave=False, disable=not show) if client is None else show or None
        with bar if client is None else contextlib.nullcontext():
            orthorectify_many(jobs, dem=terrain, accuracy=o.accuracy,
                              pose_cov=pose_cov, orientation_cov=orientation_cov, pixel_sigma=o.pixel_sigma,
                              dem_sigma=o.dem_sigma, accuracy_measure=o.accuracy_measure,
                              accuracy_step=o.accuracy_step, overwrite=o.overwrite, progress=bar,
                              cancel=ctx.meta.get("orthowarp.stop"), on_result=report, cluster=client,
                              **ortho_options)
    if o.show_profile or o.profile_json:
        _report_profile(profiles, time.perf_counter() - t_first, (t_command, t_imported, t_first),
                        show=o.show_profile, path=o.profile_json)


def _export_params(images: tuple[str, ...] | list[str], o: SimpleNamespace, *, quiet: bool) -> None:
    """``--export-params``: the frame images' orientation in orthority's formats."""
    from ..errors import ParamError
    from ..pipeline.formats.export import export_params
    from ..pipeline.formats.sensors import frame_orientations

    if o.exif:
        from .exif import exif_jobs

        orients = exif_jobs(images, o, quiet=quiet).orientations
    elif o.dimap or not o.ext_param:
        raise ParamError("--export-params writes frame images' orientations: give --ext-param (not --dimap)")
    else:
        orients = frame_orientations(images, o.int_param, o.ext_param, crs=o.crs)
    for path in export_params([(x.image, x.camera, x.pose) for x in orients], o.out_dir,
                              camera_ids={id(x.camera): x.camera_id for x in orients}, overwrite=o.overwrite):
        if not quiet:
            click.echo(path)


def _covariances(ctx: click.Context, o: SimpleNamespace) -> tuple[Any, Any]:
    """(pose_cov, orientation_cov) for the accuracy rasters: the frames' pose covariance (from
    --pose-sigma, or the --pose-cov file), the scene's (from --scene-sigma); checked here
    as far as the options go, before anything is read."""
    import numpy as np

    from ..errors import ParamError

    def given(name: str) -> bool:
        return ctx.get_parameter_source(name) not in _DEFAULT_SOURCES

    if o.pose_cov_file is not None:
        if given("pose_sigma"):
            raise ParamError("Give --pose-sigma or --pose-cov, not both: --pose-cov replaces the sigmas")
        if not o.accuracy or o.dimap:
            raise ParamError("--pose-cov goes with --accuracy for frame images")
    if not o.accuracy:
        return None, None
    options.check_measurement_sigmas(o.pixel_sigma, o.dem_sigma)
    if o.dimap is None:
        if o.pose_cov_file is not None:
            return o.pose_cov_file, None
        sigmas = options.sigma_list(o.pose_sigma, (6, 9, 12), "--pose-sigma", options.FRAME_SIGMA_UNITS)
        return np.diag(sigmas) ** 2, None
    text, name = o.scene_sigma, "--scene-sigma"
    if given("pose_sigma"):  # the scene's sigmas under their earlier name
        if given("scene_sigma"):
            raise ParamError("A --dimap scene's sigmas are --scene-sigma: give it alone, without --pose-sigma")
        click.echo("Warning: --pose-sigma for a --dimap scene is deprecated: use --scene-sigma", err=True)
        text, name = o.pose_sigma, "--pose-sigma"
    return None, np.diag(options.sigma_list(text, 8, name, options.SCENE_SIGMA_UNITS)) ** 2


def _jobs(images: tuple[str, ...] | list[str], o: SimpleNamespace, *, quiet: bool = True) -> list[tuple[str, Any, str]]:
    """(image, sensor, destination) of each image: the --dimap scene, or the frames (from
    their tags with --exif)."""
    from ..errors import ParamError, RasterIOError
    from ..pipeline.ortho.batch import ortho_destinations

    if o.rpc is not None:
        return ortho_destinations([(images[0], _rpc_sensor(images, o, quiet=quiet))], o.out_dir)
    if o.exif:
        from .exif import exif_jobs

        o.exif_job = exif_jobs(images, o, quiet=quiet)
        return ortho_destinations(o.exif_job.sensors, o.out_dir)

    if o.dimap is not None:
        from ..pipeline.formats.dimap import read_scene

        if o.int_param or o.ext_param:
            raise ParamError("--dimap replaces --int-param and --ext-param: give one or the other")
        if len(images) != 1:
            raise ParamError(f"--dimap describes one scene: give its one image, not {len(images)}")
        if not os.path.exists(images[0]):
            raise RasterIOError(f"Image '{images[0]}' does not exist")
        return ortho_destinations([(images[0], read_scene(o.dimap, attitude_model=o.attitude_model))], o.out_dir)
    if not o.ext_param:
        raise ParamError("Give --ext-param (frame images) or --dimap (a pushbroom scene)")
    from ..pipeline.formats.sensors import frame_sensors

    return ortho_destinations(frame_sensors(images, o.int_param, o.ext_param, crs=o.crs), o.out_dir)


def _adjusted(jobs: list[tuple[str, Any, str]], terrain: Any, o: SimpleNamespace, *, quiet: bool,
              same_vertical_datum: bool) -> tuple[list[tuple[str, Any, str]], Any]:
    """``--exif --adjust``: the orthos' destinations (and accuracy rasters') checked, then the
    frames' orientation refined by the chain (:func:`.exif.exif_chain`), its files in
    --adjust-dir (default ``adjust/`` in --out-dir). ``terrain`` None: the terrain returned is
    the adjusted tie points' surface (its path); else ``terrain`` as it is."""
    from ..pipeline.precision import accuracy_path
    from ..pipeline.raster.io import check_destination
    from .exif import exif_chain

    for *_, dst in jobs:  # before the chain's minutes
        check_destination(dst, overwrite=o.overwrite)
        if o.accuracy:
            check_destination(accuracy_path(dst), overwrite=o.overwrite)
    adjusted, terrain = exif_chain([(img, s) for img, s, _ in jobs], o.exif_job.orientations, terrain, o,
                                   folder=o.adjust_dir or os.path.join(o.out_dir, "adjust"), quiet=quiet,
                                   same_vertical_datum=same_vertical_datum)
    return [(img, s, dst) for (img, s), (*_, dst) in zip(adjusted, jobs)], terrain


def _rpc_sensor(images: tuple[str, ...] | list[str], o: SimpleNamespace, *, quiet: bool) -> Any:
    """The --rpc image's sensor, compensated with --gcps (the estimate and the check residuals
    printed unless ``quiet``)."""
    from ..errors import ParamError
    from ..pipeline.rpc import rpc_image_sensor

    if o.dimap is not None or o.int_param or o.ext_param or getattr(o, "exif", False):
        raise ParamError("--rpc replaces --int-param, --ext-param, --exif and --dimap: give one or the other")
    if len(images) != 1:
        raise ParamError(f"--rpc orthorectifies one image, not {len(images)}")
    item = rpc_image_sensor(images[0], rpc=o.rpc or None, gcps=o.gcps, bias=o.bias)
    if item.bias is not None and not quiet:
        s = item.summary()
        terms = ", ".join(f"{k} {v:+.6g}" for k, v in s["estimates"].items() if v != 0.0)
        sigma0 = f"{s['sigma0']:.3g}" if s["sigma0"] == s["sigma0"] else "- (no redundancy)"
        click.echo(f"{images[0]}: {s['model']} bias from {s['points']} GCPs: {terms} (px); sigma0 {sigma0}; "
                   f"leave-one-out check RMS {s['check_rms_before_px']:.3f} px without, "
                   f"{s['check_rms_after_px']:.3f} px with the compensation")
    return item.sensor


_SPARED = []


def _spare_final_collection() -> None:
    """At the process's exit, freeze the objects then alive (``gc.freeze``), so that the
    interpreter's final garbage collections do not traverse the tens of thousands of objects
    Warp, its kernels and the pipeline's modules hold: that saves ~0.25 s at the end of every
    ``orthowarp ortho`` on a 2-core machine. Runs after the command (outputs published,
    datasets closed), as an atexit handler, so in-process callers (tests) are unaffected until
    they exit too. Cyclic garbage left at exit is then reclaimed by the OS, not finalised."""
    if not _SPARED:
        import atexit
        import gc

        atexit.register(gc.freeze)
        _SPARED.append(True)


def _report_profile(profiles: list[tuple[str, dict]], batch_wall: float, marks: tuple[float, float, float], *,
                    show: bool, path: str | None) -> None:
    """The ortho command's profile: the batch total (several images) and the start-up, on stderr
    (``show``) and as JSON (``path``). ``marks``: perf_counter() readings at the command's
    start, after its imports, and at the batch's start."""
    from ..pipeline.raster.io import write_json
    from ..pipeline.reports.profile import format_profile, merge_profiles, process_start

    t_command, t_imported, t_first = marks
    first = profiles[0][1]
    p0 = process_start()
    setup = first["first_kernel_s"]
    startup = dict(
        # process start -> the first tile's first kernel launch of the first image
        startup_s=(t_first - p0 + setup) if p0 is not None and setup is not None else None,
        to_command_s=(t_command - p0) if p0 is not None else None,  # interpreter, CLI and Warp imports
        job_imports_s=t_imported - t_command,  # the pipeline's modules
        inputs_s=t_first - t_imported,  # orientation files, option checks
        image_setup_s=setup)  # Warp initialisation, geometry, output grid, kernel modules, first tile
    total = merge_profiles([p for _, p in profiles], wall=batch_wall)
    if show:
        if len(profiles) > 1:
            click.echo(format_profile(total, "total"), err=True)
        if startup["startup_s"] is None:
            click.echo("start-up: the process start time is not available on this system", err=True)
        else:
            click.echo(f"start-up: {startup['startup_s']:.3f} s from the process start to the first kernel: "
                       f"{startup['to_command_s']:.3f} s to the command (interpreter, CLI and Warp imports), "
                       f"{startup['job_imports_s']:.3f} s the pipeline's imports, {startup['inputs_s']:.3f} s "
                       f"orientation files, {startup['image_setup_s']:.3f} s image set-up (DEM, Warp "
                       f"initialisation, geometry, output grid, kernel modules, first tile)", err=True)
    if path:
        write_json(path, dict(images=[dict(path=dst, profile=p) for dst, p in profiles], total=total,
                              startup=startup))
