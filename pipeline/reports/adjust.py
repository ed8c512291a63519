"""Outputs of a bundle adjustment: refined orientation in the formats ``orthowarp ortho``
reads, adjusted points, a JSON report, and a readable report with plots (matplotlib).

Files written into the output folder, all together or none (:func:`~orthowarp.pipeline.raster.io.write_files`):

- ``exterior.csv`` + ``exterior.prj``: ``filename,x,y,z,omega,phi,kappa`` (m, deg) in the
  block's CRS (geocentric blocks: ``filename,latitude,longitude,altitude,roll,pitch,yaw``, no
  .prj): ``orthowarp ortho --ext-param exterior.csv``;
- ``cameras.yaml``: the cameras in orthority's format: ``--int-param cameras.yaml``;
- ``points.csv``: ``point,role,x,y,z,sx,sy,sz``;
- ``pose_cov.json``: each image's pose covariance in the parameters of ``exterior.csv`` (x, y,
  z m and omega, phi, kappa deg; geocentric blocks: the position's east, north, up offsets
  (m) and roll, pitch, yaw (deg), as :mod:`orthowarp.adjust.precision` takes a GNSS/INS
  pose's inputs): ``orthowarp ortho --accuracy --pose-cov pose_cov.json`` (written when the
  adjustment computed covariances);
- ``report.json``: statistics (sigma0, redundancy, RMSE per axis, pose sigmas, rejections,
  correlation warnings, residual summary);
- ``report.md``, ``residuals.png`` (image residual vectors of every image, [P1] Figures
  5-7 style) and ``errors.png`` (planimetric error vectors and height errors at control and
  check points).
"""

from __future__ import annotations

import io
import json
import os
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from pyproj import CRS

from ...adjust.bundle.result import correlation_note
from ...errors import GeometryError, ParamError
from ..formats.export import camera_dict
from ..raster.io import ensure_folder, write_files

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ...adjust.block import Block
    from ...adjust.bundle.result import AdjustResult

__all__ = ["write_adjustment", "read_pose_covariances", "POSE_COV_PARAMETERS", "finite_or_null", "png_bytes"]

# the parameters of pose_cov.json, by block mode
POSE_COV_PARAMETERS = {"map": ["x", "y", "z", "omega", "phi", "kappa"],
                       "geocentric": ["east", "north", "up", "roll", "pitch", "yaw"]}


def _csv(rows: list) -> str:
    return "\n".join(",".join(str(v) for v in r) for r in rows) + "\n"


def _pose_cov(block: Block, result: AdjustResult, k: int) -> list[list[float]]:
    """Image k's pose covariance (6 x 6 nested lists) in the parameters of exterior.csv."""
    c = result.pose_cov[k]
    if block.mode == "geocentric":
        from ...adjust.precision import input_covariance
        from ...pose import Pose

        c = input_covariance(Pose.from_ins(*result.poses[block.image_ids[k]]), c, local=result.local_frame)
    return [[float(v) for v in row] for row in c]


def read_pose_covariances(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], list[str]]:
    """The pose covariances of ``pose_cov.json`` (as :func:`write_adjustment` writes it):
    image id -> (6, 6) ndarray (m, deg), with the parameter names.

    Raises
    ------
    ParamError
        The file cannot be read or parsed, or a matrix is not a finite symmetric positive
        semi-definite 6 x 6 one (naming the file and the image).
    """
    from ...adjust.precision import square_matrix

    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
        names = doc["parameters"]
        images = doc["images"]
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as e:
        raise ParamError(f"Could not read pose covariances '{path}': {str(e)[:200]}") from e
    if names not in POSE_COV_PARAMETERS.values() or not isinstance(images, dict) or not images:
        raise ParamError(f"Could not read pose covariances '{path}': parameters must be one of "
                         f"{list(POSE_COV_PARAMETERS.values())} and images a non-empty mapping")
    out = {}
    for iid, c in images.items():
        try:
            out[str(iid)] = square_matrix(f"the pose covariance of image {str(iid)[:60]!r}", np.asarray(c, dtype=np.float64),
                                    6)
        except (ParamError, ValueError, TypeError, OverflowError, RecursionError) as e:
            raise ParamError(f"Could not read pose covariances '{path}': {str(e)[:200]}") from e
    return out, names


def write_adjustment(result: AdjustResult, block: Block, out_dir: str | os.PathLike, *,
                     plots: bool = True) -> dict[str, str]:
    """Write the adjustment's outputs (see the module doc) into ``out_dir``; returns the paths.

    The files are made in memory and published together: a failure (full disk, say) leaves
    the folder's earlier outputs as they were.

    Parameters
    ----------
    result : AdjustResult
        From :func:`~orthowarp.adjust.bundle_adjust`.
    block : Block
        The block adjusted.
    out_dir : str or os.PathLike
        The output folder (made if needed).
    plots : bool, optional
        Also write ``residuals.png`` and ``errors.png``.

    Returns
    -------
    dict of str to str
        The paths written, by kind.

    Raises
    ------
    GeometryError
        The adjustment failed (``result.success`` is False): its orientation is not written,
        so that nothing takes it for a good one.
    """
    if not result.success:
        raise GeometryError(f"The adjustment of '{block.name}' failed ({result.message}); no outputs written")
    ensure_folder(out_dir)
    paths, files = {}, {}
    b = block
    geo = b.mode == "geocentric"
    rows = [("filename", "latitude", "longitude", "altitude", "roll", "pitch", "yaw") if geo
            else ("filename", "x", "y", "z", "omega", "phi", "kappa")]
    digits = (10, 10, 4, 9, 9, 9) if geo else (6, 6, 6, 9, 9, 9)  # deg / m: 0.1 mm either way
    for iid in b.image_ids:
        rows.append((iid, *(f"{v:.{d}f}" for d, v in zip(digits, result.poses[iid]))))
    paths["exterior"] = os.path.join(out_dir, "exterior.csv")
    files[paths["exterior"]] = _csv(rows)
    if not geo:
        files[os.path.join(out_dir, "exterior.prj")] = CRS.from_user_input(b.crs).to_wkt()
    paths["cameras"] = os.path.join(out_dir, "cameras.yaml")
    cams = result.cameras or b.cameras
    files[paths["cameras"]] = yaml.safe_dump({cid: camera_dict(c) for cid, c in cams.items()})
    prow = [("point", "role", "x", "y", "z", "sx", "sy", "sz")]
    point_digits = (10, 10, 4) if geo else (4, 4, 4)  # deg / m: 0.1 mm either way (sigmas: m)
    for pid, role in zip(b.point_ids, b.roles):
        xyz = result.points.get(pid, (np.nan,) * 3)
        sd = result.point_std.get(pid, (np.nan,) * 3)
        prow.append((pid, role, *(f"{v:.{d}f}" for d, v in zip(point_digits, xyz)), *(f"{v:.4f}" for v in sd)))
    paths["points"] = os.path.join(out_dir, "points.csv")
    files[paths["points"]] = _csv(prow)
    if result.pose_cov is not None:
        paths["pose_cov"] = os.path.join(out_dir, "pose_cov.json")
        files[paths["pose_cov"]] = json.dumps(dict(
            parameters=POSE_COV_PARAMETERS[b.mode], units="m, deg",
            images={iid: _pose_cov(b, result, k) for k, iid in enumerate(b.image_ids)}), indent=1) + "\n"
    used = result.used
    res = result.residuals[used]
    report = dict(
        block=b.name, status=result.status, message=result.message, success=result.success,
        sigma0=result.sigma0, redundancy=result.redundancy, iterations=result.iterations, cost=result.cost,
        images=b.n_images, points=b.n_points, observations=int(len(used)), observations_used=int(used.sum()),
        residual_rms_px=[float(v) for v in np.sqrt(np.nanmean(res**2, axis=0))] if len(res) else None,
        control_rmse=[float(v) for v in result.control_rmse], check_rmse=[float(v) for v in result.check_rmse],
        pose_std={k: [float(x) for x in v] for k, v in result.pose_std.items()},
        rejected=[dict(image=i, point=p, w=w) for i, p, w in result.rejected],
        correlation_warnings=[dict(image=i, a=a, b=c, r=r) for i, a, c, r in result.correlation_warnings],
        max_abs_w=float(np.nanmax(np.abs(result.w_tests))) if result.w_tests is not None else None,
        camera_std=result.camera_std,
        cameras={cid: dict(f=c.focal_length, x0=c.principal_point[0], y0=c.principal_point[1], k1=c.k1, k2=c.k2,
                           k3=c.k3, p1=c.p1, p2=c.p2) for cid, c in (result.cameras or b.cameras).items()},
        check_observations=int(np.sum(np.asarray(b.roles)[b.obs_point] == "check")))
    # why observations are not in the adjustment: check points, rejected, the rest of tie
    # points left with fewer than two rays (undetermined)
    roles = np.asarray(b.roles)
    rej = {(i, p) for i, p, _ in result.rejected}
    out = ~used & (roles[b.obs_point] != "check")
    rays = np.bincount(b.obs_point[used], minlength=b.n_points)
    lonely = out & (roles[b.obs_point] == "tie") & (rays[b.obs_point] < 2) & np.array(
        [(b.image_ids[i], b.point_ids[p]) not in rej for i, p in zip(b.obs_image, b.obs_point)], dtype=bool)
    report["unused"] = dict(check=report["check_observations"], rejected=len(result.rejected),
                            lonely_ties=int(lonely.sum()), other=int(out.sum()) - len(result.rejected) - int(lonely.sum()))
    res_all = result.residuals
    index = {(b.image_ids[i], b.point_ids[p]): k for k, (i, p) in enumerate(zip(b.obs_image, b.obs_point))}
    for x in report["rejected"]:  # the rejected observation's residual (px) in the final solution
        k = index.get((x["image"], x["point"]))
        x["residual_px"] = [float(v) for v in res_all[k]] if k is not None and np.all(np.isfinite(res_all[k])) \
            else None
    paths["report"] = os.path.join(out_dir, "report.json")
    files[paths["report"]] = json.dumps(finite_or_null(report), indent=2, allow_nan=False) + "\n"
    if plots:
        for key, (path, png) in _plots(result, block, out_dir).items():
            paths[key], files[path] = path, png
    paths["markdown"] = os.path.join(out_dir, "report.md")
    files[paths["markdown"]] = _markdown(report, plots)
    write_files(files)
    return paths


def finite_or_null(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (JSON has no NaN or infinity)."""
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _markdown(r: dict, plots: bool) -> str:
    axes = ("x", "y", "z")
    lines = [f"# Bundle adjustment: {r['block']}", "",
             f"- {r['message']} after {r['iterations']} iterations",
             f"- sigma0 = {r['sigma0']:.4f} (redundancy {r['redundancy']})",
             f"- {r['images']} images, {r['points']} points, {r['observations_used']} of {r['observations']} "
             "image observations used"]
    if r["residual_rms_px"]:
        lines.append(f"- image residual RMS: col {r['residual_rms_px'][0]:.3f} px, row {r['residual_rms_px'][1]:.3f} px")
    for name in ("control", "check"):
        v = r[f"{name}_rmse"]
        if np.all(np.isfinite(v)):
            lines.append(f"- {name} point RMSE: " + ", ".join(f"{a} {x:.4f} m" for a, x in zip(axes, v)))
    u = r["unused"]
    if r["observations"] > r["observations_used"]:
        parts = [f"{u['check']} observations of check points (they only intersect those points afterwards)"] if u["check"] else []
        if u["rejected"]:
            parts.append(f"{u['rejected']} observations rejected (below)")
        if u["lonely_ties"]:
            parts.append(f"{u['lonely_ties']} observations of tie points left with fewer than two rays (undetermined)")
        if u["other"]:
            parts.append(f"{u['other']} observations set aside by the robust start")
        lines.append("- not in the adjustment: " + ", ".join(parts))
    if r["cameras"]:
        lines += ["", "## Cameras", "", "| camera | parameter | value | sigma |", "|---|---|---|---|"]
        units = dict(f="mm", x0="mm", y0="mm")
        for cid, params in r["cameras"].items():
            std = (r["camera_std"] or {}).get(cid, {})
            for name, value in params.items():
                sigma = f"{std[name]:.3g}" if name in std else "held"
                lines.append(f"| {cid} | {name} {units.get(name, '')} | {value:.6g} | {sigma} |")
    if r["rejected"]:
        lines += ["", "## Rejected observations (data snooping)", "",
                  "Observations whose normalised residual (Baarda's w-test) exceeded the critical value (3.29: "
                  "alpha 0.1 %, two-sided, unless set otherwise), largest first, with their residual in the final "
                  "solution (col, row px):", ""]
        for x in sorted(r["rejected"], key=lambda x: -abs(x["w"])):
            res = x.get("residual_px")
            tail = f", residual ({res[0]:+.2f}, {res[1]:+.2f}) px" if res else ""
            lines.append(f"- point {x['point']} in image {x['image']}: |w| = {abs(x['w']):.2f}{tail}")
    if r["correlation_warnings"]:
        worst = sorted(r["correlation_warnings"], key=lambda x: -abs(x["r"]))
        note = correlation_note([(x["image"], x["a"], x["b"], x["r"]) for x in worst])
        lines += ["", "## High correlations", "",
                  f"{len(worst)} pose parameter pairs correlated beyond the limit{note}; the "
                  f"{min(10, len(worst))} strongest (all in report.json):", ""]
        lines += [f"- {x['image']}: {x['a']} / {x['b']} r = {x['r']:+.3f}" for x in worst[:10]]
    if plots:
        lines += ["", "![image residuals](residuals.png)", "", "![control and check errors](errors.png)"]
    return "\n".join(lines) + "\n"


def png_bytes(fig: Figure) -> bytes:
    """The PNG bytes (110 dpi) of a Matplotlib figure, as the reports' plots are written."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


def _plots(result: AdjustResult, block: Block, out_dir: str | os.PathLike) -> dict:
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    b = block
    out = {}
    n = b.n_images
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    fig = Figure(figsize=(3 * cols, 3 * rows))
    res = result.residuals
    scale = 0.05 * max(c.image_size[0] for c in b.cameras.values()) / max(float(np.nanmax(np.abs(res))), 1e-9)
    for k, iid in enumerate(b.image_ids):
        ax = fig.add_subplot(rows, cols, k + 1)
        sel = (b.obs_image == k) & np.isfinite(res[:, 0])
        w, h = b.cameras[b.image_camera[k]].image_size
        ax.quiver(b.obs_xy[sel, 0], b.obs_xy[sel, 1], res[sel, 0] * scale, -res[sel, 1] * scale, angles="xy",
                  scale_units="xy", scale=1, color=np.where(result.used[sel], "tab:blue", "tab:red"), width=0.006)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_title(iid, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"image residuals x {scale:.0f} (red: rejected)")
    out["residuals_png"] = os.path.join(out_dir, "residuals.png"), png_bytes(fig)
    fig = Figure(figsize=(8, 6))
    ax = fig.add_subplot(1, 1, 1)
    centres = np.array([result.poses[i][:2] for i in b.image_ids])
    ax.plot(centres[:, 0], centres[:, 1], "k+", label="projection centres")
    roles = np.array(b.roles)
    for role, colour in (("control", "tab:green"), ("check", "tab:red")):
        idx = np.flatnonzero(roles == role)
        if not len(idx):
            continue
        got = np.array([result.points[b.point_ids[j]] for j in idx])
        err = got - b.xyz[idx]
        s = 0.05 * np.ptp(centres[:, 0]) / max(float(np.nanmax(np.hypot(err[:, 0], err[:, 1]))), 1e-9)
        ax.quiver(b.xyz[idx, 0], b.xyz[idx, 1], err[:, 0] * s, err[:, 1] * s, angles="xy", scale_units="xy",
                  scale=1, color=colour, label=f"{role} (planimetric error x {s:.0f})")
        for j, e in zip(idx, err):
            ax.annotate(f"{e[2] * 100:+.1f} cm", b.xyz[j, :2], fontsize=6, color=colour)
    ax.set_aspect("equal")
    ax.legend(fontsize=8)
    ax.set_title("errors at control and check points (labels: height error)")
    out["errors_png"] = os.path.join(out_dir, "errors.png"), png_bytes(fig)
    return out
