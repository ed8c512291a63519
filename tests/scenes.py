"""DEM fixtures shared by the geometry and ortho tests: the same heights as an orthowarp.Dem
and as the independent reference's GridDem."""

import numpy as np
from affine import Affine

import orthowarp as ow
import reference as ref

UTM32 = "EPSG:32632"


def map_dem(func, xc, yc, ncols, nrows, cell, crs=UTM32):
    """(ow.Dem, ref.GridDem) of func(x - xc, y - yc) on a north-up grid centred at (xc, yc)."""
    x0, y0 = xc - ncols * cell / 2.0, yc + nrows * cell / 2.0
    xs = x0 + (np.arange(ncols) + 0.5) * cell
    ys = y0 - (np.arange(nrows) + 0.5) * cell
    z = func(xs[None, :] - xc, ys[:, None] - yc).astype(np.float32)
    return ow.Dem(z, Affine(cell, 0.0, x0, 0.0, -cell, y0), crs), ref.GridDem(z, x0, cell, y0, -cell)


def geo_dem(func, lonc, latc, ncells, cell_m):
    """(ow.Dem, ref.GridDem) in EPSG:4326 (lon/lat deg) of func(east m, north m) around lonc, latc."""
    my = 111132.0
    mx = 111320.0 * np.cos(np.radians(latc))
    dlat, dlon = cell_m / my, cell_m / mx
    lon0, lat0 = lonc - ncells * dlon / 2.0, latc + ncells * dlat / 2.0
    lons = lon0 + (np.arange(ncells) + 0.5) * dlon
    lats = lat0 - (np.arange(ncells) + 0.5) * dlat
    z = func((lons[None, :] - lonc) * mx, (lats[:, None] - latc) * my).astype(np.float32)
    return (ow.Dem(z, Affine(dlon, 0.0, lon0, 0.0, -dlat, lat0), "EPSG:4326"),
            ref.GridDem(z, lon0, dlon, lat0, -dlat))


def make_poses(kind, pose_kw):
    """(orthowarp Pose, reference RefPose) of the same pose.

    kind "ins": pose_kw has lat, lon, h, roll, pitch, yaw and optionally boresight, lever_arm;
    kind "opk": x, y, z, omega, phi, kappa, and optionally crs (default UTM 32N).
    """
    if kind == "ins":
        p = dict(pose_kw)
        bs, la = p.pop("boresight", (0.0, 0.0, 0.0)), p.pop("lever_arm", (0.0, 0.0, 0.0))
        args = [p[n] for n in ("lat", "lon", "h", "roll", "pitch", "yaw")]
        return ow.Pose.from_ins(*args, boresight=bs, lever_arm=la), ref.RefPose.ins(*args, boresight=bs, lever_arm=la)
    args = [pose_kw[n] for n in ("x", "y", "z", "omega", "phi", "kappa")]
    return ow.Pose.from_opk(*args, crs=pose_kw.get("crs", UTM32)), ref.RefPose.opk(*args)
