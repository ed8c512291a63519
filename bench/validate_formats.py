"""Validate the orientation file readers against orthority's sample data (not a test).

Reads the NGI (aerial, pinhole) and ODM (drone, Brown) sample orientations in every form the
data holds and checks that the forms agree:

* NGI: ``io/ngi_xyz_opk.csv`` (+ ``.prj``), ``io/ngi_ext_param.geojson`` and the legacy
  header-less ``ngi/camera_pos_ori.txt`` (CRS passed from the ``.prj``); cameras from
  ``io/ngi_int_param.yaml`` and the legacy ``ngi/config.yaml``.
* ODM: ``odm/opensfm/reconstruction.json`` (ODM's projected frame, UTM 51N, the reference),
  ``io/odm_xyz_opk.csv`` (EPSG:32651 passed: there is no ``.prj``), ``io/odm_lla_rpy.csv``
  (geocentric poses), and the same ``reconstruction.json`` forced to OpenSfM's topocentric
  reading (to show what reading the frame wrongly costs).

Poses are compared in ECEF: projection centres (map poses through pyproj, z as ellipsoidal
height), optical axes (map poses: the point 100 m along the axis is transformed too) and the
whole attitude (the same with the camera x and y axes, orthonormalised), so map-Cartesian
and geocentric poses are compared with the meridian convergence accounted for.

usage: python3 bench/validate_formats.py [--data DIR] [--json FILE]
Exit status 1 when a gated comparison exceeds 0.5 m or 0.5 deg.
"""

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from pyproj import Transformer

from orthowarp import geodesy
from orthowarp.pipeline.formats import read_cameras, read_exterior
from orthowarp.pose import MOUNT

TOL_M, TOL_DEG = 0.5, 0.5


def ecef_frame(pose):
    """(centre (3,), R_ecef<-cam (3, 3)) of a pose of either mode."""
    if pose.mode == "geocentric":
        return pose.center, pose.rotation
    to_ecef = Transformer.from_crs(pose.crs, "EPSG:4978", always_xy=True)
    pts = np.vstack([pose.center, pose.center + 100.0 * pose.rotation.T])  # centre, +x, +y, +z
    e = np.array(to_ecef.transform(pts[:, 0], pts[:, 1], pts[:, 2])).T
    axes = (e[1:] - e[0]).T / 100.0
    u, _, vt = np.linalg.svd(axes)  # nearest rotation (the projection's scale is ~1e-4)
    return e[0], u @ vt


def compare(a, b):
    ca, ra = ecef_frame(a)
    cb, rb = ecef_frame(b)
    axis_a, axis_b = -ra[:, 2], -rb[:, 2]
    axis = math.degrees(math.acos(max(-1.0, min(1.0, float(axis_a @ axis_b)))))
    rel = ra.T @ rb
    full = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(rel) - 1.0) / 2.0))))
    return float(np.linalg.norm(ca - cb)), axis, full


def table(title, ref_name, ref, others, gated, rows_out):
    """Print one comparison table; ``gated`` maps a name to "all" or "centre" (what must pass)."""
    print(f"\n{title}")
    print(f"  reference: {ref_name}")
    print(f"  {'compared with':38s} {'image':30s} {'centre m':>9s} {'axis deg':>9s} {'attitude deg':>13s}  gate")
    worst = True
    for name, data in others:
        if set(data) != set(ref):
            print(f"  {name}: images differ: {sorted(set(data) ^ set(ref))}")
            worst = False if gated.get(name) else worst
            continue
        for img in ref:
            d, ax, full = compare(ref[img].pose, data[img].pose)
            gate = gated.get(name)
            ok = d <= TOL_M and (gate == "centre" or (ax <= TOL_DEG and full <= TOL_DEG))
            if gate and not ok:
                worst = False
            mark = (("ok" if ok else "FAIL") + ("" if gate == "all" else " (centre only)")) if gate else "info"
            print(f"  {name:38s} {img:30s} {d:9.4f} {ax:9.4f} {full:13.4f}  {mark}")
            rows_out.append(dict(group=title, reference=ref_name, compared=name, image=img,
                                 centre_m=d, axis_deg=ax, attitude_deg=full, gated=gate, ok=ok))
    return worst


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="/work/shared/data/orthority", help="orthority sample data folder")
    ap.add_argument("--json", help="write the comparisons as JSON here")
    args = ap.parse_args(argv)
    d = Path(args.data)
    rows, ok = [], True

    # -- cameras ---------------------------------------------------------------------------
    print("Cameras")
    cams_yaml = read_cameras(d / "io/ngi_int_param.yaml")
    cams_legacy = read_cameras(d / "ngi/config.yaml")
    cams_odm = read_cameras(d / "odm/opensfm/reconstruction.json")
    for label, cams in (("io/ngi_int_param.yaml", cams_yaml), ("ngi/config.yaml", cams_legacy),
                        ("odm/opensfm/reconstruction.json", cams_odm)):
        for cid, cam in cams.items():
            fpx = cam.focal_length / np.array(cam.pixel_size)
            pp = np.array(cam.principal_point) / np.array(cam.pixel_size) * [1, -1] + 0.0
            print(f"  {label:34s} '{cid}': {cam.image_size[0]}x{cam.image_size[1]} px, "
                  f"focal {fpx[0]:.3f} x {fpx[1]:.3f} px, principal point offset "
                  f"({pp[0]:+.3f}, {pp[1]:+.3f}) px (right, down), "
                  f"k1..k3 {cam.k1:+.4f} {cam.k2:+.4f} {cam.k3:+.4f}, p1 p2 {cam.p1:+.2e} {cam.p2:+.2e}")
    same = repr(cams_yaml) == repr(cams_legacy)
    print(f"  ngi_int_param.yaml == config.yaml: {same}")
    ok &= same

    # -- NGI ---------------------------------------------------------------------------------
    prj = (d / "io/ngi_xyz_opk.prj").read_text().strip()
    ngi_csv = read_exterior(d / "io/ngi_xyz_opk.csv", cameras=cams_yaml)
    ngi_geojson = read_exterior(d / "io/ngi_ext_param.geojson", cameras=cams_yaml)
    ngi_legacy = read_exterior(d / "ngi/camera_pos_ori.txt", crs=prj, cameras=cams_yaml)
    ok &= table("NGI (map-Cartesian, TM lon_0=25 WGS84)", "io/ngi_ext_param.geojson", ngi_geojson,
                [("io/ngi_xyz_opk.csv + .prj", ngi_csv), ("ngi/camera_pos_ori.txt (legacy)", ngi_legacy)],
                {"io/ngi_xyz_opk.csv + .prj": "all", "ngi/camera_pos_ori.txt (legacy)": "all"}, rows)

    # -- ODM ---------------------------------------------------------------------------------
    rec = d / "odm/opensfm/reconstruction.json"
    odm_rec = read_exterior(rec, cameras=cams_odm)
    frame = next(iter(odm_rec.values())).pose
    print(f"\n  reconstruction.json read as: {frame.mode} ({frame.crs.name})")
    odm_topo = read_exterior(rec, cameras=cams_odm, opensfm_frame="topocentric")
    odm_xyz = read_exterior(d / "io/odm_xyz_opk.csv", crs="EPSG:32651", cameras=cams_odm)
    odm_lla = read_exterior(d / "io/odm_lla_rpy.csv", cameras=cams_odm)
    ok &= table("ODM (drone)", "odm/opensfm/reconstruction.json (projected, auto)", odm_rec,
                [("io/odm_xyz_opk.csv (EPSG:32651)", odm_xyz), ("io/odm_lla_rpy.csv (geocentric)", odm_lla),
                 ("reconstruction.json as topocentric", odm_topo)],
                {"io/odm_xyz_opk.csv (EPSG:32651)": "all", "io/odm_lla_rpy.csv (geocentric)": "centre"}, rows)
    table("ODM: the roll-pitch-yaw file against the topocentric reading",
          "reconstruction.json as topocentric", odm_topo,
          [("io/odm_lla_rpy.csv (geocentric)", odm_lla)], {}, rows)

    # what the lla_rpy file's angles are, next to those implied by the reconstruction
    print("\nODM roll/pitch/yaw: file vs implied by reconstruction.json (projected reading, via ECEF)")
    for img, io in odm_rec.items():
        c, r = ecef_frame(io.pose)
        lat, lon, h = odm_lla[img].pose.center_geodetic
        r_nav_body = geodesy.ned_to_ecef_matrix(lat, lon).T @ r @ MOUNT.T
        pitch = math.degrees(math.asin(-r_nav_body[2, 0]))
        roll = math.degrees(math.atan2(r_nav_body[2, 1], r_nav_body[2, 2]))
        yaw = math.degrees(math.atan2(r_nav_body[1, 0], r_nav_body[0, 0]))
        p = odm_lla[img].pose.params
        print(f"  {img}: file roll {p['roll']:7.2f} pitch {p['pitch']:7.2f} yaw {p['yaw']:8.2f} | "
              f"implied roll {roll:7.2f} pitch {pitch:7.2f} yaw {yaw:8.2f}")

    print("\nio/odm_lla_rpy.csv holds rounded, apparently nominal angles (roll 0.0 and pitch 30.0 for"
          "\nevery image, yaw to 0.1 deg), not the adjusted attitude: only its positions are gated.")
    print(f"\nPASS: gated comparisons within {TOL_M} m and {TOL_DEG} deg" if ok
          else f"\nFAIL: a gated comparison exceeds {TOL_M} m or {TOL_DEG} deg")
    if args.json:
        Path(args.json).write_text(json.dumps(dict(ok=bool(ok), rows=rows), indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
