"""A drone folder to an orthomosaic from the images' EXIF/XMP tags alone (issue 38), on real data.

Given a folder of drone JPEGs (GPS in EXIF, DJI gimbal angles in XMP; e.g. the 18 DJI Phantom 3
frames of github.com/pierotofy/drone_dataset_brighton_beach, BSD-2-Clause), with no DEM (a
constant terrain height):

1. the EXIF orientation orthowarp reads (orthowarp.pipeline.formats.exif), and with ``--oty``
   orthority's (``oty exif --export-params``), interior and exterior side by side: focal length
   and principal point (px), the projection centre (UTM, m) and the camera's attitude as the
   optical axis' angle from nadir and the azimuth of the image's top (deg from true north:
   orthority's map angles carried to true north through the grid's meridian convergence at
   the camera), with their differences;
2. the mosaic of the folder in one command (``orthowarp mosaic FOLDER --exif --height H``);
3. the orthos of every image with the EXIF orientation and the misregistration between
   overlapping orthos (orthowarp.pipeline.registration.misregistration, 64-px tiles, as
   bench/match_ngi.py measures it);
4. with ``--adjust``, the chain: ``orthowarp mosaic FOLDER --exif --adjust`` (tie points by
   matching, a bundle adjustment with the GPS positions and gimbal angles as observations and
   the camera self-calibrated; each step's files in ``<mosaic>_adjust/``), then the orthos from
   the adjusted orientation (``--int-param cameras.yaml --ext-param exterior.csv``) and their
   misregistration: on the constant height given, and on the adjusted tie points' median
   height (with the EXIF orientation's orthos on that height too, for a like comparison).

The terrain height, unless ``--height`` gives one, is the take-off point's (DJI's
``AbsoluteAltitude`` - ``RelativeAltitude``, median over the images), in the datum of the GPS
altitudes. Relief (trees, buildings) is not modelled by a constant height: its parallax between
overlapping orthos is part of every misregistration figure here.

After the chain, where the misregistration comes from (``relief_at_ties``): every two
observations of a tie point carried to the ground through the adjusted orientation on the
point's own height, on ``--height`` and on the ties' median height, their distance in ortho
pixels; and with ``--tie-dem L`` the adjusted orthos on a smooth surface from the adjusted tie
points (orthowarp.pipeline.drone.tie_surface, smoothing length L m; a GeoTIFF in the work
folder).

With ``--dem FILE`` (with ``--adjust``) the orthos are also made on a given DSM: the EXIF
orientation's and the adjusted ones, the latter also on the DSM moved up or down by the median
difference between the adjusted tie points' heights and the DSM's at them (the block's vertical
datum, set by the GPS altitudes, against the DSM's); the DSM's CRS and vertical datum as its file
declares them, and those differences' quartiles, in the report. FILE may be a GeoTIFF or a LAS/LAZ
point cloud (e.g. OpenDroneMap's model.laz; needs laspy, with lazrs for LAZ), gridded here into a
DSM: the highest point of each 0.2 m cell, 3 x 3 median-filtered, empty cells from the nearest.

With ``--chain-surface`` (with ``--adjust``) the chain runs as ``orthowarp mosaic FOLDER --exif
--adjust`` does without ``--height``: it matches on the take-off point's height and makes its own
terrain from the adjusted tie points (with the dense points of every overlapping pair unless
``--setting densify=false``; ``--setting dense_spacing=N`` sets their grid); the adjusted orthos are
then made on that terrain (the chain's ``tie_surface.tif``) and measured, with the chain's steps'
seconds (matching, adjustment, surfaces, densification) in the report; the orthos on constant
heights after the adjustment and ``relief_at_ties`` are skipped.

With ``--attitude gps`` the XMP attitude is withheld: the images are copied into
``<work>/gps_only_images`` with their ``drone-dji:Gimbal*Degree`` keys renamed (the same number
of bytes, so nothing else in the files moves), and every image is taken as nadir with its top
along the flight line (GPS only), as for a consumer camera without gimbal tags.

usage: python3 bench/exif_folder.py FOLDER [--height H] [--resolution 0.05] [--oty PATH/TO/oty] [--adjust]
                                    [--heading tags|content] [--attitude tags|gps] [--tie-dem L] [--dem FILE]
                                    [--setting KEY=VALUE ...] [--chain-surface] [--no-mosaic]
                                    [--work DIR] [--reuse] [--device cpu] [--out FILE]
``--setting KEY=VALUE`` (repeatable; e.g. ``--setting zones=12,9 --setting per_zone=4``) overrides
the chain's matching and adjustment settings (orthowarp.pipeline.drone.ADJUST_DEFAULTS) in the
chain's process, which the ``orthowarp`` command does not expose.
Reads a folder outside the repository (which tests must not); CPU by default.
"""

import argparse
import glob
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from _report import save_report  # noqa: E402

from orthowarp import geodesy  # noqa: E402
from orthowarp.pipeline.formats.exif import exif_orientations  # noqa: E402


#: ``orthowarp ARGS`` with orthowarp.pipeline.drone.ADJUST_DEFAULTS updated from the JSON object
#: in argv[1] first (``--setting``: the chain's matching and adjustment settings, which the
#: command itself does not expose).
_WITH_SETTINGS = ("import json, sys; import orthowarp.pipeline.drone as d; d.ADJUST_DEFAULTS.update(json.loads("
                  "sys.argv[1])); from orthowarp.cli import main; sys.argv = ['orthowarp', *sys.argv[2:]]; main()")


def cli(*args, timed=True, settings=None):
    """Run ``orthowarp ARGS`` in a process of its own; (seconds, stderr's last lines). With
    ``settings`` (a dict), the chain's ADJUST_DEFAULTS overridden by them in that process."""
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "orthowarp.cli"] if not settings else \
        [sys.executable, "-c", _WITH_SETTINGS, json.dumps(settings)]
    r = subprocess.run([*cmd, *map(str, args)], capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"orthowarp {' '.join(map(str, args))} failed:\n{r.stdout}\n{r.stderr}")
    return time.perf_counter() - t0, (r.stderr.strip().splitlines() + r.stdout.strip().splitlines())


def without_attitude(folder, work):
    """A copy of the folder's JPEGs in ``<work>/gps_only_images`` whose XMP gimbal angles are
    withheld: ``drone-dji:GimbalRollDegree`` (and Pitch, Yaw) renamed ``drone-dji:NoGmblRollDegree``
    (same length: the JPEG's segments keep their sizes). The folder's path."""
    from orthowarp.pipeline.formats.exif import exif_images

    out = os.path.join(work, "gps_only_images")
    os.makedirs(out, exist_ok=True)
    for path in exif_images([folder]):
        with open(path, "rb") as f:
            data = f.read()
        stripped = data.replace(b"drone-dji:Gimbal", b"drone-dji:NoGmbl")
        if stripped == data:
            print(f"note: {os.path.basename(path)} holds no XMP gimbal angles")
        with open(os.path.join(out, os.path.basename(path)), "wb") as f:
            f.write(stripped)
    return out


def takeoff_height(orients):
    """Median of AbsoluteAltitude - RelativeAltitude (m), or None."""
    vals = [o.tags.xmp_number("AbsoluteAltitude") - o.tags.xmp_number("RelativeAltitude") for o in orients
            if o.tags.xmp_number("AbsoluteAltitude") is not None and o.tags.xmp_number("RelativeAltitude") is not None]
    return float(np.median(vals)) if vals else None


def ned_rotation(pose):
    """R_ned<-camera of a geocentric pose."""
    lat, lon, _ = pose.center_geodetic
    return geodesy.ned_to_ecef_matrix(lat, lon).T @ pose.rotation


def map_to_ned(crs, lat, lon):
    """R_ned<-map at (lat, lon) for a projected CRS: true north and east expressed in the map's
    grid (numerically, 1 m steps), so R_map<-ned has columns north, east, down."""
    from pyproj import Transformer

    t = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    x0, y0 = t.transform(lon, lat)
    dlat = 1.0 / 111_132.0
    dlon = dlat / np.cos(np.radians(lat))
    n = np.subtract(t.transform(lon, lat + dlat), (x0, y0))
    e = np.subtract(t.transform(lon + dlon, lat), (x0, y0))
    n, e = n / np.linalg.norm(n), e / np.linalg.norm(e)
    r_map_ned = np.array([[n[0], e[0], 0.0], [n[1], e[1], 0.0], [0.0, 0.0, -1.0]])
    return r_map_ned.T


def attitude_figures(r_ned_cam):
    """(off-nadir angle of the optical axis, azimuth of the image's top) in degrees."""
    axis = -r_ned_cam[:, 2]  # the camera looks along -z
    top = r_ned_cam[:, 1]
    return float(np.degrees(np.arccos(np.clip(axis[2], -1, 1)))), float(np.degrees(np.arctan2(top[1], top[0])) % 360)


def compare_with_orthority(orients, oty, work):
    """Side-by-side interior and exterior parameters of orthowarp's and orthority's EXIF reading."""
    from pyproj import Transformer

    from orthowarp.pipeline.formats import read_cameras, read_exterior

    folder = os.path.join(work, "oty_exif")
    os.makedirs(folder, exist_ok=True)
    subprocess.run([oty, "exif", "--export-params", "--out-dir", folder, "--overwrite", *[o.image for o in orients]],
                   check=True, capture_output=True)
    cams = read_cameras(os.path.join(folder, "int_param.yaml"))
    ext = read_exterior(os.path.join(folder, "ext_param.geojson"))
    rows, interior = [], {}
    for o in orients:
        key = os.path.splitext(os.path.basename(o.image))[0]
        theirs = ext[key]
        cam_t = cams[theirs.camera_id] if theirs.camera_id in cams else next(iter(cams.values()))
        for who, cam, cid in (("orthowarp", o.camera, o.camera_id), ("orthority", cam_t, theirs.camera_id)):
            if (who, cid) not in interior:
                f = cam.focal_length / np.array(cam.pixel_size)
                pp = cam.normalized_to_pixel(np.zeros((1, 2)))[0]
                interior[(who, cid)] = dict(who=who, camera=cid, image_size=list(cam.image_size),
                                            focal_px=[float(f[0]), float(f[1])], principal_point_px=pp.tolist(),
                                            distortion=[cam.k1, cam.k2, cam.k3, cam.p1, cam.p2],
                                            source=o.camera_source if who == "orthowarp" else "oty exif")
        crs = theirs.pose.crs
        lat, lon, h = o.pose.center_geodetic
        x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
        ours_xyz = np.array([x, y, h])
        their_xyz = np.asarray(theirs.pose.center)
        r_ours = ned_rotation(o.pose)
        r_theirs = map_to_ned(crs, lat, lon) @ theirs.pose.rotation
        d = r_ours.T @ r_theirs
        turn = float(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
        off_o, top_o = attitude_figures(r_ours)
        off_t, top_t = attitude_figures(r_theirs)
        gimbal = [o.tags.xmp.get(f"Gimbal{a}Degree") for a in ("Roll", "Pitch", "Yaw")]
        rows.append(dict(image=key, orthowarp=dict(xyz=ours_xyz.tolist(), off_nadir_deg=off_o, top_azimuth_deg=top_o,
                                                   gimbal=gimbal),
                         orthority=dict(xyz=their_xyz.tolist(), off_nadir_deg=off_t, top_azimuth_deg=top_t,
                                        opk_deg=[theirs.pose.params[k] for k in ("omega", "phi", "kappa")]),
                         position_difference_m=float(np.linalg.norm(ours_xyz - their_xyz)),
                         attitude_difference_deg=turn))
    print("interior orientation (px):")
    for v in interior.values():
        print(f"  {v['who']:9s} {v['camera']:28s} {v['image_size'][0]} x {v['image_size'][1]}  f "
              f"{v['focal_px'][0]:8.2f} {v['focal_px'][1]:8.2f}  pp ({v['principal_point_px'][0]:.2f}, "
              f"{v['principal_point_px'][1]:.2f})  k1..p2 {v['distortion']}  [{v['source']}]")
    print("exterior orientation: position (UTM m), optical axis from nadir and azimuth of the image top (deg)")
    for r in rows:
        a, b = r["orthowarp"], r["orthority"]
        print(f"  {r['image']}: orthowarp ({a['xyz'][0]:.3f}, {a['xyz'][1]:.3f}, {a['xyz'][2]:.3f}) "
              f"{a['off_nadir_deg']:.3f} {a['top_azimuth_deg']:8.3f} | orthority ({b['xyz'][0]:.3f}, "
              f"{b['xyz'][1]:.3f}, {b['xyz'][2]:.3f}) {b['off_nadir_deg']:.3f} {b['top_azimuth_deg']:8.3f} | d "
              f"{r['position_difference_m']:.1e} m, {r['attitude_difference_deg']:.1e} deg")
    return dict(interior=list(interior.values()), exterior=rows,
                max_position_difference_m=max(r["position_difference_m"] for r in rows),
                max_attitude_difference_deg=max(r["attitude_difference_deg"] for r in rows))


def pair_overlaps(paths, tile=64):
    """Per overlapping pair (a, b) of orthos, in ``paths``' order, their common part at least
    ``tile`` px each way: (a, b, grey of a, grey of b (the bands' mean, float64), valid in both,
    the part's transform in a's grid, a's pixel size)."""
    import itertools

    import rasterio
    from rasterio.windows import from_bounds

    for a, b in itertools.combinations(paths, 2):
        with rasterio.open(a) as da, rasterio.open(b) as db:
            left, bottom = max(da.bounds.left, db.bounds.left), max(da.bounds.bottom, db.bounds.bottom)
            right, top = min(da.bounds.right, db.bounds.right), min(da.bounds.top, db.bounds.top)
            if right <= left or top <= bottom:
                continue
            wa = from_bounds(left, bottom, right, top, da.transform).round_offsets().round_lengths()
            wb = from_bounds(left, bottom, right, top, db.transform).round_offsets().round_lengths()
            h, w = min(wa.height, wb.height), min(wa.width, wb.width)
            if min(h, w) < tile:
                continue
            ga = da.read(window=wa)[:, :h, :w].astype(np.float64).mean(0)
            gb = db.read(window=wb)[:, :h, :w].astype(np.float64).mean(0)
            valid = (da.read_masks(1, window=wa)[:h, :w] > 0) & (db.read_masks(1, window=wb)[:h, :w] > 0)
            transform, res = da.window_transform(wa), float(da.res[0])
        yield a, b, ga, gb, valid, transform, res


def pair_shifts(paths):
    """Per overlapping pair of orthos: the 64-px tiles' shifts (px) in their common part (grey:
    the bands' mean), by orthowarp.pipeline.registration.misregistration."""
    from orthowarp.pipeline.registration import misregistration

    out = {}
    for a, b, ga, gb, valid, _, _ in pair_overlaps(paths):
        m = misregistration(ga, gb, valid=valid, tile=64)
        if m["n_tiles"]:
            key = f"{os.path.basename(a)[:-10]}~{os.path.basename(b)[:-10]}"
            out[key] = m["shifts"]
    return out


def overlap_summary(folder, resolution, label):
    """The misregistration between the overlapping orthos of a folder: per pair the tiles, the
    RMS of their shift magnitudes and the length of their mean shift (its systematic part, as
    bench/match_ngi.py reports them); over all tiles the quartiles of the magnitudes."""
    paths = sorted(glob.glob(os.path.join(folder, "*_ORTHO.tif")))
    shifts = pair_shifts(paths)
    pairs = {k: dict(tiles=len(v), rms_px=round(float(np.sqrt(np.mean(np.sum(v * v, 1)))), 3),
                     mean_shift_px=round(float(np.hypot(*v.mean(0))), 3)) for k, v in shifts.items()}
    mags = np.concatenate([np.hypot(*v.T) for v in shifts.values()])
    rms = np.array([p["rms_px"] for p in pairs.values()])
    mean_shift = np.array([p["mean_shift_px"] for p in pairs.values()])
    q = np.percentile(mags, [25, 50, 75])
    out = dict(pairs=pairs, overlapping_pairs=len(pairs), tiles=int(len(mags)), resolution_m=resolution,
               rms_px_median=float(np.median(rms)), mean_shift_px_median=float(np.median(mean_shift)),
               tile_shift_px=dict(p25=float(q[0]), median=float(q[1]), p75=float(q[2]),
                                  under_5px=float(np.mean(mags < 5))))
    print(f"{label}: {len(pairs)} overlapping pairs, {len(mags)} tiles; per pair shift RMS median "
          f"{out['rms_px_median']:.2f} px ({out['rms_px_median'] * resolution:.3f} m), mean shift median "
          f"{out['mean_shift_px_median']:.2f} px ({out['mean_shift_px_median'] * resolution:.3f} m); tiles' shift "
          f"quartiles {q[0]:.2f}, {q[1]:.2f}, {q[2]:.2f} px, {100 * out['tile_shift_px']['under_5px']:.0f} % under 5 px")
    return out


def _adjusted_sensors(adj):
    """{image id: FrameSensor} of the chain's adjusted orientation (``cameras.yaml``, ``exterior.csv``)."""
    from orthowarp.pipeline.formats import read_cameras, read_exterior
    from orthowarp.sensor import FrameSensor

    cams = read_cameras(os.path.join(adj, "cameras.yaml"))
    ext = read_exterior(os.path.join(adj, "exterior.csv"))
    only = next(iter(cams.values()))
    return {k: FrameSensor(cams.get(v.camera_id, only) if v.camera_id else only, v.pose) for k, v in ext.items()}


def _tie_points(adj):
    """The adjusted tie points of ``points.csv``: {id: (lat, lon, h)}, their latitude and longitude
    refined by intersecting their observations' rays in the adjusted orientation (least squares;
    written when ``points.csv`` gave degrees to 4 decimals, some 11 m by 8 m here; it now gives
    10, and the refinement is kept so that the figures measured with it stay reproducible); the
    heights ``points.csv``'s (to 0.1 mm)."""
    import csv

    with open(os.path.join(adj, "points.csv")) as f:
        points = {r["point"]: (float(r["x"]), float(r["y"]), float(r["z"])) for r in csv.DictReader(f)}
    with open(os.path.join(adj, "block.json")) as f:
        block = json.load(f)
    sensors = _adjusted_sensors(adj)
    normal, rhs = {}, {}
    for o in block["observations"]:
        s = sensors.get(o["image"])
        if s is None or o["point"] not in points or not np.all(np.isfinite(points[o["point"]])):
            continue
        r = s.pose.rotation @ s.camera.pixel_to_camera(np.array([[o["col"], o["row"]]]), device="cpu")[0]
        r = r / np.linalg.norm(r)
        m = np.eye(3) - np.outer(r, r)
        normal[o["point"]] = normal.get(o["point"], 0) + m
        rhs[o["point"]] = rhs.get(o["point"], 0) + m @ np.asarray(s.pose.center, np.float64)
    for pid, n in normal.items():
        if np.linalg.cond(n) < 1e8:
            lat, lon, _ = geodesy.ecef_to_geodetic(np.linalg.solve(n, rhs[pid]))
            points[pid] = (float(lat), float(lon), points[pid][2])
    return points


def relief_parallax(adj, resolution, planes):
    """Where the orthos' misregistration after the adjustment comes from, at the tie points: every
    two observations of one tie point (the matched image positions, in the adjusted orientation)
    carried to the ground on a constant height, and the distance between the two ground points
    in ortho pixels: what a perfect shift estimator would measure between the two orthos there.
    On the point's own adjusted height it is the orientation's own misfit (the adjustment's
    residuals); on a constant height it adds the relief's parallax, baseline x (h - H) / (Z0 - h).
    Quartiles per terrain, over the pairs of observations; and the same split by the pair's
    baseline (same strip, <= 15 m; across strips)."""
    import itertools

    with open(os.path.join(adj, "block.json")) as f:
        block = json.load(f)
    sensors = _adjusted_sensors(adj)
    points = _tie_points(adj)
    lat0, lon0 = np.nanmedian([p[0] for p in points.values()]), np.nanmedian([p[1] for p in points.values()])
    enu = geodesy.enu_to_ecef_matrix(lat0, lon0)
    up = enu[:, 2]
    rays = {}
    for o in block["observations"]:
        s = sensors.get(o["image"])
        if s is None or o["point"] not in points or not np.all(np.isfinite(points[o["point"]])):
            continue  # (a point the adjustment left undetermined, NaN in points.csv)
        v = s.camera.pixel_to_camera(np.array([[o["col"], o["row"]]]), device="cpu")[0]
        rays.setdefault(o["point"], []).append((o["image"], np.asarray(s.pose.center), s.pose.rotation @ v))
    out = {}
    for label, height in [("own height", None)] + list(planes):
        d, base = [], []
        for pid, obs in rays.items():
            h = points[pid][2] if height is None else height
            p0 = geodesy.geodetic_to_ecef(lat0, lon0, h)
            ground = []
            for img, c, r in obs:
                t = (np.asarray(p0) - c) @ up / (r @ up)
                ground.append(c + t * r)
            for (a, ga), (b, gb) in itertools.combinations(zip(obs, ground), 2):
                delta = enu.T @ (ga - gb)
                d.append(np.hypot(delta[0], delta[1]) / resolution)
                base.append(float(np.linalg.norm(enu.T @ (a[1] - b[1]))))
        d, base = np.array(d), np.array(base)
        row = dict(height_m=height, pairs=len(d))
        for name, sel in (("all", np.ones(len(d), bool)), ("same strip", base <= 15.0), ("across strips", base > 15.0)):
            if sel.any():
                q = np.percentile(d[sel], [25, 50, 75])
                row[name] = dict(pairs=int(sel.sum()), p25=float(q[0]), median=float(q[1]), p75=float(q[2]),
                                 baseline_m_median=float(np.median(base[sel])))
        out[label] = row
        print(f"at the tie points, {label}{'' if height is None else f' {height:.2f} m'}: " + "; ".join(
            f"{k} {v['pairs']} pairs, baseline {v['baseline_m_median']:.1f} m, |d| quartiles {v['p25']:.2f}, "
            f"{v['median']:.2f}, {v['p75']:.2f} px" for k, v in row.items() if isinstance(v, dict)))
    hs = np.array([p[2] for p in points.values()])
    hs = hs[np.isfinite(hs)]
    out["tie_heights_m"] = dict(p5=float(np.percentile(hs, 5)), p25=float(np.percentile(hs, 25)),
                                median=float(np.median(hs)), p75=float(np.percentile(hs, 75)),
                                p95=float(np.percentile(hs, 95)))
    return out


def tie_surface(adj, path, length, margin=40.0):
    """A smooth terrain from the adjusted tie points of ``points.csv`` (GeoTIFF, UTM, heights in the
    GPS altitudes' datum) by the library's orthowarp.pipeline.drone.tie_surface (Gaussian
    smoothing length ``length`` m, outliers left out), over the cameras' extent and ``margin`` m."""
    from pyproj import CRS, Transformer

    from orthowarp.pipeline.drone import tie_surface as surface_of

    points = np.array(list(_tie_points(adj).values()))  # lat, lon, h
    cams = np.array([s.pose.center_geodetic for s in _adjusted_sensors(adj).values()])
    ok = np.all(np.isfinite(points), axis=1)
    zone = int((np.median(points[ok, 1]) + 180) // 6) + 1
    crs = CRS.from_epsg((32600 if np.median(points[ok, 0]) >= 0 else 32700) + zone)
    t = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    px, py = t.transform(points[:, 1], points[:, 0])
    cx, cy = t.transform(cams[:, 1], cams[:, 0])
    bounds = (min(cx.min(), np.nanmin(px)) - margin, min(cy.min(), np.nanmin(py)) - margin,
              max(cx.max(), np.nanmax(px)) + margin, max(cy.max(), np.nanmax(py)) + margin)
    s = surface_of(np.column_stack([px, py, points[:, 2]]), crs, path, length=length, bounds=bounds)
    return dict(path=path, length_m=s.length, spacing_m=s.spacing, points=s.points, rejected=s.rejected,
                fit_rms_m=s.fit_rms, min_m=s.height_range[0], max_m=s.height_range[1])


def laz_dsm(cloud, path, cell=0.2):
    """A DSM GeoTIFF at ``path`` from a LAS/LAZ point cloud: the highest point of each ``cell`` m
    cell, 3 x 3 median-filtered, cells without a point filled from the nearest; in the cloud's CRS
    (its header's), heights as they are. Returns ``path``."""
    import laspy
    import rasterio
    from affine import Affine
    from scipy import ndimage

    las = laspy.read(cloud)
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
    x0, y1 = np.floor(x.min() / cell) * cell, np.ceil(y.max() / cell) * cell
    cols = int(np.ceil((x.max() - x0) / cell)) + 1
    rows = int(np.ceil((y1 - y.min()) / cell)) + 1
    c = ((x - x0) / cell).astype(np.int64)
    r = ((y1 - y) / cell).astype(np.int64)
    grid = np.full(rows * cols, -np.inf)
    np.maximum.at(grid, r * cols + c, z)
    grid = grid.reshape(rows, cols)
    empty = ~np.isfinite(grid)
    idx = ndimage.distance_transform_edt(empty, return_distances=False, return_indices=True)
    grid = ndimage.median_filter(grid[tuple(idx)], size=3).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=cols, height=rows, count=1, dtype="float32",
                       crs=las.header.parse_crs().to_wkt(), transform=Affine(cell, 0, x0, 0, -cell, y1),
                       compress="deflate", tiled=True) as ds:
        ds.write(grid, 1)
    return path


def describe_dem(path):
    """The DEM's file, size, CRS and the vertical datum its CRS declares (None: a 2-D CRS, heights
    taken in the GPS altitudes' datum, nothing converted)."""
    import rasterio
    from pyproj import CRS

    with rasterio.open(path) as ds:
        crs = CRS.from_wkt(ds.crs.to_wkt())
        band = ds.read(1, masked=True)
        out = dict(path=path, size=[ds.width, ds.height], resolution_m=list(ds.res), crs=crs.name,
                   epsg=crs.to_epsg(), vertical_crs=None, heights_m=[float(band.min()), float(band.max())])
    vertical = [c for c in crs.sub_crs_list if c.is_vertical] if crs.is_compound else []
    if vertical:
        out["vertical_crs"] = vertical[0].name
    return out


def dem_at_ties(adj, dem):
    """The adjusted tie points' heights minus the DEM's at them (m): quartiles and count."""
    from pyproj import Transformer

    from orthowarp.pipeline.dem import Dem

    points = np.array(list(_tie_points(adj).values()))  # lat, lon, h
    d = Dem.from_file(dem)
    x, y = Transformer.from_crs("EPSG:4326", d.crs, always_xy=True).transform(points[:, 1], points[:, 0])
    diff = points[:, 2] - d.sample(x, y)
    diff = diff[np.isfinite(diff)]
    q = np.percentile(diff, [10, 25, 50, 75, 90])
    return dict(points=len(diff), p10=float(q[0]), p25=float(q[1]), median=float(q[2]), p75=float(q[3]),
                p90=float(q[4]))


def shifted_dem(dem, path, dz):
    """A copy of the DEM with ``dz`` m added to its heights."""
    import rasterio

    with rasterio.open(dem) as ds:
        profile, data = ds.profile, ds.read(1, masked=True)
    with rasterio.open(path, "w", **profile) as ds:
        ds.write((data + dz).filled(profile.get("nodata") or 0).astype(profile["dtype"]), 1)
    return path


def orthos(folder, args, *more, reuse=False):
    """``orthowarp ortho`` into ``folder`` (seconds, stderr's and stdout's lines); nothing where
    ``reuse`` and the folder holds orthos already."""
    if reuse and glob.glob(os.path.join(folder, "*_ORTHO.tif")):
        return None, []
    return cli("ortho", *more, "--out-dir", folder, *args)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--height", type=float, default=None, help="terrain height (default: the take-off point's)")
    ap.add_argument("--resolution", type=float, default=0.05)
    ap.add_argument("--oty", default=None, help="orthority's oty executable (compares its EXIF reading)")
    ap.add_argument("--adjust", action="store_true", help="also the chain: matching, adjustment, mosaic")
    ap.add_argument("--heading", choices=["tags", "content"], default="tags",
                    help="the images' headings (--exif-heading): the tags', or from the image content")
    ap.add_argument("--attitude", choices=["tags", "gps"], default="tags",
                    help="gps: withhold the XMP gimbal angles (nadir, heading from the flight line)")
    ap.add_argument("--tie-dem", type=float, default=None, metavar="L",
                    help="with --adjust: also orthos on a smooth surface from the adjusted tie points (Gaussian, L m)")
    ap.add_argument("--dem", default=None, metavar="FILE",
                    help="with --adjust: also orthos on this DSM (GeoTIFF, or a LAS/LAZ point cloud gridded here)")
    ap.add_argument("--setting", action="append", default=[], metavar="KEY=VALUE",
                    help="with --adjust: a setting of the chain (orthowarp.pipeline.drone.ADJUST_DEFAULTS, e.g. "
                         "zones=12,9 or per_zone=4; VALUE as JSON, or comma-separated numbers); repeatable")
    ap.add_argument("--chain-surface", action="store_true",
                    help="with --adjust: the chain without --height (its own terrain from the adjusted tie points "
                         "and dense points), the adjusted orthos on that terrain")
    ap.add_argument("--no-mosaic", action="store_true", help="skip step 2 (the EXIF mosaic)")
    ap.add_argument("--reuse", action="store_true", help="keep the orthos and the chain's files found in --work")
    ap.add_argument("--work", default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="bench/results/exif_folder.json")
    args = ap.parse_args(argv)
    settings = {}
    for item in args.setting:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--setting {item}: give KEY=VALUE")
        try:
            settings[key] = json.loads(value)
        except ValueError:
            try:
                settings[key] = [json.loads(v) for v in value.split(",")]
            except ValueError:
                settings[key] = value
    from orthowarp.pipeline.drone import ADJUST_DEFAULTS

    unknown = sorted(set(settings) - set(ADJUST_DEFAULTS))
    if unknown:
        ap.error(f"--setting: unknown {', '.join(unknown)} (known: {', '.join(ADJUST_DEFAULTS)})")
    work = args.work or tempfile.mkdtemp(prefix="orthowarp-exif-")
    os.makedirs(work, exist_ok=True)
    source_folder = args.folder
    if args.attitude == "gps":
        args.folder = without_attitude(args.folder, work)
    orients = exif_orientations([args.folder])
    height = args.height if args.height is not None else takeoff_height(orients)
    if height is None:
        raise SystemExit("give --height: the images carry no AbsoluteAltitude and RelativeAltitude")
    report = dict(folder=os.path.abspath(source_folder), images=len(orients), attitude_source=args.attitude,
                  images_read=os.path.abspath(args.folder), height_m=height,
                  height_source="--height" if args.height is not None else "take-off point (AbsoluteAltitude - "
                                                                            "RelativeAltitude, median)",
                  resolution_m=args.resolution, device=args.device, work=work, chain_settings=settings,
                  cameras=sorted({o.camera_id for o in orients}), camera_source=orients[0].camera_source,
                  attitude={a: sum(o.attitude == a for o in orients) for a in ("gimbal", "flight line")})
    print(f"{len(orients)} images; terrain height {height:.2f} m ({report['height_source']})")
    if args.oty:
        report["orthority"] = compare_with_orthority(orients, args.oty, work)
    common = ["--height", height, "--resolution", args.resolution, "--device", args.device, "--overwrite"]
    exif = ["--exif", "--exif-heading", args.heading]
    report["heading"] = args.heading
    if not args.no_mosaic:
        secs, lines = cli("mosaic", args.folder, *exif, "-o", os.path.join(work, "mosaic_exif.tif"), "--index",
                          os.path.join(work, "mosaic_exif_index.tif"), *common)
        report["mosaic_exif"] = dict(seconds=secs, output=lines)
        print(f"mosaic from the folder in one command: {secs:.1f} s; {lines[-1][:160]}")
    secs, lines = orthos(os.path.join(work, "orthos_exif"), common, args.folder, *exif, reuse=args.reuse)
    report["orthos_exif"] = dict(seconds=secs, read=[ln for ln in lines if ln.startswith("EXIF")], **overlap_summary(
        os.path.join(work, "orthos_exif"), args.resolution, f"overlaps, EXIF orientation (heading: {args.heading})"))
    if args.adjust:
        mosaic = os.path.join(work, "mosaic_adjusted.tif")
        adj = os.path.splitext(mosaic)[0] + "_adjust"
        chain_common = common[2:] if args.chain_surface else common  # (no --height: the chain's own terrain)
        secs, lines = (None, []) if args.reuse and os.path.exists(os.path.join(adj, "chain.json")) else \
            cli("mosaic", args.folder, *exif, "--adjust", "-o", mosaic, *chain_common, settings=settings)
        with open(os.path.join(adj, "chain.json")) as f:
            chain = json.load(f)
        report["chain"] = dict(seconds=secs, folder=adj, report=chain,
                               output=[ln for ln in lines if ln.startswith(("adjust", "densify", "terrain"))])
        print("\n".join(ln for ln in lines if ln.startswith(("adjust", "densify", "terrain"))))
        unmatched = set(chain.get("unmatched", []))  # (kept their EXIF orientation: not in exterior.csv)
        images = [o.image for o in orients if os.path.splitext(os.path.basename(o.image))[0] not in unmatched]
        orient_args = ["--int-param", os.path.join(adj, "cameras.yaml"),
                       "--ext-param", os.path.join(adj, "exterior.csv")]
        if args.chain_surface:
            terrain = chain["terrain"]
            steps = dict(matching=chain["match"]["seconds"], adjustment=chain["adjust"]["seconds"],
                         ties_surface=terrain.get("ties_surface", terrain["surface"]).get("seconds"),
                         densify=chain.get("densify", {}).get("seconds"),
                         surface=terrain["surface"].get("seconds") if "ties_surface" in terrain else None,
                         chain_and_mosaic_command=secs)
            folder = os.path.join(work, "orthos_adjusted_chain_surface")
            secs, _ = orthos(folder, ["--dem", os.path.join(adj, "tie_surface.tif"), *common[2:]], *images,
                             *orient_args, reuse=args.reuse)
            steps["orthos"] = secs
            s = terrain["surface"]
            d = chain.get("densify")
            label = (f"overlaps, adjusted orientation on the chain's surface ({s['points_used']} points, "
                     f"{s['smoothing_length_m']:.2f} m{', with dense points' if d else ''})")
            report["orthos_adjusted_chain_surface"] = dict(seconds=secs, surface=s, dense=dict(
                {k: v for k, v in d.items() if k != "per_pair"}) if d else None, step_seconds=steps,
                **overlap_summary(folder, args.resolution, label))
            print("step seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in steps.items() if v is not None))
            save_report(report, args.out)
            print(f"report: {args.out}")
            return
        secs, _ = orthos(os.path.join(work, "orthos_adjusted"), common, *images, *orient_args, reuse=args.reuse)
        report["orthos_adjusted"] = dict(seconds=secs, **overlap_summary(
            os.path.join(work, "orthos_adjusted"), args.resolution, "overlaps, adjusted orientation"))
        tie_h = chain["adjust"]["tie_height_m"]["median"]
        common_t = ["--height", tie_h, *common[2:]]
        secs, _ = orthos(os.path.join(work, "orthos_adjusted_tieh"), common_t, *images, *orient_args,
                         reuse=args.reuse)
        common_e = ["--height", tie_h, *common[2:]]
        secs_e, _ = orthos(os.path.join(work, "orthos_exif_tieh"), common_e, args.folder, *exif, reuse=args.reuse)
        report["orthos_exif_tie_height"] = dict(seconds=secs_e, height_m=tie_h, **overlap_summary(
            os.path.join(work, "orthos_exif_tieh"), args.resolution,
            f"overlaps, EXIF orientation on the ties' median height {tie_h:.2f} m"))
        report["orthos_adjusted_tie_height"] = dict(seconds=secs, height_m=tie_h, **overlap_summary(
            os.path.join(work, "orthos_adjusted_tieh"), args.resolution,
            f"overlaps, adjusted orientation on the ties' median height {tie_h:.2f} m"))
        report["relief_at_ties"] = relief_parallax(adj, args.resolution,
                                                   [("--height", height), ("ties' median", tie_h)])
        if args.tie_dem:
            dem = os.path.join(work, f"tie_surface_{args.tie_dem:g}m.tif")
            surface = tie_surface(adj, dem, args.tie_dem)
            common_d = ["--dem", dem, *common[2:]]
            folder = os.path.join(work, f"orthos_adjusted_tie_surface_{args.tie_dem:g}m")
            secs, _ = orthos(folder, common_d, *images, *orient_args, reuse=args.reuse)
            report["orthos_adjusted_tie_surface"] = dict(seconds=secs, surface=surface, **overlap_summary(
                folder, args.resolution, f"overlaps, adjusted orientation on the ties' surface ({args.tie_dem:g} m, "
                                         f"{surface['min_m']:.2f}..{surface['max_m']:.2f} m)"))
        if args.dem:
            dem = args.dem
            if os.path.splitext(dem)[1].lower() in (".las", ".laz"):
                dem = laz_dsm(dem, os.path.join(work, "dsm_from_cloud.tif"))
            at_ties = dem_at_ties(adj, dem)
            report["dem"] = dict(given=os.path.abspath(args.dem), **describe_dem(dem), ties_minus_dem_m=at_ties)
            print(f"DEM {dem}: {report['dem']['crs']}, vertical {report['dem']['vertical_crs']}; adjusted tie points "
                  f"minus the DEM: median {at_ties['median']:+.3f} m, quartiles {at_ties['p25']:+.3f}, "
                  f"{at_ties['p75']:+.3f} m ({at_ties['points']} points)")
            runs = [("orthos_exif_dem", "EXIF orientation", dem, [args.folder, *exif]),
                    ("orthos_adjusted_dem", "adjusted orientation", dem, [*images, *orient_args])]
            moved = shifted_dem(dem, os.path.join(work, "dem_at_ties.tif"), at_ties["median"])
            runs.append(("orthos_adjusted_dem_at_ties", f"adjusted orientation, DEM {at_ties['median']:+.3f} m",
                         moved, [*images, *orient_args]))
            for key, label, path, inputs in runs:
                folder = os.path.join(work, key)
                secs, _ = orthos(folder, ["--dem", path, *common[2:]], *inputs, reuse=args.reuse)
                report[key] = dict(seconds=secs, dem=path, **overlap_summary(folder, args.resolution,
                                                                             f"overlaps, {label} on the DEM"))
    save_report(report, args.out)
    print(f"report: {args.out}")


if __name__ == "__main__":
    main()
