"""``orthowarp mosaic``: frame images and pushbroom scenes into one mosaic, by
:func:`~orthowarp.pipeline.mosaic.mosaic`."""

from __future__ import annotations

import contextlib
import os
import sys
from types import SimpleNamespace
from typing import Any

import click

from ..options import Blend, Seams, values
from . import options
from .report import crs_label
from .warm import warm_up

# orthowarp mosaic's tile processes on a GPU (bench/reference/mosaic-speed-processes-h100.json)
MOSAIC_GPU_PROCESSES = 4


@click.command()
@click.argument("images", nargs=-1, type=click.Path())
@options.orientation
@options.odm_dataset
@options.exif_options
@options.orthos
@options.adjust_options
@options.chain_control
@options.surface_length
@options.densify
@click.option("--scene", "scenes", nargs=2, multiple=True,
              type=(click.Path(dir_okay=False), click.Path(dir_okay=False)),
              metavar="IMAGE DIMAP", help="A pushbroom scene: its image and its SPOT level-1A DIMAP metadata "
                                          "(repeatable; numbered after IMAGES in the index).")
@options.attitude_model
@options.terrain
@click.option("-o", "--out", "out_path", type=click.Path(), required=True,
              help="The mosaic (COG), or with --tiled its folder.")
@click.option("--index", "index_path", type=click.Path(dir_okay=False),
              help="Also write the per-pixel source index (uint16 COG: the image's position in IMAGES; 65535 "
                   "where no image has a value).")
@options.crs
@options.resolution
@options.resampling
@click.option("--seamlines", "seamlines_path", type=click.Path(dir_okay=False),
              help="Also write each image's part of the mosaic as GeoJSON polygons, in the mosaic's CRS (named "
                   "in a 'crs' member), images named relative to the mosaic's folder.")
@click.option("--seamlines-lonlat", is_flag=True,
              help="Write the seamlines in longitude/latitude (RFC 7946) instead.")
@click.option("--seams", type=click.Choice(values(Seams)), default="least-cost", show_default=True,
              help="Seams where the images agree (moved from the most-nadir seams around buildings, trees, "
                   "moving objects), or the most-nadir seams.")
@click.option("--seam-width", type=float, default=256.0, show_default=True,
              help="How far a least-cost seam may move from the most-nadir seam, output pixels.")
@click.option("--blend", type=click.Choice(values(Blend)), default="feather", show_default=True,
              help="Feather across seams (and towards image borders), blend by frequency bands (fine detail "
                   "sharp, brightness over the feather width), or take each pixel from one image.")
@click.option("--feather", type=float, default=32.0, show_default=True, help="Width of the blend, output pixels.")
@click.option("--no-balance", is_flag=True, help="No radiometric balancing (gain and offset per image and band).")
@click.option("--no-occlusion", is_flag=True,
              help="Project by the backward method (faster; ground hidden from an image is filled with what hides it).")
@click.option("--reference", type=int, default=None,
              help="Balancing keeps this image's radiometry (its position in IMAGES, from 0); default: the mean.")
@options.mosaic_compress
@options.compress_level
@options.quality
@options.block_codec
@options.accuracy_options
@options.creation
@options.dtype
@options.overwrite
@options.no_refraction
@options.vertical
@options.device
@options.workers
@click.option("--processes", type=click.IntRange(min=1), default=None,
              help="Worker processes computing the tiles on the same device (default: 4 on a GPU, 1 on the CPU, "
                   "where 1 is threads of this process); with --gpus, per GPU.")
@options.tile_size
@options.cluster
@click.option("--tiled", is_flag=True,
              help="Write a tiled mosaic into the folder --out: COG tiles (tiles/), mosaic.vrt over them, with "
                   "--index index/ and index.vrt, tiles.geojson naming each tile's images; written by the workers "
                   "that computed them, and a run stopped or killed resumes where it ended (the same command).")
@click.option("--product-tile", type=click.IntRange(min=16), default=None,
              help="With --tiled: the tiles' edge in pixels, a multiple of --tile-size (default: 4, 2 or 1 x "
                   "--tile-size, the largest giving at least 64 tiles).")
@options.profiling
@click.pass_context
def mosaic(ctx: click.Context, images: tuple[str, ...], **kwargs: Any) -> None:
    """Mosaic frame IMAGES and pushbroom scenes (--scene), or orthoimages (--orthos), into one
    cloud-optimized GeoTIFF: each pixel from the image that sees its ground most nearly from above (smallest off-nadir
    angle), the seams moved to where the images agree, feathered across the seams, the images'
    radiometry balanced by gains and offsets from their overlaps."""
    warm_up(kwargs["device"], accuracy=kwargs["accuracy"], more=("orthowarp.kernels.mosaic",))
    import numpy as np

    from ..errors import ParamError
    from ..pipeline.dem import Dem
    from ..pipeline.formats.sensors import odm_dataset
    from ..pipeline.mosaic import mosaic as make_mosaic
    from ..pipeline.precision import accuracy_path
    from ..pipeline.raster.io import outputs_together

    from .exif import chain_terrain, check_chain_options, check_exif_options

    o = SimpleNamespace(**kwargs)
    check_chain_options(o)
    check_exif_options(images, o)
    if o.orthos:
        _check_orthos(images, o)
    if o.odm_dataset is not None:
        images, o.int_param, o.ext_param, o.dem = odm_dataset(o.odm_dataset, images=images, int_param=o.int_param,
                                                              ext_param=o.ext_param, dem=o.dem, height=o.height)
    tie_terrain = False if o.orthos else chain_terrain(o, scenes=bool(o.scenes))
    if not images and not o.scenes:
        raise ParamError("Give frame IMAGES (with --ext-param) or pushbroom scenes (--scene IMAGE DIMAP)")
    if images and not o.ext_param and not o.exif and not o.orthos:
        raise ParamError("Frame IMAGES need --ext-param (their exterior orientation), or --exif (from their tags)")
    compress, compress_level, quality, creation_options = options.creation_args(o.creation, o.compress,
                                                                                o.compress_level, o.quality)
    if compress not in options.MOSAIC_COMPRESS:
        raise ParamError(f"the mosaic is written with {', '.join(options.MOSAIC_COMPRESS)}: -co COMPRESS takes "
                         f"{', '.join(c.upper() for c in options.MOSAIC_COMPRESS)}")
    sigmas = _accuracy_sigmas(o) if o.accuracy else None
    same_datum_given = o.same_vertical_datum  # (--exif may set it for the DEM)
    jobs = _jobs(images, o, quiet=ctx.obj["quiet"])
    if o.accuracy:  # every frame's pose takes that many sigmas, before anything is written
        from ..adjust.precision import pose_inputs

        for _, sensor in jobs:
            if not sensor.line_timed:
                pose_inputs(sensor.pose, len(sigmas[0]))
    terrain = Dem.from_file(o.dem) if o.dem is not None else o.height
    if o.adjust_chain:
        from .exif import exif_chain

        jobs, terrain = exif_chain(jobs, o.exif_job.orientations, None if tie_terrain else terrain, o,
                                   folder=o.adjust_dir or os.path.splitext(o.out_path)[0] + "_adjust",
                                   quiet=ctx.obj["quiet"], same_vertical_datum=same_datum_given)
        if tie_terrain:
            terrain = Dem.from_file(terrain)
    if o.tiled and (o.seamlines_path or o.accuracy):
        raise ParamError("--tiled writes tiles.geojson instead of --seamlines, and no --accuracy raster")
    if o.product_tile is not None and not o.tiled:
        raise ParamError("--product-tile is the tiles' size of a --tiled mosaic")
    processes = o.processes
    if o.scheduler is not None and processes not in (None, 1):
        raise ParamError("--processes is for a mosaic on this host (with --gpus: per GPU); with --scheduler the "
                         "cluster's workers compute the tiles")
    if processes is None and o.scheduler is None:  # a GPU mosaic is bound by the host work per tile: several processes feed it
        from .._device import resolve_device

        processes = MOSAIC_GPU_PROCESSES if o.gpus is not None or resolve_device(o.device).is_cuda else 1
    index = o.index_path
    if o.tiled and index is not None:  # the index's tiles and VRT in the tiled mosaic's folder
        want = os.path.join(o.out_path, "index.vrt")
        if os.path.abspath(index) != os.path.abspath(want):
            raise ParamError(f"With --tiled the index is written as {want} (over {os.path.join(o.out_path, 'index')}"
                             f"/): give --index {want}")
        index = True
    progress = not ctx.obj["quiet"] and sys.stderr.isatty()
    # the mosaic, its sidecars and accuracy raster, or none (a tiled mosaic: its folder, published whole)
    together = contextlib.nullcontext() if o.tiled else outputs_together(overwrite=o.overwrite)
    per_gpu = processes if o.gpus is not None else 1
    if o.gpus is not None:
        processes = None  # (the cluster's workers, per_gpu per GPU)
    with options.cluster_client(o, quiet=ctx.obj["quiet"], processes_per_gpu=per_gpu) as client, together:
        r = make_mosaic(jobs, o.out_path, dem=terrain, crs=o.crs, resolution=o.resolution, resampling=o.resampling,
                        refraction=not o.no_refraction, dtype=o.dtype, index=index, seamlines=o.seamlines_path,
                        seamlines_lonlat=o.seamlines_lonlat, seams=o.seams, seam_width=o.seam_width, blend=o.blend, feather=o.feather,
                        balance=not o.no_balance, reference=o.reference, occlusion=not o.no_occlusion,
                        compress=compress, compress_level=compress_level, quality=quality, block_codec=o.block_codec,
                        creation_options=creation_options,
                        overwrite=o.overwrite, device=o.device, geoid=o.geoid,
                        same_vertical_datum=o.same_vertical_datum, workers=o.workers, processes=processes,
                        tile_size=o.tile_size, cancel=ctx.meta.get("orthowarp.stop"), cluster=client,
                        tiled=o.tiled, product_tile=o.product_tile, progress=progress or None)
        if o.accuracy:
            from ..pipeline.precision import mosaic_accuracy_raster

            mosaic_accuracy_raster(accuracy_path(r.path), jobs, r.index, terrain, r.crs, r.transform, r.shape,
                                   pose_cov=np.diag(sigmas[0]) ** 2, orientation_cov=np.diag(sigmas[1]) ** 2,
                                   pixel_sigma=o.pixel_sigma, dem_sigma=o.dem_sigma, measure=o.accuracy_measure,
                                   step=o.accuracy_step, refraction=not o.no_refraction, geoid=o.geoid,
                                   same_vertical_datum=o.same_vertical_datum, device=o.device)
    if o.show_profile or o.profile_json:
        _report_profile(r, len(jobs), show=o.show_profile, path=o.profile_json)
    if o.tiled:
        if not ctx.obj["quiet"]:
            click.echo(f"{r.path}: {r.tiles} tiles ({r.tiles_computed} computed, {r.tiles_kept} kept from an earlier "
                       f"run); {r.vrt}")
        return
    if not ctx.obj["quiet"]:
        counts = ", ".join(f"{os.path.basename(img)} {n}" for (img, *_), n in zip(jobs, r.pixels_per_image))
        click.echo(f"{r.path}: {r.shape[1]} x {r.shape[0]} px at {r.resolution:.4g} ({crs_label(r.crs)}); pixels per "
                   f"image: {counts}")


def _accuracy_sigmas(o: SimpleNamespace) -> tuple[list[float], list[float]]:
    """(frame pose sigmas, scene sigmas) of ``--accuracy``, checked, and the accuracy raster's
    destination checked, before any work."""
    from ..errors import ParamError
    from ..pipeline.precision import accuracy_path
    from ..pipeline.raster.io import check_destination

    if not o.index_path:
        raise ParamError("--accuracy takes each cell's image from the index: give --index too")
    frame = options.sigma_list(o.pose_sigma, (6, 9, 12), "--pose-sigma", options.FRAME_SIGMA_UNITS)
    scene = options.sigma_list(o.scene_sigma, 8, "--scene-sigma", options.SCENE_SIGMA_UNITS)
    options.check_measurement_sigmas(o.pixel_sigma, o.dem_sigma)
    check_destination(accuracy_path(o.out_path), overwrite=o.overwrite)
    return frame, scene


def _jobs(images: tuple[str, ...] | list[str], o: SimpleNamespace, *, quiet: bool = True) -> list[tuple[str, Any]]:
    """(image, sensor) of the frame IMAGES (from their tags with --exif), then of the --scene
    scenes."""
    from ..errors import RasterIOError
    from ..pipeline.formats.sensors import frame_sensors

    if o.orthos:
        from ..pipeline.formats.orthos import ortho_images

        return ortho_images(images)
    if o.exif:
        from .exif import exif_jobs

        o.exif_job = exif_jobs(images, o, quiet=quiet)
        jobs = list(o.exif_job.sensors)
    else:
        jobs = frame_sensors(images, o.int_param, o.ext_param, crs=o.crs) if images else []
    if o.scenes:
        from ..pipeline.formats.dimap import read_scene

        for image, dimap in o.scenes:
            if not os.path.exists(image):
                raise RasterIOError(f"Image '{image}' does not exist")
            jobs.append((image, read_scene(dimap, attitude_model=o.attitude_model)))
    return jobs


def _report_profile(r: Any, images: int, *, show: bool, path: str | None) -> None:
    """The mosaic's profile: the plan's steps and the tiles' stages, on stderr (``show``) and
    as JSON (``path``)."""
    from ..pipeline.raster.io import write_json
    from ..pipeline.reports.profile import format_profile

    steps = ", ".join(f"{k} {v:.3f} s" for k, v in r.setup_s.items() if k != "total")
    if show:
        click.echo(f"plan: {r.setup_s.get('total', 0.0):.3f} s ({steps})", err=True)
        click.echo(format_profile(r.profile, f"{r.path} (tiles and writing)"), err=True)
        call = getattr(r, "call_s", None)
        if call:
            click.echo("call: " + ", ".join(f"{k[:-2].replace('_', ' ')} {v:.3f} s" for k, v in call.items()
                                            if v is not None), err=True)
    if path:
        write_json(path, dict(plan_s=r.setup_s, tiles=r.profile, wall_s=r.wall_s,
                              output_pixels=int(r.shape[0]) * int(r.shape[1]),
                              shape=list(r.shape), resolution=r.resolution, image_builds=r.image_builds,
                              images_held_peak=r.images_held_peak, images=images,
                              call_s=getattr(r, "call_s", None)))


def _check_orthos(images: tuple[str, ...], o: SimpleNamespace) -> None:
    """ParamError for the options that ``--orthos`` has no use for (orientation, terrain, the
    accuracy and adjustment of raw images), and for no IMAGES."""
    from ..errors import ParamError

    given = [name for name, v in (("--int-param", o.int_param), ("--ext-param", o.ext_param), ("--exif", o.exif),
                                  ("--odm-dataset", o.odm_dataset), ("--scene", o.scenes), ("--dem", o.dem),
                                  ("--height", o.height is not None), ("--geoid", o.geoid),
                                  ("--accuracy", o.accuracy), ("--adjust", o.adjust_chain)) if v]
    if given:
        raise ParamError(f"--orthos mosaics orthoimages by their own georeferencing: give it without "
                         f"{', '.join(given)}")
    if not images:
        raise ParamError("--orthos needs IMAGES: the orthoimages (files or wildcards)")
