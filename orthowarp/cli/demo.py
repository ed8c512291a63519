"""``orthowarp demo``: the embedded synthetic scene end to end, then the automatic chain."""

from __future__ import annotations

from typing import Any

import click

from . import options


@click.command()
@options.out_dir(default="orthowarp-demo", legacy_out=True)
@options.device
@click.option("--no-chain", is_flag=True,
              help="Skip the second part: a four-frame block from approximate orientation through matching, "
                   "adjustment and mosaic (about 30 s on two CPU cores).")
def demo(out_dir: str, device: str | None, no_chain: bool) -> None:
    """Run the embedded synthetic scene end to end and report its accuracy; then the automatic
    chain (approximate orientation -> tie points by matching -> adjustment -> mosaic) on a
    block of four frames of the same scene, measured against its truth."""
    from ..pipeline.demo import run_demo

    s = run_demo(out_dir, device=device, chain=not no_chain)
    for line in _summary(s, out_dir):
        click.echo(line)


def _summary(s: dict[str, Any], out_dir: str) -> list[str]:
    """The demo's report, line by line, from :func:`~orthowarp.pipeline.demo.run_demo`'s summary."""
    w, h = s["image_size"]
    lines = [
        f"orthowarp demo: synthetic {w}x{h} frame (GSD {s['gsd_m']:.2f} m), DEM {s['dem_shape'][1]}x"
        f"{s['dem_shape'][0]}, device {s['device']}",
        f"  forward geolocation (DEM relief search, refraction): {s['geolocation_seconds']:.2f} s, "
        f"{s['geolocation_mpix_per_s']:.2f} Mpix/s, {s['pixels_without_ground']} pixels without ground",
        f"  accuracy vs scene truth ({s['check_points']} points on the terrain): "
        f"RMS {s['check_rms_m'] * 1000:.3f} mm, "
        f"max {s['check_max_m'] * 1000:.3f} mm ({s['check_max_px']:.2e} px)",
        f"  ground -> pixel -> ground -> pixel round trip: max {s['round_trip_max_px']:.2e} px",
        f"  orthoimage {s['ortho_size'][0]}x{s['ortho_size'][1]} at {s['ortho_resolution_m']:.2f} m "
        f"({s['ortho_crs']}), "
        f"{s['ortho_seconds']:.2f} s; misregistration vs truth texture over {s['ortho_misregistration_tiles']} tiles: "
        f"RMS {s['ortho_misregistration_rms_px']:.3f} px, mean ({s['ortho_misregistration_mean_px'][0]:+.3f}, "
        f"{s['ortho_misregistration_mean_px'][1]:+.3f}) px"]
    if "chain" in s:
        c = s["chain"]
        lines.append(f"  chain on {c['images']} frames: {c['ties']} tie points by matching ({c['tie_observations']} "
                     f"observations, {c['match_seconds']:.1f} s), adjusted with {c['control_points']} control points "
                     f"(sigma0 {c['sigma0']:.2f}, {c['adjust_seconds']:.2f} s); outputs in {out_dir}/chain/")
        for name in ("approximate", "adjusted"):
            r = c[name]
            lines.append(f"    {name:>11s} orientation: centres off by up to {r['pose_error_max_m']:.2f} m, attitudes "
                         f"{r['attitude_error_max_deg']:.3f} deg; mosaic vs truth texture: RMS "
                         f"{r['mosaic_misregistration_rms_m']:.2f} m, max {r['mosaic_misregistration_max_m']:.2f} m "
                         f"({r['mosaic_tiles']} tiles)")
    lines.append(f"  outputs in {out_dir}/: {', '.join(s['outputs'])}")
    return lines
