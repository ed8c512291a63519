"""Predicted-accuracy rasters of orthoimages: the precision of each ground position by error
propagation (:mod:`orthowarp.adjust.precision`, [P4]) on a grid aligned with the ortho.

For every ``step`` x ``step`` cell of the ortho's grid, the ground point at the cell's centre
(its height from the DEM, the DEM's slope from its bilinear surface) is projected into the
image; where the image sees it, its covariance from one image on the DEM
(:func:`~orthowarp.adjust.precision.monoplot_covariance`) is turned into the output CRS (the
horizontal part through the Jacobian of the transformation from the pose's map CRS, or from
the east-north-up frame of a GNSS/INS pose, to the output CRS) and written
as three float32 bands: sigma east, sigma north, sigma up (m; NaN where the image does not see
the point). The raster's pixels are ``step`` ortho pixels, with the ortho's origin.
"""

import numpy as np
from affine import Affine
from pyproj import Transformer

from ..adjust import collinearity as col
from ..adjust.precision import _camera_row, _Frame, monoplot_covariance
from ..errors import ParamError
from .io import write_raster

__all__ = ["accuracy_raster"]


def accuracy_raster(dst, camera, pose, dem, crs, transform, shape, *, pose_cov, pixel_sigma=0.5, camera_cov=None,
                    camera_params=(), dem_sigma=0.0, step=16):
    """Write the predicted accuracy of an ortho of one frame image.

    Parameters
    ----------
    dst : str or os.PathLike
        The raster (GeoTIFF, written atomically).
    camera : FrameCamera
    pose : Pose
        A photogrammetric (omega-phi-kappa) or GNSS/INS pose (see
        :mod:`orthowarp.adjust.precision` for the inputs ``pose_cov`` states).
    dem : Dem, str or float
        The terrain (any CRS): a Dem, a DEM file or a constant height (m).
    crs : pyproj.CRS
        The ortho's CRS.
    transform : affine.Affine
    shape : (int, int)
        The ortho's grid (rows, cols).
    pose_cov, pixel_sigma, camera_cov, camera_params, dem_sigma :
        As for :func:`~orthowarp.adjust.precision.monoplot_covariance`.
    step : int, optional
        Ortho pixels per accuracy pixel, each way.

    Returns
    -------
    ndarray (3, rows, cols) float32
        What was written.
    """
    from .dem import Dem

    if not isinstance(dem, Dem):
        dem = Dem.from_file(dem) if isinstance(dem, (str, bytes)) or hasattr(dem, "__fspath__") else \
            Dem.constant(float(dem))
    step = int(step)
    if step < 1:
        raise ParamError(f"step must be >= 1, got {step}")
    frame = _Frame([pose])  # photogrammetric or GNSS/INS (a clear error otherwise)
    row, _ = frame.pose(pose)
    geo = frame.local is not None
    rows, cols = -(-shape[0] // step), -(-shape[1] // step)
    grid = transform @ Affine.scale(step)
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    ox, oy = grid @ (jj.ravel(), ii.ravel())
    ox, oy = np.asarray(ox, dtype=np.float64), np.asarray(oy, dtype=np.float64)
    pose_crs = "EPSG:4326" if geo else pose.crs  # the points' horizontal coordinates: lon/lat, or map x/y
    to_pose = Transformer.from_crs(crs, pose_crs, always_xy=True)
    px, py = (np.asarray(v, dtype=np.float64) for v in to_pose.transform(ox, oy))
    terrain = dem.for_frame(None if geo else pose.crs)
    h = terrain.sample(px, py)
    if terrain.is_constant:
        slopes = np.zeros((len(px), 2))
    else:  # the bilinear surface's slope (per metre east and north for lon/lat grids)
        d = 0.1 * min(abs(terrain.transform.a), abs(terrain.transform.e))
        sx = sy = 2 * d
        if geo:  # degrees -> metres on the sphere of the mean radius (the slope to ~0.3 %)
            sx, sy = sx * np.radians(1.0) * 6371008.8 * np.cos(np.radians(py)), sy * np.radians(1.0) * 6371008.8
        slopes = np.stack([(terrain.sample(px + d, py) - terrain.sample(px - d, py)) / sx,
                           (terrain.sample(px, py + d) - terrain.sample(px, py - d)) / sy], -1)
    pts = np.stack([px, py, h], -1)
    ok = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(slopes), axis=1)
    if ok.any():  # seen by the image: in front of it and inside its frame
        n = int(ok.sum())
        pix = col.project(np.broadcast_to(row, (n, 6)), frame.points(pts[ok]),
                          np.broadcast_to(_camera_row(camera), (n, 10)),
                          np.broadcast_to(np.asarray(camera.image_size, np.float64), (n, 2)))
        w, hh = camera.image_size
        inside = np.all(np.isfinite(pix), axis=1) & (pix[:, 0] >= 0) & (pix[:, 0] <= w) & (pix[:, 1] >= 0) & (
            pix[:, 1] <= hh)
        ok[np.flatnonzero(ok)[~inside]] = False
    out = np.full((3, rows * cols), np.nan, np.float32)
    if ok.any():
        res = monoplot_covariance(camera, pose, pts[ok], slopes[ok], pose_cov=pose_cov, pixel_sigma=pixel_sigma,
                                  camera_cov=camera_cov, camera_params=camera_params, dem_sigma=dem_sigma)
        cov = res.cov
        # the horizontal covariance in the output CRS: J C J^T, J = d(out x, y)/d(frame x, y)
        # (the frame: the pose's map CRS, or the east-north-up frame of a GNSS/INS pose)
        local = frame.points(pts[ok])
        if geo:
            to_out = Transformer.from_crs("EPSG:4326", crs, always_xy=True)

            def out_xy(q):
                lla = frame.local.to_lla(q)
                return np.stack(to_out.transform(lla[:, 1], lla[:, 0]), -1)
        else:
            to_out = Transformer.from_crs(pose.crs, crs, always_xy=True)

            def out_xy(q):
                return np.stack(to_out.transform(q[:, 0], q[:, 1]), -1)

        e = 1.0
        ex, ny = np.array([e, 0.0, 0.0]), np.array([0.0, e, 0.0])
        jac = np.stack([out_xy(local + ex) - out_xy(local - ex), out_xy(local + ny) - out_xy(local - ny)], -1) / (2 * e)
        horizontal = jac @ cov[:, :2, :2] @ np.transpose(jac, (0, 2, 1))
        out[0, ok] = np.sqrt(np.maximum(horizontal[:, 0, 0], 0.0))
        out[1, ok] = np.sqrt(np.maximum(horizontal[:, 1, 1], 0.0))
        out[2, ok] = np.sqrt(np.maximum(cov[:, 2, 2], 0.0))
    out = out.reshape(3, rows, cols)
    write_raster(dst, out, transform=grid, crs=crs.to_wkt(), nodata=np.nan)
    return out
