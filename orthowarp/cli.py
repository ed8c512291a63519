"""The ``orthowarp`` command line: parses, calls the public API, reports.

Library errors become one-line messages on stderr and a non-zero exit code.
"""

import logging
import os
import signal
import sys
import threading
import time
import warnings

import click
import numpy as np

from .errors import OrthowarpError, OrthowarpWarning
from .sensor import FrameSensor


class _Group(click.Group):
    """Run a command so that it can be stopped cleanly, and report its end: library errors
    become a one-line message and exit code 1; SIGINT and SIGTERM a clean stop with exit code
    130 or 143.

    The command runs in a worker thread. A signal only sets the event
    ``ctx.meta["orthowarp.stop"]``, which the commands pass to the library as ``cancel``: the
    ortho stops before its next tile, and nothing is published. The main thread waits; if the
    command has not ended ``STOP_GRACE`` seconds after the signal (a stage that does not look
    at the event), or at a second signal, it removes this process's temporaries and exits at
    once. No exception is ever raised asynchronously into library code (where it could leave
    a lock held)."""

    STOP_GRACE = 10.0

    def invoke(self, ctx):
        shown = warnings.showwarning

        def show(message, category, *args, **kwargs):  # the library's warnings as one line each
            if issubclass(category, OrthowarpWarning):
                click.echo(f"Warning: {message}", err=True)
            else:
                shown(message, category, *args, **kwargs)

        warnings.showwarning = show
        try:
            return self._invoke(ctx)
        finally:
            warnings.showwarning = shown

    def _invoke(self, ctx):
        stop = ctx.meta["orthowarp.stop"] = threading.Event()
        if threading.current_thread() is not threading.main_thread():  # no signals: run here
            return self._report(lambda: super(_Group, self).invoke(ctx))
        outcome, received = {}, []

        def work():
            try:
                outcome["value"] = super(_Group, self).invoke(ctx)
            except BaseException as e:  # handed to the main thread
                outcome["error"] = e

        def handle(signum, frame):
            if received:
                _exit_now(signum)
            received.append((signum, time.monotonic()))
            stop.set()

        previous = {sig: signal.signal(sig, handle) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            worker = threading.Thread(target=work, name="orthowarp-command")
            worker.start()
            while worker.is_alive():
                worker.join(0.1)
                if received and time.monotonic() - received[0][1] > self.STOP_GRACE:
                    _exit_now(received[0][0])
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if received:
            terminated = received[0][0] == signal.SIGTERM
            click.echo(f"Error: {'terminated' if terminated else 'interrupted'}; no output was left half-written",
                       err=True)
            sys.exit(128 + received[0][0])

        def result():
            if "error" in outcome:
                raise outcome["error"]
            return outcome.get("value")

        return self._report(result)

    @staticmethod
    def _report(call):
        try:
            return call()
        except OrthowarpError as e:
            click.echo(f"Error: {e}", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            click.echo("Error: interrupted; no output was left half-written", err=True)
            sys.exit(128 + signal.SIGINT)


def _exit_now(signum):
    """Last resort of a stop: remove the temporaries, exit without waiting for anything."""
    from .pipeline.io import remove_own_temporaries

    remove_own_temporaries()
    sys.stderr.write(f"Error: stopped by signal {signum}; temporaries removed\n")
    sys.stderr.flush()
    os._exit(128 + signum)


_FRAME_POSE_SIGMA = "0.05,0.05,0.1,0.005,0.005,0.01"
_SCENE_SIGMA = "10,10,5,0.001,0.001,0.001,0.001,0.001"
# orthowarp mosaic's tile processes on a GPU (bench/reference/mosaic-speed-processes-h100.json)
MOSAIC_GPU_PROCESSES = 4


@click.group(cls=_Group)
@click.version_option(package_name="orthowarp")
@click.option("-v", "--verbose", count=True,
              help="More log output, Warp's own messages included (-vv for debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors; no progress bars.")
@click.pass_context
def main(ctx, verbose, quiet):
    """orthowarp: rigorous orthorectification on the GPU with NVIDIA Warp."""
    import warp as wp

    from ._device import set_warp_messages

    ctx.obj = {"quiet": quiet}
    level = logging.ERROR if quiet else (logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    # Warp's banner, module-load lines and driver notices only with -v; the library keeps them
    # quiet during its calls, and this process is the CLI's own, so its Warp level is set too.
    show = bool(verbose) and not quiet
    set_warp_messages(show)
    if show and hasattr(wp, "LOG_INFO") and wp.config.log_level > wp.LOG_INFO:
        wp.config.log_level = wp.LOG_INFO
    elif not show:
        if hasattr(wp, "LOG_WARNING"):
            wp.config.log_level = wp.LOG_WARNING
        else:  # warp-lang < 1.10
            wp.config.quiet = True


@main.command()
@click.option("--out", "out_dir", default="orthowarp-demo", show_default=True, type=click.Path(file_okay=False),
              help="Output folder.")
@click.option("--device", default=None, help="Warp device (cpu, cuda, cuda:N); default: first GPU, else CPU.")
@click.option("--no-chain", is_flag=True,
              help="Skip the second part: a four-frame block from approximate orientation through matching, "
                   "adjustment and mosaic (about 30 s on two CPU cores).")
def demo(out_dir, device, no_chain):
    """Run the embedded synthetic scene end to end and report its accuracy; then the automatic
    chain (approximate orientation -> tie points by matching -> adjustment -> mosaic) on a
    block of four frames of the same scene, measured against its truth."""
    from .pipeline.demo import run_demo

    s = run_demo(out_dir, device=device, chain=not no_chain)
    w, h = s["image_size"]
    click.echo(f"orthowarp demo: synthetic {w}x{h} frame (GSD {s['gsd_m']:.2f} m), DEM {s['dem_shape'][1]}x{s['dem_shape'][0]}, device {s['device']}")
    click.echo(f"  forward geolocation (DEM relief search, refraction): {s['geolocation_seconds']:.2f} s, "
               f"{s['geolocation_mpix_per_s']:.2f} Mpix/s, {s['pixels_without_ground']} pixels without ground")
    click.echo(f"  accuracy vs scene truth ({s['check_points']} points on the terrain): RMS {s['check_rms_m'] * 1000:.3f} mm, "
               f"max {s['check_max_m'] * 1000:.3f} mm ({s['check_max_px']:.2e} px)")
    click.echo(f"  ground -> pixel -> ground -> pixel round trip: max {s['round_trip_max_px']:.2e} px")
    click.echo(f"  orthoimage {s['ortho_size'][0]}x{s['ortho_size'][1]} at {s['ortho_resolution_m']:.2f} m ({s['ortho_crs']}), "
               f"{s['ortho_seconds']:.2f} s; misregistration vs truth texture over {s['ortho_misregistration_tiles']} tiles: "
               f"RMS {s['ortho_misregistration_rms_px']:.3f} px, mean ({s['ortho_misregistration_mean_px'][0]:+.3f}, "
               f"{s['ortho_misregistration_mean_px'][1]:+.3f}) px")
    if "chain" in s:
        c = s["chain"]
        click.echo(f"  chain on {c['images']} frames: {c['ties']} tie points by matching ({c['tie_observations']} "
                   f"observations, {c['match_seconds']:.1f} s), adjusted with {c['control_points']} control points "
                   f"(sigma0 {c['sigma0']:.2f}, {c['adjust_seconds']:.2f} s); outputs in {out_dir}/chain/")
        for name in ("approximate", "adjusted"):
            r = c[name]
            click.echo(f"    {name:>11s} orientation: centres off by up to {r['pose_error_max_m']:.2f} m, attitudes "
                       f"{r['attitude_error_max_deg']:.3f} deg; mosaic vs truth texture: RMS "
                       f"{r['mosaic_misregistration_rms_m']:.2f} m, max {r['mosaic_misregistration_max_m']:.2f} m "
                       f"({r['mosaic_tiles']} tiles)")
    click.echo(f"  outputs in {out_dir}/: {', '.join(s['outputs'])}")


@main.command()
@click.argument("images", nargs=-1, type=click.Path(dir_okay=False))
@click.option("--odm-dataset", type=click.Path(file_okay=False),
              help="An OpenDroneMap dataset folder: its opensfm/reconstruction.json for --int-param and --ext-param, "
                   "its odm_dem/dsm.tif for --dem (unless --dem or --height is given) and, without IMAGES, "
                   "its images/.")
@click.option("--int-param", "int_param", type=click.Path(dir_okay=False),
              help="Interior orientation: orthority/ODM camera file (YAML/JSON) or reconstruction.json.")
@click.option("--ext-param", "ext_param", type=click.Path(dir_okay=False),
              help="Exterior orientation: CSV (x,y,z,omega,phi,kappa or latitude,longitude,altitude,roll,pitch,yaw), "
                   "orthority GeoJSON or OpenSfM reconstruction.json.")
@click.option("--dimap", type=click.Path(dir_okay=False),
              help="SPOT level-1A DIMAP metadata of a pushbroom scene, or a scene JSON from 'orthowarp spot-adjust' (instead of --int-param/--ext-param; one image).")
@click.option("--attitude-model", type=click.Choice(["full", "first_order"]), default=None,
              help="Pushbroom attitude matrix: full (the default for DIMAP), or its first-order (linearised) form; "
                   "a scene JSON from 'orthowarp spot-adjust' keeps its own.")
@click.option("--dem", type=click.Path(dir_okay=False), help="DEM file (any CRS).")
@click.option("--height", type=float, help="Constant terrain height (m) instead of a DEM.")
@click.option("--crs", help="Output CRS (EPSG code, WKT or PROJ string); also the CRS of x,y,z poses in a file that "
                           "names none (no .prj; without --crs the images' own CRS, if they have one).")
@click.option("--resolution", type=float,
              help="Output pixel size in CRS units (default: the mean GSD in those units, so it carries the CRS's "
                   "scale: e.g. 1/cos(latitude) times the metres on the ground in Web Mercator).")
@click.option("--resampling", type=click.Choice(["nearest", "bilinear", "bicubic", "lanczos"]), default="bilinear",
              show_default=True)
@click.option("--method", type=click.Choice(["backward", "forward"]), default="backward", show_default=True,
              help="backward: project each output pixel into the source; forward: the direct method "
                   "(geolocate each source pixel; hidden ground stays nodata).")
@click.option("--driver", type=click.Choice(["cog", "gtiff"], case_sensitive=False), default="cog", show_default=True)
@click.option("--compress", type=click.Choice(["deflate", "zstd", "lzw", "jpeg", "webp", "none"]), default="deflate",
              show_default=True, help="Lossless (deflate, zstd, lzw, none) or lossy for uint8 RGB (jpeg, webp: "
                                      "files 10-40 times smaller; see --quality).")
@click.option("--quality", type=click.IntRange(1, 100), default=None,
              help="JPEG / WebP quality 1-100 (default 90; orthority's JPEG default is 75).")
@click.option("--compress-level", type=int, default=None,
              help="Deflate level 1-12 (default 6) or zstd level 1-22 (default 9).")
@click.option("--block-codec", type=click.Choice(["auto", "host", "nvcomp", "hybrid", "warp"]), default="auto", show_default=True,
              help="Who deflates a COG's blocks: host (libdeflate on all cores), nvcomp (the GPU; needs "
                   "orthowarp[gpu]), warp (orthowarp's own deflate kernels on the device), hybrid (the device: nvCOMP at "
                   "--compress-level 1-4 where installed, else warp; and the host cores at once); auto: "
                   "on a GPU nvcomp at --compress-level 1-4 where installed, else hybrid; on the CPU host.")
@click.option("--source-reads", type=click.Choice(["auto", "whole", "tiles"]), default="auto", show_default=True,
              help="How the image reaches the device: whole (read once, by strips on several threads, into device "
                   "memory), tiles (each output tile reads its own window); auto: whole on a GPU where the image takes "
                   "at most a quarter of its free memory, else tiles. The pixels written are the same.")
@click.option("-co", "--co", "creation", multiple=True, metavar="KEY=VALUE",
              help="GDAL-style creation option, repeatable: BLOCKSIZE (64-4096, multiple of 16; default 512), "
                   "BIGTIFF (YES, NO, IF_NEEDED, IF_SAFER), NUM_THREADS (count or ALL_CPUS); COMPRESS, LEVEL (ZLEVEL) "
                   "and QUALITY (JPEG_QUALITY) set --compress, --compress-level and --quality; PREDICTOR=YES (2) is "
                   "what orthowarp writes for integer data.")
@click.option("--dtype", type=click.Choice(["uint8", "uint16", "float32"]), help="Output data type (default: the source's).")
@click.option("--out-dir", type=click.Path(file_okay=False), default=".", show_default=True)
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@click.option("--no-refraction", is_flag=True, help="Do not correct atmospheric refraction.")
@click.option("--geoid", type=click.Path(dir_okay=False), help="Geoid grid for converting between DEM and position heights.")
@click.option("--same-vertical-datum", is_flag=True, help="Take DEM and position heights as the same vertical datum.")
@click.option("--device", default=None, help="Warp device (cpu, cuda, cuda:N); default: first GPU, else CPU.")
@click.option("--tile-size", type=int, default=None, help="Output tile edge (pixels); default 512 on the CPU, up to 4096 on a GPU.")
@click.option("--export-params", is_flag=True,
              help="Write the frame IMAGES' orientation in orthority's formats (int_param.yaml, ext_param.csv "
                   "and .prj) into --out-dir, and stop (no orthos).")
@click.option("--accuracy", is_flag=True,
              help="Also write <image>_ACCURACY.tif: the predicted accuracy of each ground position (sigma x, y, "
                   "up in m, or CE90 and LE90, by error propagation from --pose-sigma or --pose-cov, --pixel-sigma "
                   "and --dem-sigma), one pixel per --accuracy-step x --accuracy-step ortho pixels; frame images "
                   "and --dimap scenes.")
@click.option("--pose-sigma", default=_FRAME_POSE_SIGMA, show_default=True,
              metavar="SX,SY,SZ,SA,SB,SC",
              help="With --accuracy: the poses' standard deviations: x, y, z (or east, north, up for GNSS/INS "
                   "poses) in m, omega, phi, kappa (or roll, pitch, yaw) in deg; GNSS/INS poses may add the "
                   "boresight angles (deg), then the lever arm (m): 9 or 12 numbers. For a --dimap scene eight "
                   "numbers (default 10,10,5,0.001,0.001,0.001,0.001,0.001): the orbit across, along the track and "
                   "radially (m), roll, pitch, yaw and the look angles psi_x, psi_y (deg).")
@click.option("--pose-cov", "pose_cov_file", type=click.Path(dir_okay=False),
              help="With --accuracy: each image's pose covariance from 'orthowarp adjust' (its pose_cov.json, "
                   "the exterior file's parameters), instead of --pose-sigma.")
@click.option("--accuracy-measure", type=click.Choice(["sigma", "ce90"]), default="sigma", show_default=True,
              help="With --accuracy: three bands sigma x, y (in the output CRS's units: m, or deg where it is "
                   "longitude/latitude) and up (m), or two bands CE90 (the radius holding 90 % of the horizontal "
                   "error) and LE90 (m); each band's description says which. Ground that faces away from the image "
                   "(hidden by its own slope) is NaN.")
@click.option("--accuracy-step", type=click.IntRange(1, 4096), default=16, show_default=True,
              help="With --accuracy: ortho pixels per accuracy pixel, each way (1: full resolution).")
@click.option("--pixel-sigma", type=float, default=0.5, show_default=True,
              help="With --accuracy: standard deviation of an image position (px).")
@click.option("--dem-sigma", type=float, default=0.5, show_default=True,
              help="With --accuracy: standard deviation of the DEM's heights (m).")
@click.option("--profile", "show_profile", is_flag=True,
              help="Print on stderr, per image and in total: seconds per stage (summed over threads and "
                   "wall-clock), the device busy fraction, what bounds the run, and the start-up time.")
@click.option("--profile-json", type=click.Path(dir_okay=False),
              help="Write the same profile as JSON to this file.")
@click.pass_context
def ortho(ctx, images, odm_dataset, int_param, ext_param, dimap, attitude_model, dem, height, crs, resolution, resampling, method,
          driver, compress, compress_level, quality, block_codec, source_reads, creation, dtype,
          out_dir, overwrite, no_refraction, geoid, same_vertical_datum, device, tile_size, export_params, accuracy,
          pose_sigma, pose_cov_file, accuracy_measure, accuracy_step,
          pixel_sigma, dem_sigma, show_profile, profile_json):
    """Orthorectify frame IMAGES, or one pushbroom scene (--dimap), into (cloud-optimized)
    GeoTIFFs named <image>_ORTHO.tif."""
    import os

    t_command = time.perf_counter()
    _spare_final_collection()
    from .errors import ParamError, RasterIOError
    from .pipeline.dem import Dem
    from .pipeline.io import check_destination, outputs_together
    from .pipeline.ortho import orthorectify

    t_imported = time.perf_counter()

    if odm_dataset is not None:
        images, int_param, ext_param, dem = _odm_dataset(odm_dataset, images, int_param, ext_param, dem, height)
    if not images:
        if dimap is not None:
            raise ParamError(f"--dimap '{dimap}' describes a scene: give its image as IMAGES")
        raise ParamError("Give IMAGES (or --odm-dataset DIR)")
    if export_params:
        if dimap or not ext_param:
            raise ParamError("--export-params writes frame images' orientations: give --ext-param (not --dimap)")
        from .pipeline.formats import export_params as export

        ids = {}
        jobs = _frame_orientations(images, int_param, ext_param, crs, ids)
        for path in export(jobs, out_dir, camera_ids=ids, overwrite=overwrite):
            if not ctx.obj["quiet"]:
                click.echo(path)
        return
    sigmas = covs = cov_names = None
    if pose_cov_file is not None:
        from .pipeline.adjust_report import POSE_COV_PARAMETERS, read_pose_covariances

        if ctx.get_parameter_source("pose_sigma") not in (None, click.core.ParameterSource.DEFAULT,
                                                           click.core.ParameterSource.DEFAULT_MAP):
            raise ParamError("Give --pose-sigma or --pose-cov, not both: --pose-cov replaces the sigmas")

        covs, cov_names = read_pose_covariances(pose_cov_file)
    if accuracy:
        if dimap and pose_sigma == _FRAME_POSE_SIGMA:
            pose_sigma = _SCENE_SIGMA
        sigmas = _sigma_list(pose_sigma, 8, "--pose-sigma", "m, m, m, deg x 5 for a --dimap scene") if dimap \
            else _sigma_list(pose_sigma, (6, 9, 12), "--pose-sigma", "m, m, m, deg, deg, deg; GNSS/INS poses: "
                             "then boresight deg x 3, lever arm m x 3")
        _check_measurement_sigmas(pixel_sigma, dem_sigma)
    if pose_cov_file is not None and (not accuracy or dimap):
        raise ParamError("--pose-cov goes with --accuracy for frame images")
    if (dem is None) == (height is None):
        raise ParamError("Give exactly one of --dem FILE and --height METRES")
    compress, compress_level, quality, creation_options = _creation_args(creation, compress, compress_level, quality)
    if show_profile or profile_json:
        from .pipeline.profile import format_profile
    quiet = ctx.obj["quiet"]
    options = dict(crs=crs, resolution=resolution, resampling=resampling, method=method,
                   refraction=not no_refraction, dtype=dtype, driver="COG" if driver.lower() == "cog" else "GTiff",
                   compress=compress, compress_level=compress_level, quality=quality, block_codec=block_codec,
                   source_reads=source_reads, creation_options=creation_options, overwrite=overwrite,
                   device=device,
                   tile_size=tile_size, geoid=geoid, same_vertical_datum=same_vertical_datum)

    def run(jobs):
        """Check every destination, then read the terrain and write the orthos, two at a time:
        the next image's set-up and first tiles overlap the finishing of the one before (its
        last tiles, overview tail and file assembly), so the device is not left idle between
        images. Results are reported in order; after a failure the image in flight is
        cancelled (nothing of it is written) and the first error is raised."""
        import collections
        import threading
        from concurrent.futures import ThreadPoolExecutor

        from .errors import Cancelled

        stop, failed = ctx.meta.get("orthowarp.stop"), threading.Event()
        options["cancel"] = _Either(stop, failed)
        # one bar for the batch (the tiles of every image, as each starts), on a terminal only
        from tqdm import tqdm

        options["progress"] = tqdm(total=0, unit="tile", leave=False, disable=quiet or not sys.stderr.isatty())
        for *_, dst in jobs:
            check_destination(dst, overwrite=overwrite)
            if accuracy:
                check_destination(_accuracy_name(dst), overwrite=overwrite)
        if accuracy and not dimap:  # every image's pose covariance, before anything is written
            from .adjust.precision import pose_inputs

            for image, sensor, _ in jobs:
                if covs is None:
                    pose_inputs(sensor.pose, len(sigmas))
                    continue
                want = POSE_COV_PARAMETERS["map" if sensor.pose.mode == "map" else "geocentric"]
                if cov_names != want:
                    raise ParamError(f"'{pose_cov_file}' gives covariances of {cov_names}; the pose of "
                                     f"'{image}' takes {want}")
                if _image_key(image) not in covs:
                    raise ParamError(f"Image '{image}' has no pose covariance in '{pose_cov_file}'")
        terrain = Dem.from_file(dem) if dem is not None else height
        profiles = []

        def one(job):
            image, sensor, dst = job
            with outputs_together(overwrite=overwrite):  # the ortho and its accuracy raster, or neither
                r = orthorectify(image, sensor, dst, dem=terrain, **options)
                if accuracy:
                    pose_cov = np.diag(sigmas) ** 2 if covs is None else covs[_image_key(image)]
                    from .pipeline.precision import accuracy_raster

                    if sensor.kind == "pushbroom":
                        from .pipeline.precision import scene_accuracy_raster

                        scene_accuracy_raster(_accuracy_name(dst), sensor, terrain, r.crs, r.transform, r.shape,
                                              orientation_cov=np.diag(sigmas) ** 2, pixel_sigma=pixel_sigma,
                                              dem_sigma=dem_sigma, measure=accuracy_measure, step=accuracy_step,
                                              refraction=not no_refraction, device=device)
                    else:
                        accuracy_raster(_accuracy_name(dst), sensor.camera, sensor.pose, terrain, r.crs, r.transform, r.shape,
                                        pose_cov=pose_cov, pixel_sigma=pixel_sigma, dem_sigma=dem_sigma,
                                        measure=accuracy_measure, step=accuracy_step, refraction=not no_refraction,
                                        geoid=geoid,
                                        same_vertical_datum=same_vertical_datum, device=device)
            return dst, r

        def report(dst, r):
            if not quiet:
                click.echo(f"{dst}: {r.shape[1]} x {r.shape[0]} px at {r.resolution:.4g} ({_crs_label(r.crs)}), "
                           f"{r.timings['wall']:.2f} s")
            profiles.append((dst, r.profile))
            if show_profile:
                click.echo(format_profile(r.profile, dst), err=True)

        pending, error = collections.deque(), None

        def collect(future):
            nonlocal error
            try:
                report(*future.result())
            except Cancelled as e:  # a stop, or the image in flight when another failed
                error = error or e
            except BaseException as e:  # noqa: BLE001 - raised below, after the image in flight stops
                failed.set()
                error = e if error is None or isinstance(error, Cancelled) else error

        t_first = time.perf_counter()
        with options["progress"], ThreadPoolExecutor(max_workers=min(2, len(jobs)),
                                                     thread_name_prefix="image") as pool:
            for job in jobs:
                if error is not None:
                    break
                pending.append(pool.submit(one, job))
                if len(pending) == 2:
                    collect(pending.popleft())
            while pending:
                collect(pending.popleft())
        if error is not None:
            raise error
        if show_profile or profile_json:
            _report_profile(profiles, time.perf_counter() - t_first, (t_command, t_imported, t_first),
                            show=show_profile, path=profile_json)

    if dimap is not None:
        from .pipeline.dimap import read_scene

        if int_param or ext_param:
            raise ParamError("--dimap replaces --int-param and --ext-param: give one or the other")
        if len(images) != 1:
            raise ParamError(f"--dimap describes one scene: give its one image, not {len(images)}")
        if not os.path.exists(images[0]):
            raise RasterIOError(f"Image '{images[0]}' does not exist")
        scene = read_scene(dimap, attitude_model=attitude_model)
        key = _image_key(images[0])
        run([(images[0], scene, os.path.join(out_dir, f"{key}_ORTHO.tif"))])
        return
    if not ext_param:
        raise ParamError("Give --ext-param (frame images) or --dimap (a pushbroom scene)")
    jobs, seen = [], {}
    for image, camera, pose in _frame_orientations(images, int_param, ext_param, crs):
        key = _image_key(image)
        dst = os.path.join(out_dir, f"{key}_ORTHO.tif")
        if dst in seen:
            raise ParamError(f"Images '{seen[dst]}' and '{image}' would both be written to '{dst}'")
        seen[dst] = image
        jobs.append((image, FrameSensor(camera, pose), dst))
    run(jobs)


class _Either:
    """Set when any of the events is (the ``cancel`` the library polls with ``is_set()``)."""

    def __init__(self, *events):
        self.events = [e for e in events if e is not None]

    def is_set(self):
        return any(e.is_set() for e in self.events)


def _match_control(block, pixels, sensors, terrain, control_csv, reference, sigma, out_path, *, overwrite, quiet,
                   **kw):
    """``orthowarp match --control``: the block with the control points matched against the
    reference's chips; without a reference the block as it is, and the points' predicted
    image positions written to <OUT>_control.csv."""
    import rasterio
    from pyproj import CRS

    from .errors import ParamError, RasterIOError
    from .pipeline.blockio import read_ground_points_csv
    from .pipeline.io import check_destination, write_text
    from .pipeline.matching import control_observations

    gcps = read_ground_points_csv(control_csv, sigma=sigma)
    if not gcps:
        raise ParamError(f"Control points file '{control_csv}' holds no point")
    geo = block.mode == "geocentric"
    xyz = np.array([g["xyz"] for g in gcps], dtype=np.float64)  # the block's form: lat, lon, h if geocentric
    pts = xyz[:, [1, 0, 2]] if geo else xyz  # the sensors' frame: lon, lat, h or x, y, z
    ref = None
    if reference is not None:
        try:
            with rasterio.open(reference) as ds:
                if ds.crs is None:
                    raise ParamError(f"Reference '{reference}' has no CRS")
                ref = (ds.read(1).astype(np.float32), ds.transform, CRS.from_wkt(ds.crs.to_wkt()))
        except rasterio.errors.RasterioIOError as e:
            raise RasterIOError(f"Could not read reference '{reference}': {e}") from e
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


def _image_key(image):
    """An image's name in orientation files: its file name without the extension."""
    return os.path.splitext(os.path.basename(image))[0]


def _accuracy_name(dst):
    """<image>_ACCURACY.tif beside <image>_ORTHO.tif."""
    base = dst[:-len("_ORTHO.tif")] if dst.endswith("_ORTHO.tif") else os.path.splitext(dst)[0]
    return base + "_ACCURACY.tif"


_SIGMA_BOUNDS = {"m": 1e6, "deg": 180.0}  # the largest standard deviation a pose's input may take


def _sigma_list(text, n, option, units):
    """``n`` (an int, or a tuple of the counts allowed) comma-separated standard deviations
    (finite, >= 0: 0 leaves that input out, and at most 1e6 m or 180 deg) of a CLI option:
    m, m, m, then deg (a scene's eight numbers; a frame pose's six, then boresight deg x 3,
    lever arm m x 3)."""
    from .errors import ParamError

    counts = (n,) if isinstance(n, int) else tuple(n)
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in counts or not all(np.isfinite(v) and v >= 0 for v in values):
        raise ParamError(f"{option} must be {' or '.join(map(str, counts))} numbers >= 0 ({units}), got {text!r}")
    kinds = ["m"] * 3 + ["deg"] * 5 if counts == (8,) else ["m"] * 3 + ["deg"] * 6 + ["m"] * 3
    for k, (v, unit) in enumerate(zip(values, kinds)):
        if v > _SIGMA_BOUNDS[unit]:
            raise ParamError(f"{option}: number {k + 1}, {text.split(',')[k].strip()} {unit}, is beyond "
                             f"{_SIGMA_BOUNDS[unit]:g} {unit} (no pose is that uncertain: check the units, {units})")
    return values


def _check_measurement_sigmas(pixel_sigma, dem_sigma):
    from .errors import ParamError

    if not (np.isfinite(pixel_sigma) and pixel_sigma >= 0 and np.isfinite(dem_sigma) and dem_sigma >= 0):
        raise ParamError("--pixel-sigma and --dem-sigma must be >= 0")


_COMPRESS_NAMES = {"deflate", "zstd", "lzw", "jpeg", "webp", "none"}


def _creation_args(values, compress, compress_level, quality):
    """``-co KEY=VALUE`` options: COMPRESS, LEVEL/ZLEVEL/ZSTD_LEVEL, QUALITY/JPEG_QUALITY and
    PREDICTOR (YES/2/STANDARD only) taken into the matching options, the rest returned as the
    writer's creation options (checked by orthorectify)."""
    from .errors import ParamError

    rest = {}
    for item in values:
        key, sep, value = item.partition("=")
        key, value = key.strip().upper(), value.strip()
        if not sep or not key or not value:
            raise ParamError(f"-co takes KEY=VALUE, got {item!r}")
        if key == "COMPRESS":
            if value.lower() not in _COMPRESS_NAMES:
                raise ParamError(f"-co COMPRESS must be one of {sorted(n.upper() for n in _COMPRESS_NAMES)}, got {value!r}")
            compress = value.lower()
        elif key in ("LEVEL", "ZLEVEL", "ZSTD_LEVEL"):
            try:
                compress_level = int(value)
            except ValueError:
                raise ParamError(f"-co {key} must be an integer, got {value!r}") from None
        elif key in ("QUALITY", "JPEG_QUALITY", "WEBP_LEVEL"):
            try:
                quality = int(value)
            except ValueError:
                raise ParamError(f"-co {key} must be an integer, got {value!r}") from None
        elif key == "PREDICTOR":
            if value.upper() not in ("YES", "2", "STANDARD"):
                raise ParamError(f"-co PREDICTOR={value}: orthowarp writes horizontal differencing (PREDICTOR=2) for "
                                 "integer data with deflate, zstd and lzw, and no other predictor")
        else:
            rest[key] = value
    return compress, compress_level, quality, rest


def _odm_dataset(folder, images, int_param, ext_param, dem, height):
    """(images, int_param, ext_param, dem) from an OpenDroneMap dataset folder: what the caller
    gave, else the folder's opensfm/reconstruction.json, odm_dem/dsm.tif and images/."""
    from .errors import ParamError

    if not os.path.isdir(folder):
        raise ParamError(f"--odm-dataset '{folder}' is not a folder")
    recon = os.path.join(folder, "opensfm", "reconstruction.json")
    if (int_param is None or ext_param is None) and not os.path.isfile(recon):
        raise ParamError(f"--odm-dataset '{folder}' has no opensfm/reconstruction.json")
    int_param, ext_param = int_param or recon, ext_param or recon
    if dem is None and height is None:
        dem = os.path.join(folder, "odm_dem", "dsm.tif")
        if not os.path.isfile(dem):
            raise ParamError(f"--odm-dataset '{folder}' has no odm_dem/dsm.tif: give --dem or --height")
    if not images:
        folder_images = os.path.join(folder, "images")
        images = sorted(os.path.join(folder_images, f) for f in os.listdir(folder_images)
                        if os.path.splitext(f)[1].lower() in (".tif", ".tiff", ".jpg", ".jpeg", ".png")) \
            if os.path.isdir(folder_images) else []
        if not images:
            raise ParamError(f"--odm-dataset '{folder}' has no images in images/: give IMAGES")
    return images, int_param, ext_param, dem


def _expand_globs(images):
    """IMAGES with wildcards (``*``, ``?``, ``[...]``) the shell left unexpanded (quoted, or a
    shell that does not expand them) expanded, sorted; a pattern matching nothing is an error."""
    import glob

    from .errors import RasterIOError

    out = []
    for image in images:
        if glob.has_magic(image) and not os.path.exists(image):
            found = sorted(glob.glob(image))
            if not found:
                raise RasterIOError(f"No image matches '{image}'")
            out += found
        else:
            out.append(image)
    return out


def _image_crs(images):
    """The CRS of the first image that has one (a georeferenced frame), else None."""
    import rasterio

    for image in images:
        try:
            with rasterio.open(image) as ds:
                if ds.crs is not None:
                    return ds.crs.to_wkt()
        except rasterio.errors.RasterioIOError:
            continue
    return None


def _crs_label(crs):
    """A CRS's name and its horizontal unit for a summary line ("WGS 84 / UTM zone 32N, metre");
    where it has no name ("unknown", "unnamed"), its EPSG code or else its PROJ string."""
    name = crs.name
    if not name or name.lower() in ("unknown", "unnamed"):
        code = crs.to_epsg()
        if code is not None:
            name = f"EPSG:{code}"
        else:
            with warnings.catch_warnings():  # pyproj: a PROJ string may lose a WKT's details (here: a label)
                warnings.simplefilter("ignore")
                name = crs.to_proj4()
    unit = crs.axis_info[0].unit_name if crs.axis_info else None
    return f"{name}, {unit}" if unit else name


def _frame_orientations(images, int_param, ext_param, crs, ids=None):
    """[(image, FrameCamera, Pose)] of frame images from the camera and exterior files."""
    from .errors import CrsError, ParamError, RasterIOError
    from .pipeline.formats import read_cameras, read_exterior

    images = _expand_globs(images)
    try:  # the poses in their file's own CRS (a .prj beside a CSV, a GeoJSON's, ...)
        exterior = read_exterior(ext_param)
    except CrsError:
        # a file of map positions that names no CRS: --crs, else the first image's own CRS
        pose_crs = crs if crs is not None else _image_crs(images)
        if pose_crs is None:
            raise
        exterior = read_exterior(ext_param, crs=pose_crs)
    cameras = read_cameras(int_param) if int_param else read_cameras(ext_param)
    out = []
    for image in images:
        if not os.path.exists(image):
            raise RasterIOError(f"Image '{image}' does not exist")
        key = _image_key(image)
        if key not in exterior:
            raise ParamError(f"Image '{image}' is not in the exterior orientation file '{ext_param}'")
        orient = exterior[key]
        cam_id = orient.camera_id
        if cam_id is None:
            if len(cameras) != 1:
                raise ParamError(f"'{ext_param}' names no camera for '{key}' and '{int_param}' holds "
                                 f"{len(cameras)} cameras: add a camera column")
            cam_id = next(iter(cameras))
        if cam_id not in cameras:
            raise ParamError(f"Camera '{cam_id}' of image '{key}' is not in '{int_param or ext_param}'")
        out.append((image, cameras[cam_id], orient.pose))
        if ids is not None:
            ids[id(cameras[cam_id])] = cam_id
    return out


@main.command()
@click.argument("images", nargs=-1, type=click.Path(dir_okay=False))
@click.option("--int-param", type=click.Path(dir_okay=False), help="Camera file (orthority/ODM YAML or JSON, OpenSfM).")
@click.option("--ext-param", type=click.Path(dir_okay=False),
              help="Exterior orientation of the frame IMAGES (CSV, orthority GeoJSON, OpenSfM reconstruction.json).")
@click.option("--odm-dataset", type=click.Path(file_okay=False),
              help="An OpenDroneMap dataset folder (as for ortho): its reconstruction.json, odm_dem/dsm.tif and, "
                   "without IMAGES, its images/.")
@click.option("--scene", "scenes", nargs=2, multiple=True, type=(click.Path(dir_okay=False), click.Path(dir_okay=False)),
              metavar="IMAGE DIMAP", help="A pushbroom scene: its image and its SPOT level-1A DIMAP metadata "
                                          "(repeatable; numbered after IMAGES in the index).")
@click.option("--attitude-model", type=click.Choice(["full", "first_order"]), default=None,
              help="Attitude matrix of the pushbroom scenes: full (the default for DIMAP) or first_order (the "
                   "linearised form); a scene JSON from 'orthowarp spot-adjust' keeps its own.")
@click.option("--dem", type=click.Path(dir_okay=False), help="DEM/DSM file.")
@click.option("--height", type=float, help="Constant ellipsoidal height (m) instead of a DEM.")
@click.option("--out", "out_path", type=click.Path(dir_okay=False), required=True, help="The mosaic (COG).")
@click.option("--index", "index_path", type=click.Path(dir_okay=False),
              help="Also write the per-pixel source index (uint16 COG: the image's position in IMAGES).")
@click.option("--crs", default=None, help="Output CRS (default: that of the first image's ortho); also the CRS of "
                                         "x,y,z poses in a file that names none (as for ortho).")
@click.option("--resolution", type=float,
              help="Pixel size in CRS units (default: the images' mean GSD in those units, with the CRS's scale).")
@click.option("--resampling", type=click.Choice(["nearest", "bilinear", "bicubic", "lanczos"]), default="bilinear",
              show_default=True)
@click.option("--seamlines", "seamlines_path", type=click.Path(dir_okay=False),
              help="Also write each image's part of the mosaic as GeoJSON polygons (longitude/latitude).")
@click.option("--seams", type=click.Choice(["least-cost", "nadir"]), default="least-cost", show_default=True,
              help="Seams where the images agree (moved from the most-nadir seams around buildings, trees, "
                   "moving objects), or the most-nadir seams.")
@click.option("--seam-width", type=float, default=256.0, show_default=True,
              help="How far a least-cost seam may move from the most-nadir seam, output pixels.")
@click.option("--blend", type=click.Choice(["feather", "multiband", "none"]), default="feather", show_default=True,
              help="Feather across seams (and towards image borders), blend by frequency bands (fine detail "
                   "sharp, brightness over the feather width), or take each pixel from one image.")
@click.option("--feather", type=float, default=32.0, show_default=True, help="Width of the blend, output pixels.")
@click.option("--no-balance", is_flag=True, help="No radiometric balancing (gain and offset per image and band).")
@click.option("--no-occlusion", is_flag=True,
              help="Project by the backward method (faster; ground hidden from an image is filled with what hides it).")
@click.option("--reference", type=int, default=None,
              help="Balancing keeps this image's radiometry (its position in IMAGES, from 0); default: the mean.")
@click.option("--compress-level", type=int, default=None, help="Deflate level 1-12 (default 6).")
@click.option("--block-codec", type=click.Choice(["auto", "host", "nvcomp", "hybrid", "warp"]), default="auto", show_default=True,
              help="Who deflates the mosaic's blocks: host (libdeflate on all cores), nvcomp (the tiles stay on the "
                   "GPU; needs orthowarp[gpu]), warp (orthowarp's own deflate kernels on the device), hybrid (the device: "
                   "nvCOMP at --compress-level 1-4 where installed, else warp; and the host cores at once); "
                   "auto: warp on a GPU, host on the CPU.")
@click.option("--accuracy", is_flag=True,
              help="Also write <mosaic>_ACCURACY.tif: the predicted accuracy (sigma x, y in the CRS's units and up "
                   "in m, or CE90 and LE90 in m) of each --accuracy-step x --accuracy-step cell from the image its centre was taken from "
                   "(needs --index).")
@click.option("--pose-sigma", default=_FRAME_POSE_SIGMA, show_default=True, metavar="SX,SY,SZ,SA,SB,SC",
              help="With --accuracy: frame images' pose standard deviations (m, m, m, deg, deg, deg; GNSS/INS poses "
                   "also 9 or 12 numbers with the boresight and the lever arm; as for ortho).")
@click.option("--accuracy-measure", type=click.Choice(["sigma", "ce90"]), default="sigma", show_default=True,
              help="With --accuracy: sigma x, y, up, or CE90 and LE90 (as for ortho).")
@click.option("--accuracy-step", type=click.IntRange(1, 4096), default=16, show_default=True,
              help="With --accuracy: mosaic pixels per accuracy pixel, each way (1: full resolution).")
@click.option("--scene-sigma", default=_SCENE_SIGMA, show_default=True, metavar="8 NUMBERS",
              help="With --accuracy: pushbroom scenes' orientation standard deviations (orbit across, along, radial "
                   "in m; roll, pitch, yaw, psi_x, psi_y in deg).")
@click.option("--pixel-sigma", type=float, default=0.5, show_default=True,
              help="With --accuracy: standard deviation of an image position (px).")
@click.option("--dem-sigma", type=float, default=0.5, show_default=True,
              help="With --accuracy: standard deviation of the DEM's heights (m).")
@click.option("-co", "--co", "creation", multiple=True, metavar="KEY=VALUE",
              help="GDAL-style creation option of the mosaic (and index) file, repeatable: BLOCKSIZE, BIGTIFF, "
                   "NUM_THREADS as for ortho; LEVEL (ZLEVEL) sets --compress-level; the mosaic is deflate with "
                   "PREDICTOR=2.")
@click.option("--dtype", type=click.Choice(["uint8", "uint16", "float32"]), help="Output data type (default: the sources').")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@click.option("--no-refraction", is_flag=True, help="Do not correct atmospheric refraction.")
@click.option("--geoid", type=click.Path(dir_okay=False), help="Geoid grid for converting between DEM and position heights.")
@click.option("--same-vertical-datum", is_flag=True, help="Take DEM and position heights as the same vertical datum.")
@click.option("--device", default=None, help="Warp device (cpu, cuda, cuda:N); default: first GPU, else CPU.")
@click.option("--workers", type=int, default=None,
              help="Tiles in flight (default: CPU cores on the CPU, 8 on a GPU); with --processes, per process (default 2).")
@click.option("--processes", type=click.IntRange(min=1), default=None,
              help="Worker processes computing the tiles on the same device (default: 4 on a GPU, 1 on the CPU, "
                   "where 1 is threads of this process).")
@click.option("--tile-size", type=int, default=None, help="Output tile edge, pixels (default: 2048 on a GPU, 512 on the CPU).")
@click.option("--profile", "show_profile", is_flag=True,
              help="Print where the time went: the plan's steps, per-stage times, GPU busy fraction, what bounds it.")
@click.option("--profile-json", type=click.Path(dir_okay=False), help="Write the same profile as JSON to this file.")
@click.pass_context
def mosaic(ctx, images, int_param, ext_param, odm_dataset, scenes, attitude_model, dem, height, out_path, index_path, seamlines_path, crs, resolution,
           resampling, seams, seam_width, blend, feather, no_balance, no_occlusion, reference, compress_level, block_codec, accuracy,
           pose_sigma, accuracy_measure, accuracy_step, scene_sigma, pixel_sigma, dem_sigma, creation, dtype, overwrite, no_refraction, geoid,
           same_vertical_datum, device, workers, processes, tile_size, show_profile, profile_json):
    """Mosaic frame IMAGES and pushbroom scenes (--scene) into one cloud-optimized GeoTIFF: each
    pixel from the image that sees its ground most nearly from above (smallest off-nadir
    angle), the seams moved to where the images agree, feathered across the seams, the images'
    radiometry balanced by gains and offsets from their overlaps."""
    from .errors import ParamError, RasterIOError
    from .pipeline.dem import Dem
    from .pipeline.io import check_destination, outputs_together
    from .pipeline.mosaic import mosaic as make_mosaic

    if odm_dataset is not None:
        images, int_param, ext_param, dem = _odm_dataset(odm_dataset, images, int_param, ext_param, dem, height)
    if (dem is None) == (height is None):
        raise ParamError("Give exactly one of --dem FILE and --height METRES")
    if not images and not scenes:
        raise ParamError("Give frame IMAGES (with --ext-param) or pushbroom scenes (--scene IMAGE DIMAP)")
    if images and not ext_param:
        raise ParamError("Frame IMAGES need --ext-param (their exterior orientation)")
    compress, compress_level, quality, creation_options = _creation_args(creation, "deflate", compress_level, None)
    if compress != "deflate" or quality is not None:
        raise ParamError("the mosaic is written with deflate: -co COMPRESS and QUALITY do not apply")
    if accuracy:
        if not index_path:
            raise ParamError("--accuracy takes each cell's image from the index: give --index too")
        frame_sigmas = _sigma_list(pose_sigma, (6, 9, 12), "--pose-sigma", "m, m, m, deg, deg, deg; GNSS/INS "
                                   "poses: then boresight deg x 3, lever arm m x 3")
        scene_sigmas = _sigma_list(scene_sigma, 8, "--scene-sigma", "m, m, m, deg x 5")
        _check_measurement_sigmas(pixel_sigma, dem_sigma)
        check_destination(_accuracy_name(out_path), overwrite=overwrite)
    jobs = [(image, FrameSensor(camera, pose))
            for image, camera, pose in (_frame_orientations(images, int_param, ext_param, crs) if images else [])]
    if scenes:
        from .pipeline.dimap import read_scene

        for image, dimap in scenes:
            if not os.path.exists(image):
                raise RasterIOError(f"Image '{image}' does not exist")
            jobs.append((image, read_scene(dimap, attitude_model=attitude_model)))
    if accuracy:  # every frame's pose takes that many sigmas, before anything is written
        from .adjust.precision import pose_inputs

        for _, sensor in jobs:
            if sensor.kind != "pushbroom":
                pose_inputs(sensor.pose, len(frame_sigmas))
    terrain = Dem.from_file(dem) if dem is not None else height
    if processes is None:  # a GPU mosaic is bound by the host work per tile: several processes feed it
        from ._device import resolve_device

        processes = MOSAIC_GPU_PROCESSES if resolve_device(device).is_cuda else 1
    with outputs_together(overwrite=overwrite):  # the mosaic, its sidecars and accuracy raster, or none
        r = make_mosaic(jobs, out_path, dem=terrain, crs=crs, resolution=resolution, resampling=resampling,
                        refraction=not no_refraction, dtype=dtype, index=index_path, seamlines=seamlines_path,
                        seams=seams, seam_width=seam_width, blend=blend, feather=feather,
                        balance=not no_balance, reference=reference, occlusion=not no_occlusion,
                        compress_level=compress_level, block_codec=block_codec, creation_options=creation_options,
                        overwrite=overwrite, device=device, geoid=geoid, same_vertical_datum=same_vertical_datum,
                        workers=workers, processes=processes, tile_size=tile_size, cancel=ctx.meta.get("orthowarp.stop"))
        if accuracy:
            from .pipeline.precision import mosaic_accuracy_raster

            mosaic_accuracy_raster(_accuracy_name(r.path), jobs, r.index, terrain, r.crs, r.transform, r.shape,
                                   pose_cov=np.diag(frame_sigmas) ** 2, orientation_cov=np.diag(scene_sigmas) ** 2,
                                   pixel_sigma=pixel_sigma, dem_sigma=dem_sigma, measure=accuracy_measure,
                                   step=accuracy_step, refraction=not no_refraction, geoid=geoid, same_vertical_datum=same_vertical_datum,
                                   device=device)
    if show_profile or profile_json:
        from .pipeline.io import write_json
        from .pipeline.profile import format_profile

        steps = ", ".join(f"{k} {v:.3f} s" for k, v in r.setup_s.items() if k != "total")
        if show_profile:
            click.echo(f"plan: {r.setup_s.get('total', 0.0):.3f} s ({steps})", err=True)
            click.echo(format_profile(r.profile, f"{r.path} (tiles and writing)"), err=True)
        if profile_json:
            write_json(profile_json, dict(plan_s=r.setup_s, tiles=r.profile, wall_s=r.wall_s,
                                          output_pixels=int(r.shape[0]) * int(r.shape[1]),
                                          shape=list(r.shape), resolution=r.resolution, image_builds=r.image_builds,
                                          images_held_peak=r.images_held_peak, images=len(jobs)))
    if not ctx.obj["quiet"]:
        counts = ", ".join(f"{os.path.basename(img)} {n}" for (img, *_), n in zip(jobs, r.pixels_per_image))
        click.echo(f"{r.path}: {r.shape[1]} x {r.shape[0]} px at {r.resolution:.4g} ({_crs_label(r.crs)}); pixels per "
                   f"image: {counts}")


_SPARED = []


def _spare_final_collection():
    """At the process's exit, freeze the objects then alive (``gc.freeze``), so that the
    interpreter's final garbage collections do not traverse the tens of thousands of objects
    Warp, its kernels and the pipeline's modules hold: that saves ~0.25 s at the end of every
    ``orthowarp ortho`` on the 2-core machine. Runs after the command (outputs published,
    datasets closed), as an atexit handler, so in-process callers (tests) are unaffected until
    they exit too. Cyclic garbage left at exit is then reclaimed by the OS, not finalised."""
    if not _SPARED:
        import atexit
        import gc

        atexit.register(gc.freeze)
        _SPARED.append(True)


def _report_profile(profiles, batch_wall, marks, *, show, path):
    """The ortho command's profile: the batch total (several images) and the start-up, on stderr
    (``show``) and as JSON (``path``). ``marks``: perf_counter() readings at the command's
    start, after its imports, and at the first image's call."""
    from .pipeline.io import write_json
    from .pipeline.profile import format_profile, merge_profiles, process_start

    t_command, t_imported, t_first = marks
    first = profiles[0][1]
    p0 = process_start()
    setup = first["first_kernel_s"]
    startup = dict(
        # process start -> the first tile's first kernel launch of the first image
        startup_s=(t_first - p0 + setup) if p0 is not None and setup is not None else None,
        to_command_s=(t_command - p0) if p0 is not None else None,  # interpreter, CLI and Warp imports
        job_imports_s=t_imported - t_command,  # the pipeline's modules
        inputs_s=t_first - t_imported,  # orientation files, DEM, destinations
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
                       f"orientation files and DEM, {startup['image_setup_s']:.3f} s image set-up (Warp "
                       f"initialisation, geometry, output grid, kernel modules, first tile)", err=True)
    if path:
        write_json(path, dict(images=[dict(path=dst, profile=p) for dst, p in profiles], total=total,
                              startup=startup))


@main.command()
@click.argument("block_file", required=False, type=click.Path(dir_okay=False))
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Output folder.")
@click.option("--write-example", is_flag=True,
              help="First write a synthetic example block (3 strips of 8 images, control at the corners and "
                   "centre, 0.5 px image noise) to BLOCK_FILE, which must not exist, then adjust it.")
@click.option("--cameras", type=click.Path(dir_okay=False),
              help="Instead of BLOCK_FILE: cameras (orthority/ODM camera file) ...")
@click.option("--exterior", type=click.Path(dir_okay=False),
              help="... initial exterior orientation (CSV + .prj, GeoJSON, reconstruction.json) ...")
@click.option("--image-points", type=click.Path(dir_okay=False), help="... image points CSV (image,point,col,row[,sigma]) ...")
@click.option("--ground-points", type=click.Path(dir_okay=False),
              help="... and ground points CSV (point,x,y,z[,sx,sy,sz][,role]).")
@click.option("--fix-control", is_flag=True, help="Hold control points fixed instead of weighting them.")
@click.option("--no-gnss", is_flag=True, help="Ignore the images' GNSS positions.")
@click.option("--no-ins", is_flag=True, help="Ignore the images' INS attitudes.")
@click.option("--snooping", is_flag=True, help="Baarda data snooping with iterative rejection.")
@click.option("--robust", type=click.Choice(["huber"]), default=None, help="Robust loss.")
@click.option("--covariance", type=click.Choice(["auto", "full", "poses", "none"]), default="auto", show_default=True)
@click.option("--self-calibration", "self_cal", default=None,
              help="Camera parameters to estimate: 'all' (f,x0,y0,k1,k2,p1,p2) or a comma list of f,x0,y0,k1,k2,k3,p1,p2.")
@click.option("--no-plots", is_flag=True, help="Skip the PNG plots.")
@click.option("--drop-outside-observations", "drop_outside", is_flag=True,
              help="Drop image observations outside their image (logged) instead of refusing the block.")
@click.pass_context
def adjust(ctx, block_file, out_dir, write_example, cameras, exterior, image_points, ground_points, fix_control, no_gnss,
           no_ins, snooping, robust, covariance, self_cal, no_plots, drop_outside):
    """Bundle-adjust the block in BLOCK_FILE (JSON; or from --cameras, --exterior, --image-points
    and --ground-points) and write the refined orientation, points and reports into --out. A run
    that does not converge, or ends singular, writes nothing and exits with status 1. Try it:
    orthowarp adjust block.json --write-example --out adjusted"""
    from .adjust import bundle_adjust
    from .pipeline.blockio import read_block
    from .errors import Cancelled, GeometryError, ParamError
    from .pipeline.adjust_report import write_adjustment

    parts = (cameras, exterior, image_points, ground_points)
    if any(parts):
        if block_file or write_example:
            raise ParamError("Give BLOCK_FILE or --cameras/--exterior/--image-points/--ground-points, not both")
        if not all(parts):
            raise ParamError("A block from files needs all of --cameras, --exterior, --image-points, --ground-points")
        from .pipeline.blockio import block_from_files

        block = block_from_files(cameras, exterior, image_points, ground_points, drop_outside=drop_outside)
        block_file = exterior
    else:
        if not block_file:
            raise ParamError("Give BLOCK_FILE (a block JSON; --write-example writes one) or the four CSV/orientation "
                             "files")
        if write_example:
            from .adjust import synthetic_block
            from .pipeline.blockio import write_block
            from .pipeline.io import check_destination

            check_destination(block_file, overwrite=False)
            write_block(synthetic_block()[0], block_file)
            if not ctx.obj["quiet"]:
                click.echo(f"wrote the example block {block_file}")
        block = read_block(block_file, drop_outside=drop_outside)
    calib = None if not self_cal else (True if self_cal == "all" else tuple(x.strip() for x in self_cal.split(",")))
    result = bundle_adjust(block, fix_control=fix_control, use_gnss=not no_gnss, use_ins=not no_ins,
                           snooping=snooping, robust=robust, covariance=covariance, self_calibration=calib)
    if not result.success:
        raise GeometryError(f"adjustment of '{block_file}' failed (status {result.status}): {result.message}; "
                            f"nothing written to '{out_dir}'")
    if ctx.meta["orthowarp.stop"].is_set():  # stopped by a signal while adjusting: publish nothing
        raise Cancelled(f"adjustment of '{block_file}' cancelled; nothing written to '{out_dir}'")
    paths = write_adjustment(result, block, out_dir, plots=not no_plots)
    if not ctx.obj["quiet"]:
        check = (f"check RMSE (m) {np.array2string(result.check_rmse, precision=4)}"
                 if np.all(np.isfinite(result.check_rmse)) else "no check points")
        click.echo(f"{result.message}; sigma0 {result.sigma0:.4f}, redundancy {result.redundancy}; {check}; outputs: "
                   + ", ".join(os.path.basename(p) for p in paths.values()))



def _eo_sigma(text):
    """--eo-sigma "position=10,attitude=5e-5" -> dict."""
    from .errors import ParamError

    out = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, _, value = part.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            raise ParamError(f"--eo-sigma: {part!r} is not quantity=sigma (position m, velocity m/s, attitude rad)") \
                from None
    return out


@main.command("spot-adjust")
@click.option("--scene", "scenes", multiple=True, nargs=2, metavar="ID FILE",
              help="A scene: its id in the points file and its DIMAP metadata (or scene JSON). Two or more.")
@click.option("--points", "points_file", type=click.Path(dir_okay=False),
              help="Measured points: JSON (orthowarp-scene-points) or CSV (id,role,x,y,z,sx,sy,sz,scene,col,row,sigma).")
@click.option("--points-crs", default="EPSG:4979", show_default=True, help="CRS of a CSV's x, y (z: ellipsoidal).")
@click.option("--pixel-sigma", type=float, default=0.3, show_default=True,
              help="Image sigma (px) of CSV rows that give none.")
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
@click.option("--attitude-model", type=click.Choice(["full", "first_order"]), default=None,
              help="Attitude matrix of DIMAP scenes (default full; a scene JSON keeps its own).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Output folder.")
@click.option("--write-example", type=click.Path(file_okay=False), default=None,
              help="First write a simulated SPOT-like stereo pair with attitude and look-angle errors (two scene "
                   "JSON files and 47 points, 20 of them check points) into this folder, which must not exist, "
                   "then adjust it (--scene and --points are then not given).")
@click.option("--no-plots", is_flag=True, help="Skip the PNG plots.")
@click.pass_context
def spot_adjust(ctx, scenes, points_file, points_crs, pixel_sigma, groups, eo_sigma, look_degree, no_preadjust,
                attitude_model, out_dir, write_example, no_plots):
    """Adjust pushbroom (SPOT-5 level 1A) scenes with ground control: the look angles first
    (EO fixed), then the chosen exterior-orientation groups of all scenes together, with check
    points intersected from the adjusted scenes. Writes the adjusted scenes (for
    'orthowarp ortho --dimap'), the points and reports into --out; a failed adjustment writes
    nothing and exits with status 1. Try it:
    orthowarp spot-adjust --write-example spot-example --out spot-adjusted"""
    from .adjust import adjust_scenes, preadjust_look_angles
    from .errors import Cancelled, GeometryError, ParamError
    from .pipeline.dimap import read_scene
    from .pipeline.scenepoints import read_scene_points, read_scene_points_csv
    from .pipeline.spot_report import write_scene_adjustment

    if write_example:
        if scenes or points_file:
            raise ParamError("--write-example writes its own scenes and points: give neither --scene nor --points")
        scenes, points_file = _write_spot_example(write_example)
        if not ctx.obj["quiet"]:
            click.echo(f"wrote the example stereo pair and points into {write_example}")
    if len(scenes) < 2 or not points_file:
        raise ParamError("Give two or more --scene ID FILE and --points FILE (or --write-example DIR)")
    ids = [s for s, _ in scenes]
    dup = next((s for s in ids if ids.count(s) > 1), None)
    if dup is not None:
        raise ParamError(f"--scene id '{dup}' is given twice")
    models = {sid: read_scene(path, attitude_model=attitude_model) for sid, path in scenes}
    if points_file.lower().endswith(".csv"):
        points = read_scene_points_csv(points_file, crs=points_crs, sigma=pixel_sigma)
    else:
        points = read_scene_points(points_file)
    unknown = [s for s in points.scene_ids if s not in models]
    if unknown:
        raise ParamError(f"'{points_file}' measures points in scene(s) {unknown}, which no --scene gives")
    freed = () if groups.strip().lower() == "none" else tuple(g.strip() for g in groups.split(",") if g.strip())
    priors = _eo_sigma(eo_sigma) if eo_sigma else None
    before = adjust_scenes(models, points, groups=())
    pre = None
    if not no_preadjust and "look" not in freed:
        pre = preadjust_look_angles(models, points, degree=look_degree)
        if not pre.success:
            raise GeometryError(f"look-angle pre-adjustment of '{points_file}' failed: {pre.message}; nothing written "
                                f"to '{out_dir}'")
        models = {**models, **pre.scenes}
    result = adjust_scenes(models, points, groups=freed, eo_sigma=priors, look_degree=look_degree)
    if not result.success:
        raise GeometryError(f"adjustment of '{points_file}' failed (status {result.status}): {result.message}; "
                            f"nothing written to '{out_dir}'")
    if ctx.meta["orthowarp.stop"].is_set():
        raise Cancelled(f"adjustment of '{points_file}' cancelled; nothing written to '{out_dir}'")
    paths = write_scene_adjustment(result, points, out_dir, preadjustment=pre, before=before, plots=not no_plots)
    if not ctx.obj["quiet"]:
        click.echo(f"{result.message}; check RMSE east/north/up (m) {np.array2string(result.check_rmse, precision=3)} "
                   f"(uncorrected {np.array2string(before.check_rmse, precision=3)}); outputs: "
                   + ", ".join(os.path.basename(p) for p in paths.values()))


def _write_spot_example(folder):
    """A simulated stereo pair with errors (see orthowarp.adjust.spot_synthetic) written into a
    new folder: ((id, scene JSON) x 2, points JSON)."""
    from .adjust.spot_synthetic import perturbed, simulate_points, stereo_pair
    from .pipeline.dimap import write_scene
    from .pipeline.io import check_destination, ensure_folder
    from .pipeline.scenepoints import write_scene_points

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
    write_scene_points(points, os.path.join(folder, "points.json"))
    return tuple(out), os.path.join(folder, "points.json")


@main.command()
@click.argument("images", nargs=-1, type=click.Path(dir_okay=False))
@click.option("--int-param", type=click.Path(dir_okay=False), help="Camera file (orthority/ODM YAML or JSON, OpenSfM).")
@click.option("--ext-param", type=click.Path(dir_okay=False),
              help="Approximate exterior orientation (x,y,z,omega,phi,kappa CSV + .prj, GeoJSON, reconstruction.json).")
@click.option("--crs", help="CRS of x,y,z poses in a file that has no .prj.")
@click.option("--dem", type=click.Path(dir_okay=False), help="DEM file (any CRS).")
@click.option("--height", type=float, help="Constant terrain height (m) instead of a DEM.")
@click.option("--out", "out_path", type=click.Path(dir_okay=False), required=True,
              help="The block file to write (JSON, for 'orthowarp adjust').")
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
@click.option("--no-refraction", is_flag=True, help="Do not model atmospheric refraction in the predictions.")
@click.option("--overwrite", is_flag=True, help="Replace an existing block file.")
@click.option("--device", default=None, help="Warp device (cpu, cuda, cuda:N); default: first GPU, else CPU.")
@click.pass_context
def match(ctx, images, int_param, ext_param, crs, dem, height, out_path, zones, per_zone, window, radius, pyramid,
          control_csv, reference, control_sigma, min_score, gnss_sigma, ins_sigma, no_refraction, overwrite, device):
    """Find tie points between frame IMAGES by area-based matching (interest points, NCC,
    least-squares matching, back-matching, a check across images), predicted through their
    approximate orientation and the DEM, and write them as a block for 'orthowarp adjust' (add
    control with --control and --reference, or to its 'points' before adjusting, or give
    --gnss-sigma/--ins-sigma). The first band of each image is matched; the poses are all
    omega-phi-kappa ones in one projected CRS, or all GNSS/INS ones without boresight and lever
    arm."""
    import rasterio

    from .adjust.matching import zones_allowed
    from .errors import ParamError, RasterIOError
    from .pipeline.blockio import write_block
    from .pipeline.dem import Dem
    from .pipeline.io import check_destination
    from .pipeline.matching import match_block

    images = _expand_globs(images)
    if len(images) < 2 or not (int_param or ext_param) or (dem is None) == (height is None):
        raise ParamError("Give two or more IMAGES, --ext-param (and --int-param) and one of --dem or --height")
    try:
        zx, zy = (int(v) for v in zones.lower().split("x"))
    except ValueError:
        raise ParamError(f"--zones must be COLSxROWS such as 4x3, got {zones!r}") from None
    if zx < 1 or zy < 1:
        raise ParamError(f"--zones must be COLSxROWS of at least 1x1, got {zones!r}")
    check_destination(out_path, overwrite=overwrite)
    jobs = _frame_orientations(images, int_param, ext_param, crs)
    pixels = []
    for image, cam, _ in jobs:
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
    terrain = Dem.from_file(dem) if dem is not None else height
    ids = [_image_key(image) for image, _, _ in jobs]
    block, stats = match_block(pixels, [FrameSensor(c, p) for _, c, p in jobs], terrain, ids=ids, zones=(zx, zy),
                               per_zone=per_zone, window=window, radius=radius, levels=pyramid,
                               min_score=min_score, gnss_sigma=gnss_sigma, ins_sigma=ins_sigma, refraction=not no_refraction,
                               device=device)
    if not block.n_points and stats.get("no_ground"):
        off = stats["no_ground"]
        raise ParamError(f"No tie point matched: {f'the DEM {dem!r}' if dem else f'--height {height:g}'} does not cover "
                         f"{'the images' if len(off) == len(ids) else 'image(s) ' + ', '.join(off)} (none of "
                         f"{'their' if len(off) > 1 else 'its'} interest points meets it): check the DEM and the "
                         "poses' CRS (--crs, .prj)")
    if not block.n_points:
        raise ParamError(f"No tie point matched between the {len(images)} images ({stats['interest']} interest "
                         "points): no texture, no overlap, or the orientation is further off than the search "
                         "reaches (--radius, --pyramid)")
    if control_csv is not None:
        block = _match_control(block, pixels, [FrameSensor(c, p) for _, c, p in jobs], terrain, control_csv,
                               reference, control_sigma, out_path, overwrite=overwrite, quiet=ctx.obj["quiet"],
                               window=window, radius=radius, levels=pyramid, min_score=min_score,
                               refraction=not no_refraction, device=device)
    write_block(block, out_path)
    if not ctx.obj["quiet"]:
        pairs = ", ".join(f"{k} {v['accepted']}/{v['predicted']}" for k, v in stats["pairs"].items())
        click.echo(f"{out_path}: {stats['points']} tie points, {stats['observations']} observations "
                   f"({stats['interest']} interest points; matched/predicted per pair: {pairs})")


if __name__ == "__main__":  # pragma: no cover
    main()
