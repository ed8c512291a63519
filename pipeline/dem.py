"""Digital elevation models (:class:`Dem`): reading, reprojection, cropping, packing."""

import math
import os
import warnings

import numpy as np
import rasterio
import rasterio.warp
import warp as wp
from affine import Affine
from rasterio.errors import RasterioIOError

from .._validate import as_crs, finite
from ..errors import CrsError, ParamError, RasterIOError
from ..kernels.dem import DemData

__all__ = ["Dem"]

GEOGRAPHIC = "EPSG:4326"
BLOCK = 8  # cells per block of the ray-marching bounds


class Dem:
    """A north-up grid of ellipsoidal heights, or a constant height.

    Parameters
    ----------
    array : array_like, shape (rows, cols)
        Heights (m). NaN (or ``nodata``) marks cells without data.
    transform : affine.Affine or sequence of 6 floats
        Pixel-corner affine transform (rasterio order a, b, c, d, e, f); no rotation.
    crs : str, int or pyproj.CRS
        Horizontal CRS of the grid.
    nodata : float, optional
        Value marking cells without data.

    Notes
    -----
    Heights are taken as ellipsoidal (WGS84) in geocentric mode and as the z of map-Cartesian
    poses in map mode. Sampling is bilinear between cell centres.
    """

    def __init__(self, array, transform, crs, *, nodata=None):
        arr = np.array(array, dtype=np.float32)  # a copy: the caller's array is never modified
        if arr.ndim != 2 or min(arr.shape) < 1:
            raise ParamError(f"DEM array must be 2-D and non-empty, got shape {arr.shape}")
        if nodata is not None and not (isinstance(nodata, float) and math.isnan(nodata)):
            arr[arr == np.float32(nodata)] = np.nan
        arr[~np.isfinite(arr)] = np.nan
        if not np.any(np.isfinite(arr)):
            raise ParamError("DEM has no valid heights")
        try:
            t = transform if isinstance(transform, Affine) else Affine(*transform)
        except (TypeError, ValueError) as e:
            raise ParamError(f"DEM transform must be an affine transform: {e}") from e
        if t.b != 0.0 or t.d != 0.0 or t.a == 0.0 or t.e == 0.0:
            raise ParamError(f"DEM transform must be north-up without rotation, got {tuple(t)[:6]}")
        self.array = arr
        self.transform = t
        self.crs = as_crs(crs, "DEM crs")
        self.source = None  # the file it was read from, for messages
        self.value = None
        self.hmin = float(np.nanmin(arr))
        self.hmax = float(np.nanmax(arr))

    @classmethod
    def constant(cls, height):
        """A DEM of constant height (m) everywhere."""
        h = finite("height", height)
        dem = cls.__new__(cls)
        dem.array = np.full((1, 1), h, dtype=np.float32)
        dem.transform = Affine.identity()
        dem.crs = None
        dem.source = None
        dem.value = h
        dem.hmin = dem.hmax = h
        return dem

    @classmethod
    def from_file(cls, path, *, band=1):
        """Read a DEM band from a raster file (GeoTIFF or anything GDAL reads).

        Raises
        ------
        RasterIOError
            The file does not exist or cannot be read.
        CrsError
            The file has no CRS.
        """
        path = os.fspath(path)
        if not os.path.exists(path):
            raise RasterIOError(f"DEM file '{path}' does not exist")
        try:
            with rasterio.open(path) as src:
                if src.crs is None:
                    raise CrsError(f"DEM file '{path}' has no coordinate reference system")
                if band < 1 or band > src.count:
                    raise ParamError(f"DEM file '{path}' has no band {band}")
                arr = src.read(band, out_dtype="float32")
                nodata, transform, crs = src.nodata, src.transform, src.crs.to_wkt()
        except RasterioIOError as e:
            raise RasterIOError(f"Could not read DEM file '{path}': {e}") from e
        try:
            dem = cls(arr, transform, crs, nodata=nodata)
        except ParamError as e:
            raise ParamError(f"DEM file '{path}': {e}") from e
        dem.source = path
        return dem

    @property
    def is_constant(self):
        return self.value is not None

    @property
    def shape(self):
        return self.array.shape

    def __repr__(self):
        if self.is_constant:
            return f"Dem.constant({self.value!r})"
        return f"Dem(shape={self.shape}, crs={self.crs.to_string()!r}, heights=[{self.hmin:.1f}, {self.hmax:.1f}])"

    def sample(self, x, y):
        """Bilinear heights (m) at horizontal coordinates x, y of the DEM's CRS (host, float64).

        Same rule as the kernels: between cell centres, NaN outside the grid or next to
        nodata. Returns an array of the broadcast shape of x and y.
        """
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        if self.is_constant:
            return np.full(x.shape, self.value)
        rows, cols = self.shape
        t = self.transform
        gx = (x - t.c) / t.a - 0.5
        gy = (y - t.f) / t.e - 0.5
        inside = (gx >= -0.5) & (gy >= -0.5) & (gx <= cols - 0.5) & (gy <= rows - 0.5)
        gx = np.clip(np.nan_to_num(gx), 0.0, cols - 1)
        gy = np.clip(np.nan_to_num(gy), 0.0, rows - 1)
        j = np.minimum(gx.astype(int), max(cols - 2, 0))
        i = np.minimum(gy.astype(int), max(rows - 2, 0))
        j1, i1 = np.minimum(j + 1, cols - 1), np.minimum(i + 1, rows - 1)
        ax, ay = gx - j, gy - i
        z = self.array.astype(np.float64)
        h = ((1 - ay) * ((1 - ax) * z[i, j] + ax * z[i, j1]) + ay * ((1 - ax) * z[i1, j] + ax * z[i1, j1]))
        return np.where(inside, h, np.nan)

    # -- preparation for the kernels ------------------------------------------------------------
    def for_frame(self, crs):
        """This DEM on a grid in the horizontal coordinates of a geometry frame.

        Parameters
        ----------
        crs : pyproj.CRS or None
            The map CRS of map-Cartesian poses, or None for geocentric poses (longitude and
            latitude in degrees on WGS84).

        Returns
        -------
        Dem
            ``self`` when the grid already is in those coordinates, else a bilinear reprojection
            at about the same resolution.
        """
        if self.is_constant:
            return self
        if crs is None:
            if self.crs.is_geographic and _is_wgs84(self.crs):
                return self
            return self.reproject(GEOGRAPHIC)
        if self.crs.equals(crs, ignore_axis_order=True) or _horizontal(self.crs).equals(_horizontal(crs), ignore_axis_order=True):
            return self
        return self.reproject(crs)

    def reproject(self, crs):
        """Bilinear reprojection onto a north-up grid in ``crs`` (pyproj/rasterio CRS)."""
        dst_crs = rasterio.crs.CRS.from_user_input(_horizontal(as_crs(crs)).to_wkt())
        src_crs = rasterio.crs.CRS.from_user_input(_horizontal(self.crs).to_wkt())
        rows, cols = self.shape
        bounds = rasterio.transform.array_bounds(rows, cols, self.transform)
        transform, width, height = rasterio.warp.calculate_default_transform(
            src_crs, dst_crs, cols, rows, *bounds)
        out = np.full((height, width), np.nan, dtype=np.float32)
        rasterio.warp.reproject(self.array, out, src_transform=self.transform, src_crs=src_crs,
                                src_nodata=np.nan, dst_transform=transform, dst_crs=dst_crs,
                                dst_nodata=np.nan, resampling=rasterio.warp.Resampling.bilinear)
        return Dem(out, transform, crs)

    def window(self, xmin, ymin, xmax, ymax, *, margin=2):
        """Cell index ranges (i0, i1, j0, j1) covering the given bounds plus ``margin`` cells,
        clipped to the grid; None where they leave it."""
        rows, cols = self.shape
        inv = ~self.transform
        corners = np.array([inv @ (x, y) for x in (xmin, xmax) for y in (ymin, ymax)])
        j0 = max(int(math.floor(corners[:, 0].min())) - margin, 0)
        j1 = min(int(math.ceil(corners[:, 0].max())) + margin, cols)
        i0 = max(int(math.floor(corners[:, 1].min())) - margin, 0)
        i1 = min(int(math.ceil(corners[:, 1].max())) + margin, rows)
        if j1 <= j0 or i1 <= i0:
            return None
        return i0, i1, j0, j1

    def crop(self, xmin, ymin, xmax, ymax, *, margin=2):
        """The part of the grid covering the given bounds plus ``margin`` cells, or None if none."""
        if self.is_constant:
            return self
        win = self.window(xmin, ymin, xmax, ymax, margin=margin)
        if win is None:
            return None
        i0, i1, j0, j1 = win
        sub = self.array[i0:i1, j0:j1]
        if not np.any(np.isfinite(sub)):
            return None
        return Dem(sub, self.transform @ Affine.translation(j0, i0), self.crs)

    def block_bounds(self, block=BLOCK):
        """Upper bounds of sampled heights per block of ``block`` x ``block`` cells (float32).

        Entry (I, J) bounds the bilinear height at any grid point within ``block`` cells of
        block (I, J): the maximum over the block grown by ``block + 1`` cells on every side
        (nodata and cells beyond the border count as no terrain, -inf; see
        :class:`orthowarp.kernels.dem.DemData`).
        """
        rows, cols = self.shape
        nbi, nbj = -(-rows // block), -(-cols // block)
        grow = block + 1
        padded = np.full((nbi * block + 2 * grow, nbj * block + 2 * grow), -np.inf, dtype=np.float32)
        padded[grow:grow + rows, grow:grow + cols] = np.where(np.isfinite(self.array), self.array, -np.inf)
        # running maximum over windows of 3 block + 2 cells, taken at block starts
        win = 3 * block + 2
        colmax = np.lib.stride_tricks.sliding_window_view(padded, win, axis=1)[:, ::block][:, :nbj].max(axis=2)
        return np.ascontiguousarray(
            np.lib.stride_tricks.sliding_window_view(colmax, win, axis=0)[::block][:nbi].max(axis=2))

    def block_range(self, block=32):
        """Lowest and highest height per block of ``block`` x ``block`` cells (float32, NaN
        where a block has none), for bounding the heights under a region cheaply."""
        rows, cols = self.shape
        nbi, nbj = -(-rows // block), -(-cols // block)
        padded = np.full((nbi * block, nbj * block), np.nan, np.float32)
        padded[:rows, :cols] = self.array
        cells = padded.reshape(nbi, block, nbj, block)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # blocks without heights
            return np.nanmin(cells, axis=(1, 3)), np.nanmax(cells, axis=(1, 3))

    def to_struct(self, device):
        """Pack into :class:`orthowarp.kernels.dem.DemData` on ``device``."""
        s = DemData()
        s.data = wp.array(self.array, dtype=wp.float32, device=device)
        s.block = BLOCK
        s.bmax = wp.array(self.block_bounds() if not self.is_constant else np.zeros((1, 1), np.float32),
                          dtype=wp.float32, device=device)
        t = self.transform
        s.x0, s.dx, s.y0, s.dy = float(t.c), float(t.a), float(t.f), float(t.e)
        s.inv_dx, s.inv_dy = 1.0 / s.dx, 1.0 / s.dy
        s.constant = 1 if self.is_constant else 0
        s.value = float(self.value) if self.is_constant else 0.0
        s.hmin, s.hmax = self.hmin, self.hmax
        return s


def _is_wgs84(crs):
    ell = crs.ellipsoid
    return ell is not None and abs(ell.semi_major_metre - 6378137.0) < 1e-3 and abs(ell.inverse_flattening - 298.257223563) < 1e-6


def _horizontal(crs):
    """The horizontal part of a (possibly compound) CRS."""
    return crs.sub_crs_list[0] if crs.is_compound else crs
