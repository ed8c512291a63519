"""The options of the ``orthowarp`` commands that several commands take: one declaration, one
meaning and one help text each; and the parsing of option values that click's types do not
cover (sigma lists, ``-co KEY=VALUE``).

Output options follow one rule: ``-o/--out FILE`` names the one file a command writes,
``-O/--out-dir DIR`` the folder it writes into.

Only click is imported here: ``orthowarp --help`` loads no numerical library.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

import click

from ..options import AccuracyMeasure, BlockCodec, Compress, Resampling, values

F = TypeVar("F", bound=Callable[..., Any])

FRAME_POSE_SIGMA = "0.05,0.05,0.1,0.005,0.005,0.01"  # --pose-sigma's default: m x 3, deg x 3
SCENE_SIGMA = "10,10,5,0.001,0.001,0.001,0.001,0.001"  # --scene-sigma's default: m x 3, deg x 5
RESAMPLING = values(Resampling)
BLOCK_CODECS = values(BlockCodec)
COMPRESS = values(Compress)
MOSAIC_COMPRESS = ("deflate", "zstd", "jpeg", "webp")  # (pipeline.mosaic.MOSAIC_COMPRESS, without importing it)


def compose(*decorators: Callable[[F], F]) -> Callable[[F], F]:
    """One decorator applying ``decorators`` as if stacked in this order (the options appear
    in ``--help`` in this order)."""
    def apply(f: F) -> F:
        for decorate in reversed(decorators):
            f = decorate(f)
        return f
    return apply


# -- where it runs ----------------------------------------------------------------------------

device = click.option("-d", "--device", default=None,
                      help="Warp device (cpu, cuda, cuda:N); default: the first GPU, else the CPU.")
tile_size = click.option("--tile-size", type=int, default=None,
                         help="Output tile edge in pixels, a multiple of 16 (default: 512 on the CPU; on a GPU an "
                              "ortho takes up to 4096 as the device's free memory allows, a mosaic 2048).")
workers = click.option("--workers", type=int, default=None,
                       help="Tiles in flight (default: CPU cores on the CPU, 8 on a GPU); with --processes, per "
                            "process (default 2).")


def cluster(f: Callable) -> Callable:
    """--gpus, --scheduler and the TLS files of a --scheduler (see :func:`cluster_client`)."""
    for opt in reversed([
        click.option("--gpus", type=click.IntRange(min=1), default=None,
                     help="Run on this many GPUs of this host: a Dask cluster of worker processes (4 per GPU), "
                          "started for the run and listening on localhost only."),
        click.option("--scheduler", default=None, metavar="ADDRESS",
                     help="Run on an existing Dask cluster (tcp://HOST:PORT, tls://HOST:PORT): its workers read the "
                          "images and write their outputs themselves, so they must see the same files at the same "
                          "(absolute) paths, e.g. on a shared file system or as /vsis3/ paths."),
        click.option("--tls-ca-file", type=click.Path(exists=True, dir_okay=False), default=None,
                     help="With --scheduler tls://...: the certificate authority (default: Dask's configuration)."),
        click.option("--tls-cert", type=click.Path(exists=True, dir_okay=False), default=None,
                     help="With --scheduler tls://...: this client's certificate."),
        click.option("--tls-key", type=click.Path(exists=True, dir_okay=False), default=None,
                     help="With --scheduler tls://...: this client's private key."),
    ]):
        f = opt(f)
    return f


@contextlib.contextmanager
def cluster_client(o: Any, *, quiet: bool, processes_per_gpu: int = 4) -> Iterator[Any]:
    """The Dask client of --gpus (``processes_per_gpu`` worker processes per GPU) / --scheduler
    (None without them), for the block; the dashboard's address echoed where there is one."""
    from ..errors import ParamError

    if o.gpus is None and o.scheduler is None and not any((o.tls_ca_file, o.tls_cert, o.tls_key)):
        yield None  # no cluster: spare this process the mosaic package's imports (~0.08 s)
        return
    from ..pipeline.mosaic.cluster import connect, dashboard_link

    if o.gpus is not None and o.scheduler is not None:
        raise ParamError("Give --gpus (a cluster on this host) or --scheduler (an existing one), not both")
    tls = (o.tls_ca_file, o.tls_cert, o.tls_key)
    security = None
    if any(tls):
        if o.scheduler is None or not o.scheduler.startswith("tls://"):
            raise ParamError("--tls-ca-file, --tls-cert and --tls-key go with --scheduler tls://HOST:PORT")
        if not all(tls):
            raise ParamError("Give --tls-ca-file, --tls-cert and --tls-key together")
        from distributed.security import Security

        security = Security(tls_ca_file=o.tls_ca_file, tls_client_cert=o.tls_cert, tls_client_key=o.tls_key,
                            require_encryption=True)
    with connect(o.scheduler, gpus=o.gpus, security=security, processes_per_gpu=processes_per_gpu) as client:
        if client is not None and not quiet:
            link = dashboard_link(client)
            workers = len(client.scheduler_info()["workers"])
            click.echo(f"Dask cluster: {workers} worker(s)" + (f", dashboard {link}" if link else ""), err=True)
        yield client

# -- inputs -----------------------------------------------------------------------------------

int_param = click.option("--int-param", "int_param", type=click.Path(dir_okay=False),
                         help="Interior orientation: orthority/ODM camera file (YAML/JSON) or OpenSfM "
                              "reconstruction.json.")
ext_param = click.option("--ext-param", "ext_param", type=click.Path(dir_okay=False),
                         help="Exterior orientation of the frame IMAGES: CSV (x,y,z,omega,phi,kappa or latitude,"
                              "longitude,altitude,roll,pitch,yaw; a .prj beside it names the CRS of x,y,z), "
                              "orthority GeoJSON or OpenSfM reconstruction.json.")
orientation = compose(int_param, ext_param)
odm_dataset = click.option("--odm-dataset", type=click.Path(file_okay=False),
                           help="An OpenDroneMap dataset folder: its opensfm/reconstruction.json for --int-param and "
                                "--ext-param, its odm_dem/dsm.tif for --dem (unless --dem or --height is given) "
                                "and, without IMAGES, its images/.")
exif = click.option("--exif", is_flag=True,
                    help="Cameras and poses from the IMAGES' own EXIF/XMP tags (drone JPEGs or TIFFs; IMAGES may be "
                         "folders or wildcards): focal length and sensor size (or the 35 mm equivalent, or DJI's "
                         "calibration), GPS position, DJI gimbal angles (else nadir, the image's top along the "
                         "flight line); instead of --ext-param (--int-param replaces the tags' cameras).")
exif_altitude = click.option("--exif-altitude", type=click.Choice(["auto", "ellipsoidal", "relative"]),
                             default="auto", show_default=True,
                             help="With --exif, the cameras' heights: auto, the GPS altitude, above the geoid (mean "
                                  "sea level) unless the EXIF says the ellipsoid; ellipsoidal, the same taken as "
                                  "ellipsoidal heights; relative, DJI's RelativeAltitude above the take-off point "
                                  "(--height is then the terrain's height above that point).")
exif_heading = click.option("--exif-heading", type=click.Choice(["tags", "content"]), default="tags", show_default=True,
                            help="With --exif, the cameras' attitude: tags, DJI's gimbal angles (else nadir along "
                                 "the flight line); content, nadir with the image's top where the image content moves "
                                 "against the GPS track between neighbouring images (where that cannot be measured, "
                                 "the tags' corrected as their strip's, else the tags').")
exif_options = compose(exif, exif_altitude, exif_heading)
gcps = click.option("--gcps", type=click.Path(dir_okay=False),
                    help="Ground control points. With --rpc (ortho): orthority's GCP GeoJSON, estimating a bias "
                         "compensation of the RPCs in image space (--bias); the estimate and the points' leave-one-out "
                         "check residuals with and without it are printed. With --exif --adjust (ortho, mosaic): "
                         "OpenDroneMap's gcp_list.txt, control points of the adjustment (--gcp-sigma), those of "
                         "--check-points kept out as check points whose errors are reported.")
check_points = click.option("--check-points", default=None, metavar="N|NAMES",
                            help="With --gcps and --adjust: keep GCPs out of the adjustment as check points, their "
                                 "intersected minus given positions (east, north, up, m) in the report: N of them, "
                                 "spread over the file's order, or their names, comma-separated.")
gcp_sigma = click.option("--gcp-sigma", type=click.FloatRange(min=0.0, min_open=True), default=0.05,
                         show_default=True,
                         help="With --gcps and --adjust: standard deviation (m) of each GCP coordinate (east, north, "
                              "up) in the adjustment.")
gcp_pixel_sigma = click.option("--gcp-pixel-sigma", type=click.FloatRange(min=0.0, min_open=True), default=1.0,
                               show_default=True,
                               help="With --gcps and --adjust: standard deviation (px) of each GCP's image "
                                    "measurement.")
chain_control = compose(gcps, check_points, gcp_sigma, gcp_pixel_sigma)


adjust = click.option(
    "--adjust", "adjust_chain", is_flag=True,
    help="With --exif: first refine the tags' orientation: tie points by matching, then a bundle adjustment with the "
         "GPS positions and gimbal angles as observations (and --gcps) and the camera's radial distortion (k1, k2) "
         "self-calibrated; without --dem and --height the matching takes the take-off point's height and the orthos "
         "or the mosaic a terrain from the adjusted tie points (and dense points: --densify); each step's files and "
         "report in --adjust-dir.")
adjust_dir = click.option(
    "--adjust-dir", type=click.Path(file_okay=False), default=None,
    help="Folder of --adjust's files (exif/ with the tags' orientation, block.json, exterior.csv, cameras.yaml, "
         "points.csv, pose_cov.json, report.md, report.json, chain.json; tie_surface.tif, tie_points.csv and, with "
         "--densify, dense_points.csv where the terrain comes from the tie points); default: adjust/ in the orthos' "
         "--out-dir, <mosaic>_adjust beside a mosaic.")
adjust_options = compose(adjust, adjust_dir)
surface_length = click.option("--surface-length", type=click.FloatRange(min=0.0, min_open=True), default=None,
                              metavar="METRES",
                              help="With --exif --adjust and neither --dem nor --height: the smoothing length of the "
                                   "terrain made from the adjusted tie points (a Gaussian's standard deviation, m; "
                                   "default the median distance from a point to its 6th nearest).")
#: ``--densify/--no-densify`` of ``ortho`` and ``mosaic`` (None where not given: on).
densify = click.option(
    "--densify/--no-densify", "densify", default=None,
    help="With --exif --adjust and neither --dem nor --height: before the terrain is made, match every overlapping "
         "pair of images on a dense grid (one point every 64 px) with the adjusted orientation held, intersect the "
         "matches and make the terrain from the tie points and these points together (dense_points.csv in "
         "--adjust-dir). Default: on.")
orthos = click.option("--orthos", is_flag=True,
                      help="IMAGES are orthoimages already (georeferenced rasters: orthority's orthos, GDAL's, "
                           "orthowarp's), mosaicked by their CRS and geotransform, reprojected where their grids "
                           "differ from the mosaic's; no orientation, no DEM (--dem and --height are refused). "
                           "Default CRS: the first image's; default resolution: the finest image's, the grid "
                           "aligned to that image's.")
attitude_model = click.option("--attitude-model", type=click.Choice(["full", "first_order"]), default=None,
                              help="Attitude matrix of pushbroom scenes read from DIMAP: full (the default) or "
                                   "first_order (its linearised form); a scene JSON from 'orthowarp spot-adjust' "
                                   "keeps its own.")
dem = click.option("--dem", type=click.Path(dir_okay=False), help="DEM or DSM file, in any CRS.")
height = click.option("--height", type=float,
                      help="Constant terrain height (m) instead of a DEM, in the vertical datum of the camera "
                           "positions: ellipsoidal for GNSS/INS poses (latitude, longitude, altitude; OpenSfM "
                           "topocentric reconstructions too) and pushbroom scenes, that of the poses' z for x,y,z "
                           "poses.")
terrain = compose(dem, height)
geoid = click.option("--geoid", type=click.Path(dir_okay=False),
                     help="Geoid grid (any raster GDAL reads, e.g. egm08_25.gtx) converting the DEM's heights where "
                          "the DEM and the positions declare different vertical datums.")
same_vertical_datum = click.option("--same-vertical-datum", is_flag=True,
                                   help="Take the DEM's and the positions' heights as one vertical datum, whatever "
                                        "their CRSs declare.")
vertical = compose(geoid, same_vertical_datum)
crs = click.option("--crs", default=None,
                   help="CRS (EPSG code, WKT or PROJ string) of x,y,z poses in an exterior file that names none (no "
                        ".prj; without --crs the images' own CRS, if they have one); for ortho and mosaic also the "
                        "output CRS (default: the poses' map CRS, else the UTM zone of the first image's centre).")

# -- the output's grid and pixels ---------------------------------------------------------------

resolution = click.option("-r", "--resolution", type=float,
                          help="Output pixel size in CRS units (default: the images' mean GSD in those units, so it "
                               "carries the CRS's scale: e.g. 1/cos(latitude) times the metres on the ground in Web "
                               "Mercator).")
resampling = click.option("--resampling", type=click.Choice(RESAMPLING), default="bilinear", show_default=True,
                          help="Resampling of the source images.")
dtype = click.option("--dtype", type=click.Choice(["uint8", "uint16", "float32"]),
                     help="Output data type (default: the source images').")
no_refraction = click.option("--no-refraction", is_flag=True, help="Do not model atmospheric refraction.")

# -- files ---------------------------------------------------------------------------------------

compress = click.option("--compress", type=click.Choice(COMPRESS), default="deflate", show_default=True,
                        help="Lossless (deflate, zstd, lzw, none) or lossy for uint8 RGB (jpeg, webp: files 10-40 "
                             "times smaller; see --quality).")
quality = click.option("--quality", type=click.IntRange(1, 100), default=None,
                       help="JPEG / WebP quality 1-100 (default 90; orthority's JPEG default is 75).")
mosaic_compress = click.option("--compress", type=click.Choice(MOSAIC_COMPRESS), default="deflate",
                               show_default=True,
                               help="Compression of the mosaic: lossless (deflate, zstd; with the TIFF predictor "
                                    "for integer data; its --index the same) or lossy for uint8 mosaics (jpeg, webp; "
                                    "see --quality; the --index deflate).")
compress_level = click.option("--compress-level", type=int, default=None,
                              help="Deflate level 1-12 (default 6), or zstd level 1-22 (default 9).")
block_codec = click.option("--block-codec", type=click.Choice(BLOCK_CODECS), default="auto", show_default=True,
                           help="Who compresses the blocks of a deflate, zstd or jpeg COG: host (libdeflate or zstd on all "
                                "cores), nvcomp (the GPU; needs orthowarp[gpu]; its zstd takes no level), warp "
                                "(orthowarp's own deflate kernels on the device), hybrid (the device, nvCOMP at "
                                "--compress-level 1-4 where installed, else warp, and the host cores at once); warp "
                                "and hybrid are deflate codecs. auto: host on the CPU and for zstd; on a GPU, "
                                "for a deflate ortho nvcomp at --compress-level 1-4 where "
                                "installed, else hybrid; for a deflate mosaic warp. A jpeg COG: host (libjpeg on "
                                "the cores), hybrid (on a GPU its blocks made there, libjpeg on the cores), warp "
                                "(orthowarp's own JPEG kernels on the device: the host's file, byte for byte) or "
                                "auto (warp on a GPU, host on the CPU).")
creation = click.option("-co", "--co", "creation", multiple=True, metavar="KEY=VALUE",
                        help="GDAL-style creation option, repeatable: BLOCKSIZE (64-4096, multiple of 16; default "
                             "512), BIGTIFF (YES, NO, IF_NEEDED, IF_SAFER), NUM_THREADS (count or ALL_CPUS); "
                             "COMPRESS, LEVEL (ZLEVEL, ZSTD_LEVEL) and QUALITY (JPEG_QUALITY) set --compress, "
                             "--compress-level and --quality (a mosaic takes DEFLATE or ZSTD); PREDICTOR=YES (2) is "
                             "what orthowarp writes for integer data.")
overwrite = click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
no_plots = click.option("--no-plots", is_flag=True, help="Skip the PNG plots.")


def out_file(what: str) -> Callable[[F], F]:
    """``-o/--out FILE``, required: the one file the command writes (``what``, for the help)."""
    return click.option("-o", "--out", "out_path", type=click.Path(dir_okay=False), required=True, help=what)


def out_dir(*, default: str | None = None, required: bool = False, legacy_out: bool = False,
            what: str = "Output folder.") -> Callable[[F], F]:
    """``-O/--out-dir DIR``: the folder the command writes into.

    Parameters
    ----------
    default : str, optional
    required : bool, optional
    legacy_out : bool, optional
        Also take the folder as ``--out DIR`` (hidden; the command's earlier name of the
        option), with a one-line deprecation warning on stderr.
    what : str, optional
        The help text.
    """
    defaults = {} if default is None else dict(default=default, show_default=True)  # (None would count as given)
    option = click.option("-O", "--out-dir", "out_dir", type=click.Path(file_okay=False), required=required,
                          help=what, callback=_one_out_dir if legacy_out else None, **defaults)
    if not legacy_out:
        return option
    legacy = click.option("--out", "legacy_out", type=click.Path(file_okay=False), hidden=True, expose_value=False,
                          is_eager=True, callback=_legacy_out)
    return compose(option, legacy)


def _legacy_out(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
    """``--out DIR`` where ``--out-dir DIR`` is meant: warn, and give its value to
    ``--out-dir`` (as its default: processed first, this option is eager)."""
    if value is None:
        return
    click.echo(f"Warning: '{ctx.info_name} --out DIR' is deprecated: use --out-dir DIR (-O DIR)", err=True)
    ctx.meta["orthowarp.legacy_out"] = value
    ctx.default_map = {**(ctx.default_map or {}), "out_dir": value}


def _one_out_dir(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    """Refuse ``--out-dir`` and ``--out`` together."""
    if "orthowarp.legacy_out" in ctx.meta and ctx.get_parameter_source("out_dir") is \
            click.core.ParameterSource.COMMANDLINE:
        raise click.UsageError("Give the output folder once, as --out-dir DIR (--out DIR is its deprecated name)",
                               ctx=ctx)
    return value


# -- accuracy rasters -----------------------------------------------------------------------------

accuracy = click.option("--accuracy", is_flag=True,
                        help="Also write the predicted accuracy of each ground position beside the output, as "
                             "<image>_ACCURACY.tif (an ortho) or <mosaic>_ACCURACY.tif (a mosaic, with --index: each "
                             "cell from the image its centre was taken from): by error propagation from "
                             "--pose-sigma (or --pose-cov) and --scene-sigma, --pixel-sigma and --dem-sigma, one "
                             "pixel per --accuracy-step x --accuracy-step output pixels.")
pose_sigma = click.option("--pose-sigma", default=FRAME_POSE_SIGMA, show_default=True, metavar="SX,SY,SZ,SA,SB,SC",
                          help="With --accuracy: frame images' pose standard deviations: x, y, z (or east, north, up "
                               "for GNSS/INS poses) in m, omega, phi, kappa (or roll, pitch, yaw) in deg; GNSS/INS "
                               "poses may add the boresight angles (deg), then the lever arm (m): 9 or 12 numbers.")
scene_sigma = click.option("--scene-sigma", default=SCENE_SIGMA, show_default=True, metavar="8 NUMBERS",
                           help="With --accuracy: pushbroom scenes' orientation standard deviations: the orbit "
                                "across, along the track and radially (m), roll, pitch, yaw and the look angles "
                                "psi_x, psi_y (deg).")
accuracy_measure = click.option("--accuracy-measure", type=click.Choice(values(AccuracyMeasure)), default="sigma",
                                show_default=True,
                                help="With --accuracy: three bands sigma x, y (in the output CRS's units: m, or deg "
                                     "where it is longitude/latitude) and up (m), or two bands CE90 (the radius "
                                     "holding 90 % of the horizontal error) and LE90 (m); each band's description "
                                     "says which. Ground that faces away from the image (hidden by its own slope) "
                                     "is NaN.")
accuracy_step = click.option("--accuracy-step", type=click.IntRange(1, 4096), default=16, show_default=True,
                             help="With --accuracy: output pixels per accuracy pixel, each way (1: full resolution).")
pixel_sigma = click.option("--pixel-sigma", type=float, default=0.5, show_default=True,
                           help="With --accuracy: standard deviation of an image position (px).")
dem_sigma = click.option("--dem-sigma", type=float, default=0.5, show_default=True,
                         help="With --accuracy: standard deviation of the DEM's heights (m).")
accuracy_options = compose(accuracy, pose_sigma, scene_sigma, accuracy_measure, accuracy_step, pixel_sigma,
                           dem_sigma)

# -- profiling ------------------------------------------------------------------------------------

profile = click.option("--profile", "show_profile", is_flag=True,
                       help="Print on stderr where the time went: seconds per stage (summed over threads, and "
                            "wall-clock), the device's busy fraction, what bounds the run; for orthos per image, "
                            "in total and the start-up, for a mosaic also the plan's steps.")
profile_json = click.option("--profile-json", type=click.Path(dir_okay=False),
                            help="Write the same profile as JSON to this file.")
profiling = compose(profile, profile_json)


# -- option values --------------------------------------------------------------------------------

_SIGMA_BOUNDS = {"m": 1e6, "deg": 180.0}  # the largest standard deviation a pose's input may take
FRAME_SIGMA_UNITS = "m, m, m, deg, deg, deg; GNSS/INS poses: then boresight deg x 3, lever arm m x 3"
SCENE_SIGMA_UNITS = "m, m, m, deg x 5"


def sigma_list(text: str, n: int | Sequence[int], option: str, units: str) -> list[float]:
    """Comma-separated standard deviations of an option: ``n`` (a count, or the counts allowed)
    finite numbers >= 0 (0 leaves that input out), each at most 1e6 m or 180 deg by its unit:
    m, m, m, then deg (a scene's eight numbers; a frame pose's six, then boresight deg x 3,
    lever arm m x 3).

    Raises
    ------
    ParamError
        Not that many numbers, a negative or non-finite one, or one beyond its bound.
    """
    from ..errors import ParamError

    counts = (n,) if isinstance(n, int) else tuple(n)
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in counts or not all(math.isfinite(v) and v >= 0 for v in values):
        raise ParamError(f"{option} must be {' or '.join(map(str, counts))} numbers >= 0 ({units}), got {text!r}")
    kinds = ["m"] * 3 + ["deg"] * 5 if counts == (8,) else ["m"] * 3 + ["deg"] * 6 + ["m"] * 3
    for k, (v, unit) in enumerate(zip(values, kinds)):
        if v > _SIGMA_BOUNDS[unit]:
            raise ParamError(f"{option}: number {k + 1}, {text.split(',')[k].strip()} {unit}, is beyond "
                             f"{_SIGMA_BOUNDS[unit]:g} {unit} (no pose is that uncertain: check the units, {units})")
    return values


def check_measurement_sigmas(pixel_sigma: float, dem_sigma: float) -> None:
    """Refuse a ``--pixel-sigma`` or ``--dem-sigma`` that is negative or not finite (ParamError)."""
    from ..errors import ParamError

    if not (math.isfinite(pixel_sigma) and pixel_sigma >= 0 and math.isfinite(dem_sigma) and dem_sigma >= 0):
        raise ParamError("--pixel-sigma and --dem-sigma must be >= 0")


def creation_args(values: Sequence[str], compress: str, compress_level: int | None,
                  quality: int | None) -> tuple[str, int | None, int | None, dict[str, str]]:
    """``-co KEY=VALUE`` options: COMPRESS, LEVEL/ZLEVEL/ZSTD_LEVEL, QUALITY/JPEG_QUALITY and
    PREDICTOR (YES/2/STANDARD only) taken into the matching options; the rest returned as the
    writer's creation options (checked by the library).

    Returns
    -------
    (compress, compress_level, quality, creation_options)

    Raises
    ------
    ParamError
        An item is not KEY=VALUE, or a value of the keys taken here is wrong.
    """
    from ..errors import ParamError

    rest = {}
    for item in values:
        key, sep, value = item.partition("=")
        key, value = key.strip().upper(), value.strip()
        if not sep or not key or not value:
            raise ParamError(f"-co takes KEY=VALUE, got {item!r}")
        if key == "COMPRESS":
            if value.lower() not in COMPRESS:
                raise ParamError(f"-co COMPRESS must be one of {sorted(n.upper() for n in COMPRESS)}, got {value!r}")
            compress = value.lower()
        elif key in ("LEVEL", "ZLEVEL", "ZSTD_LEVEL"):
            compress_level = _int_value(key, value)
        elif key in ("QUALITY", "JPEG_QUALITY", "WEBP_LEVEL"):
            quality = _int_value(key, value)
        elif key == "PREDICTOR":
            if value.upper() not in ("YES", "2", "STANDARD"):
                raise ParamError(f"-co PREDICTOR={value}: orthowarp writes horizontal differencing (PREDICTOR=2) for "
                                 "integer data with deflate, zstd and lzw, and no other predictor")
        else:
            rest[key] = value
    return compress, compress_level, quality, rest


def _int_value(key: str, value: str) -> int:
    from ..errors import ParamError

    try:
        return int(value)
    except ValueError:
        raise ParamError(f"-co {key} must be an integer, got {value!r}") from None
