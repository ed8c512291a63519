"""Predicted-accuracy rasters of orthoimages: the precision of each ground position by error
propagation (:mod:`orthowarp.adjust.precision`, [P4]) on a grid aligned with the ortho.

For every ``step`` x ``step`` cell of the ortho's grid, the ground point at the cell's centre
(its height from the DEM, the DEM's slope from its bilinear surface) is projected into the
image; where the image sees it, its covariance from one image on the DEM
(:func:`~orthowarp.adjust.precision.monoplot_covariance`) is turned into the output CRS (the
horizontal part through the Jacobian of the pose CRS -> output CRS transformation) and written
as three float32 bands: sigma east, sigma north, sigma up (m; NaN where the image does not see
the point). The raster's pixels are ``step`` ortho pixels, with the ortho's origin.
"""

import numpy as np
from affine import Affine
from pyproj import Transformer

from ..adjust import collinearity as col
from ..adjust.precision import _camera_row, _pose_row, monoplot_covariance
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
        A photogrammetric (omega-phi-kappa) pose.
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
    _pose_row(pose)  # photogrammetric poses only (clear error otherwise)
    rows, cols = -(-shape[0] // step), -(-shape[1] // step)
    grid = transform @ Affine.scale(step)
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    ox, oy = grid @ (jj.ravel(), ii.ravel())
    ox, oy = np.asarray(ox, dtype=np.float64), np.asarray(oy, dtype=np.float64)
    to_pose = Transformer.from_crs(crs, pose.crs, always_xy=True)
    px, py = (np.asarray(v, dtype=np.float64) for v in to_pose.transform(ox, oy))
    terrain = dem.for_frame(pose.crs)
    h = terrain.sample(px, py)
    if terrain.is_constant:
        slopes = np.zeros((len(px), 2))
    else:  # the bilinear surface's slope: central differences over a tenth of a cell
        d = 0.1 * min(abs(terrain.transform.a), abs(terrain.transform.e))
        slopes = np.stack([(terrain.sample(px + d, py) - terrain.sample(px - d, py)) / (2 * d),
                           (terrain.sample(px, py + d) - terrain.sample(px, py - d)) / (2 * d)], -1)
    pts = np.stack([px, py, h], -1)
    ok = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(slopes), axis=1)
    if ok.any():  # seen by the image: in front of it and inside its frame
        n = int(ok.sum())
        pix = col.project(np.broadcast_to(_pose_row(pose), (n, 6)), pts[ok],
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
        # the horizontal covariance in the output CRS: J C J^T, J = d(out x, y)/d(pose x, y)
        to_out = Transformer.from_crs(pose.crs, crs, always_xy=True)
        e = 1.0
        x, y = pts[ok, 0], pts[ok, 1]
        dxe = np.stack(to_out.transform(x + e, y), -1) - np.stack(to_out.transform(x - e, y), -1)
        dye = np.stack(to_out.transform(x, y + e), -1) - np.stack(to_out.transform(x, y - e), -1)
        jac = np.stack([dxe, dye], -1) / (2 * e)  # (n, 2 out, 2 pose)
        horizontal = jac @ cov[:, :2, :2] @ np.transpose(jac, (0, 2, 1))
        out[0, ok] = np.sqrt(np.maximum(horizontal[:, 0, 0], 0.0))
        out[1, ok] = np.sqrt(np.maximum(horizontal[:, 1, 1], 0.0))
        out[2, ok] = np.sqrt(np.maximum(cov[:, 2, 2], 0.0))
    out = out.reshape(3, rows, cols)
    write_raster(dst, out, transform=grid, crs=crs.to_wkt(), nodata=np.nan)
    return out
