"""The ``orthowarp`` command line: parses, calls the public API, reports.

Library errors become one-line messages on stderr and a non-zero exit code.
"""

import logging
import sys

import click

from .errors import OrthowarpError


class _Group(click.Group):
    """Turn library errors into a one-line message and exit code 1."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except OrthowarpError as e:
            click.echo(f"Error: {e}", err=True)
            sys.exit(1)


@click.group(cls=_Group)
@click.version_option(package_name="orthowarp")
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors.")
def main(verbose, quiet):
    """orthowarp: rigorous orthorectification on the GPU with NVIDIA Warp."""
    import warp as wp

    level = logging.ERROR if quiet else (logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if verbose < 2:  # Warp's own banner and module-load messages only with -vv
        if hasattr(wp, "LOG_WARNING"):
            wp.config.log_level = wp.LOG_WARNING
        else:  # warp-lang < 1.10
            wp.config.quiet = True


@main.command()
@click.option("--out", "out_dir", default="orthowarp-demo", show_default=True, type=click.Path(file_okay=False),
              help="Output folder.")
@click.option("--device", default=None, help="Warp device (cpu, cuda, cuda:N); default: first GPU, else CPU.")
def demo(out_dir, device):
    """Run the embedded synthetic scene end to end and report its accuracy."""
    from .pipeline.demo import run_demo

    s = run_demo(out_dir, device=device)
    w, h = s["image_size"]
    click.echo(f"orthowarp demo: synthetic {w}x{h} frame (GSD {s['gsd_m']:.2f} m), DEM {s['dem_shape'][1]}x{s['dem_shape'][0]}, device {s['device']}")
    click.echo(f"  forward geolocation (DEM relief search, refraction): {s['geolocation_seconds']:.2f} s, "
               f"{s['geolocation_mpix_per_s']:.2f} Mpix/s, {s['pixels_without_ground']} pixels without ground")
    click.echo(f"  accuracy vs scene truth ({s['check_points']} points on the terrain): RMS {s['check_rms_m'] * 1000:.3f} mm, "
               f"max {s['check_max_m'] * 1000:.3f} mm ({s['check_max_px']:.2e} px)")
    click.echo(f"  ground -> pixel -> ground -> pixel round trip: max {s['round_trip_max_px']:.2e} px")
    click.echo(f"  outputs in {out_dir}/: {', '.join(s['outputs'])}")


if __name__ == "__main__":  # pragma: no cover
    main()
