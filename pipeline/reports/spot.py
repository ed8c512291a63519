"""Outputs of the SPOT-5 stereo adjustment (:func:`~orthowarp.adjust.adjust_scenes`, after
:func:`~orthowarp.adjust.preadjust_look_angles`), all written together or none
(:func:`~orthowarp.pipeline.raster.io.write_files`):

- ``<scene>_ADJUSTED.json``: each scene with its corrected look angles and adjusted
  exterior-orientation polynomials (:func:`~orthowarp.pipeline.formats.dimap.scene_json`), which
  ``orthowarp ortho --dimap`` and :func:`orthowarp.read_scene` take;
- ``points.csv``: ``point,role,lon,lat,h,se,sn,su`` of the adjusted points (deg, m);
- ``report.json``: sigma0, redundancy, the rounds of the two steps, RMSE east/north/up at
  control and check points before and after, the freed groups' coefficients, sigmas and
  correlations, the (last) pre-adjustment's corrections, sigma0 and global test;
- ``report.md``, ``residuals.png`` (image residual vectors over each scene, [P1]'s Figure 5)
  and ``errors.png`` (check-point errors).
"""

from __future__ import annotations

import json
import os
from typing import TYPE_CHECKING

import numpy as np

from ...errors import GeometryError
from ..formats.dimap import scene_json
from ..raster.io import ensure_folder, write_files
from .adjust import finite_or_null, png_bytes

if TYPE_CHECKING:
    from ...adjust.lookangles import LookAngleResult
    from ...adjust.scene_points import ScenePoints
    from ...adjust.spot_bundle import SceneBundleResult

__all__ = ["write_scene_adjustment"]


def write_scene_adjustment(result: SceneBundleResult, points: ScenePoints, out_dir: str | os.PathLike, *,
                           preadjustment: LookAngleResult | None = None, before: SceneBundleResult | None = None,
                           plots: bool = True) -> dict[str, str]:
    """Write the stereo adjustment's outputs (see the module doc) into ``out_dir``; returns the
    paths by kind.

    Parameters
    ----------
    result : SceneBundleResult
    points : ScenePoints
    out_dir : str or os.PathLike
    preadjustment : LookAngleResult, optional
        The pre-adjustment whose corrected look angles the adjusted scenes have (after
        repeated rounds: ``result.preadjustment``).
    before : SceneBundleResult, optional
        The same points with nothing freed and the look angles as given (the "uncorrected"
        row of the report).
    plots : bool, optional

    Raises
    ------
    GeometryError
        The adjustment failed: nothing is written.
    """
    if not result.success:
        raise GeometryError(f"The adjustment of '{points.name}' failed ({result.message}); no outputs written")
    out_dir = os.fspath(out_dir)
    ensure_folder(out_dir)
    files, paths = {}, {}
    for sid, scene in result.scenes.items():
        extra = {"groups": list(result.freed[sid]), "sigma0": result.sigma0,
                 "coefficient_std": result.coefficient_std[sid].tolist(), "points": points.name}
        if preadjustment is not None and sid in preadjustment.coefficients:
            extra["look_angle_correction"] = preadjustment.coefficients[sid].tolist()
        if sid in result.look_coefficients:
            extra["look_angle_correction"] = result.look_coefficients[sid].tolist()
            extra["look_angle_correction_std"] = result.look_std[sid].tolist()
        paths[f"scene_{sid}"] = p = os.path.join(out_dir, f"{sid}_ADJUSTED.json")
        files[p] = scene_json(scene, extra=finite_or_null(extra))
    rows = ["point,role,lon,lat,h,se,sn,su"]
    for i, pid in enumerate(result.point_ids):
        sd = np.sqrt(np.clip(np.diag(result.point_cov[i]), 0, None))
        rows.append(",".join([pid, points.roles[i], *(f"{v:.9f}" for v in result.llh[i, :2]), f"{result.llh[i, 2]:.4f}",
                              *(f"{v:.4f}" for v in sd)]))
    paths["points"] = p = os.path.join(out_dir, "points.csv")
    files[p] = "\n".join(rows) + "\n"
    report = dict(
        points=points.name, status=result.status, message=result.message, sigma0=result.sigma0,
        redundancy=result.redundancy, iterations=result.iterations, rounds=result.rounds,
        freed={k: list(v) for k, v in result.freed.items()},
        control_rmse_enu=result.control_rmse.tolist(), check_rmse_enu=result.check_rmse.tolist(),
        check_errors_enu={pid: e.tolist() for pid, e in zip(result.check_ids, result.check_errors)},
        group_correlation=[dict(scene=s, a=a, b=b, r=r) for (s, a, b), r in result.group_correlation.items()],
        coefficients={sid: c.tolist() for sid, c in result.coefficients.items()},
        coefficient_std={sid: c.tolist() for sid, c in result.coefficient_std.items()},
        look_angle_correction={sid: c.tolist() for sid, c in result.look_coefficients.items()},
        look_angle_correction_std={sid: c.tolist() for sid, c in result.look_std.items()},
        image_residual_rms_px=np.sqrt(np.mean(result.residuals ** 2, 0)).tolist())
    if before is not None:
        report["uncorrected"] = dict(control_rmse_enu=before.control_rmse.tolist(),
                                     check_rmse_enu=before.check_rmse.tolist())
    if preadjustment is not None:
        report["preadjustment"] = dict(
            message=preadjustment.message,
            coefficients={k: v.tolist() for k, v in preadjustment.coefficients.items()},
            coefficient_std={k: preadjustment.coefficient_std(k).tolist() for k in preadjustment.coefficients},
            sigma0=preadjustment.sigma0, global_test=preadjustment.global_test,
            check_rmse_px={k: v.tolist() for k, v in preadjustment.check_rmse.items()},
            check_rmse_px_before={k: v.tolist() for k, v in preadjustment.check_rmse_before.items()})
    report = finite_or_null(report)
    paths["report"] = p = os.path.join(out_dir, "report.json")
    files[p] = json.dumps(report, indent=2, allow_nan=False) + "\n"
    if plots:
        for key, (p, png) in _plots(result, points, out_dir).items():
            paths[key], files[p] = p, png
    paths["markdown"] = p = os.path.join(out_dir, "report.md")
    files[p] = _markdown(report, plots)
    write_files(files)
    return paths


def _fmt3(v: object) -> str:
    return " / ".join("-" if v is None else f"{x:.3f}" for x in v) if v is not None else "-"


def _markdown(r: dict, plots: bool) -> str:
    lines = [f"# SPOT stereo adjustment of {r['points']}", "",
             f"{r['message']}.", "",
             "| | control RMSE E / N / U (m) | check RMSE E / N / U (m) |", "|---|---|---|"]
    if "uncorrected" in r:
        u = r["uncorrected"]
        lines.append(f"| uncorrected | {_fmt3(u['control_rmse_enu'])} | {_fmt3(u['check_rmse_enu'])} |")
    lines.append(f"| adjusted ({', '.join(next(iter(r['freed'].values()))) or 'no EO group'}) | "
                 f"{_fmt3(r['control_rmse_enu'])} | {_fmt3(r['check_rmse_enu'])} |")
    if r["group_correlation"]:
        lines += ["", "Largest correlations between freed groups:", ""]
        lines += [f"- {c['scene']}: {c['a']} ~ {c['b']}: {c['r']:.3f}" for c in r["group_correlation"]]
    if "preadjustment" in r:
        lines += ["", f"Look-angle pre-adjustment: {r['preadjustment']['message']}."]
    if plots:
        lines += ["", "![image residuals](residuals.png)", "", "![check-point errors](errors.png)"]
    return "\n".join(lines) + "\n"


def _plots(result: SceneBundleResult, points: ScenePoints, out_dir: str | os.PathLike) -> dict:
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    out = {}
    sids = list(result.scenes)
    fig = Figure(figsize=(4.5 * len(sids), 4.5))
    res = result.residuals
    scale = 0.05 * max(s.width for s in result.scenes.values()) / max(float(np.max(np.abs(res))), 1e-9)
    control = points.role_mask("control")
    for k, sid in enumerate(sids):
        ax = fig.add_subplot(1, len(sids), k + 1)
        sel = points.obs_scene == points.scene_ids.index(sid)
        sc = result.scenes[sid]
        colour = np.where(control[points.obs_point[sel]], "tab:blue", "tab:orange")
        ax.quiver(points.obs_xy[sel, 0], points.obs_xy[sel, 1], res[sel, 0] * scale, -res[sel, 1] * scale,
                  angles="xy", scale_units="xy", scale=1, color=colour, width=0.005)
        ax.set_xlim(0, sc.width)
        ax.set_ylim(sc.height, 0)
        ax.set_title(sid, fontsize=9)
    fig.suptitle(f"image residuals x {scale:.0f} (blue: control, orange: tie and check)")
    out["residuals_png"] = os.path.join(out_dir, "residuals.png"), png_bytes(fig)
    fig = Figure(figsize=(6, 5))
    ax = fig.add_subplot(1, 1, 1)
    chk = points.role_mask("check")
    if np.any(chk):
        g, e = points.llh[chk], result.check_errors
        s = 0.05 * max(np.ptp(g[:, 0]), 1e-9) / max(float(np.max(np.hypot(e[:, 0], e[:, 1]))), 1e-12)
        ax.quiver(g[:, 0], g[:, 1], e[:, 0] * s, e[:, 1] * s, angles="xy", scale_units="xy", scale=1, color="tab:red")
        for (lon, lat), dz in zip(g[:, :2], e[:, 2]):
            ax.annotate(f"{dz:+.2f} m", (lon, lat), fontsize=6)
        ax.set_title(f"check points: planimetric errors x {s:.3g} deg/m, labels: height errors")
    else:
        ax.set_title("no check points")
    out["errors_png"] = os.path.join(out_dir, "errors.png"), png_bytes(fig)
    return out
