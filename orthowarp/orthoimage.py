"""An already orthorectified image as a sensor: :class:`OrthoImage` (a
:class:`~orthowarp.sensor.SensorModel`), so that orthos made elsewhere (orthority's, GDAL's,
orthowarp's own) mosaic, or are reprojected onto another grid, by the same machinery as raw
images.

The image's ground -> image mapping is its CRS and affine geotransform: a ground point's
horizontal coordinates (x, y) in the image's CRS go to the pixel (col, row) = A^-1 ((x, y) -
origin), A the geotransform's matrix (``transform.a, b, d, e``) and origin (``transform.c, f``)
the corner of its top-left pixel. Heights play no part: the image lies on the ground already,
and the geometry (:class:`~orthowarp.pipeline.geometry.SensorGeometry`) gives it a constant
terrain of height 0 and no refraction whatever DEM it is handed. A grid in another CRS reaches
the image's through the exact PROJ transformation of the coarse grid's nodes (as for every
sensor's horizontal CRS), and the inverse geotransform runs per pixel on the device
(:mod:`orthowarp.kernels.orthoimage`); on a grid that coincides with the image's (the same CRS,
pixel size and alignment) nearest and bilinear resampling return its pixels exactly.

An orthoimage has no viewpoint: a mosaic's seams, which take each pixel from the image that
sees it most nearly from above, rank orthoimages by the ground distance from their valid data's
centre (:attr:`OrthoImage.centre`: the centroid of the valid pixels, the nadir of a near-vertical
frame) instead of an off-nadir angle.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from ._validate import image_size as image_size_pair
from .errors import CrsError, ParamError
from .sensor import SensorKernels, SensorModel, generic_kernels

if TYPE_CHECKING:
    import warp as wp
    from affine import Affine
    from numpy.typing import ArrayLike
    from pyproj import CRS

    from .kernels.orthoimage import OrthoData

__all__ = ["OrthoImage", "MapPositions", "MAX_SKEW"]

#: The largest relative skew (|a b + d e| / (|col axis| |row axis|), the cosine of the angle
#: between the pixel axes' directions on the ground) of a geotransform taken: rotated grids
#: are fine, sheared ones are refused beyond this.
MAX_SKEW = 1e-6


class MapPositions:
    """Positions in a map CRS (an orthoimage's, for
    :func:`orthowarp.pipeline.vertical.reconcile_dem`; the constant terrain an orthoimage's
    geometry takes needs no reconciling)."""

    mode = "map"

    def __init__(self, crs: CRS) -> None:
        self.crs = crs


def _horizontal(crs: Any, name: str) -> CRS:
    from ._validate import as_crs

    c = as_crs(crs, name)
    if c.is_compound:
        c = next((sub for sub in c.sub_crs_list if not sub.is_vertical), c)
    if c.is_geocentric or not (c.is_projected or c.is_geographic):
        raise CrsError(f"{name} must be a projected or geographic CRS for an orthoimage, got {c.name!r}")
    return c


def _affine(transform: Any, name: str) -> Affine:
    from affine import Affine

    if isinstance(transform, Affine):
        t = transform
    else:
        try:
            vals = [float(v) for v in transform]
        except (TypeError, ValueError) as e:
            raise ParamError(f"{name} must be an affine.Affine or its six numbers (a, b, c, d, e, f), "
                             f"got {transform!r}") from e
        if len(vals) not in (6, 9):
            raise ParamError(f"{name} must be an affine.Affine or its six numbers (a, b, c, d, e, f), "
                             f"got {len(vals)} numbers")
        t = Affine(*vals[:6])
    coeffs = (t.a, t.b, t.c, t.d, t.e, t.f)
    if not all(math.isfinite(v) for v in coeffs):
        raise ParamError(f"{name} holds NaN or infinite values: {coeffs}")
    det = t.a * t.e - t.b * t.d
    if det == 0.0:
        raise ParamError(f"{name} is singular (a e - b d = 0): {coeffs}")
    norm = math.hypot(t.a, t.d) * math.hypot(t.b, t.e)
    if abs(t.a * t.b + t.d * t.e) > MAX_SKEW * norm:
        raise ParamError(f"{name} is sheared (its pixel axes are not perpendicular on the ground): {coeffs}; "
                         "orthoimages take north-up or rotated geotransforms")
    return t


class OrthoImage(SensorModel):
    """An already orthorectified image: its CRS and geotransform are its ground -> image mapping
    (see the module doc), a :class:`~orthowarp.sensor.SensorModel`.

    Parameters
    ----------
    crs : CRS-like
        The image's CRS, projected or geographic (a compound CRS's horizontal part is taken).
    transform : affine.Affine or 6 numbers
        Its geotransform (rasterio's ``transform``: x = a col + b row + c, y = d col + e row +
        f, from the corner of the top-left pixel); north-up or rotated, not sheared.
    image_size : (int, int)
        (width, height) in pixels.
    centre : (float, float), optional
        (x, y) in ``crs`` of its valid data's centre, for a mosaic's seams (default: the
        image's centre). :func:`orthowarp.pipeline.formats.orthos.read_ortho` gives the
        centroid of the valid pixels.
    source : str, optional
        The image's file (for messages).

    Raises
    ------
    CrsError
        A CRS that is neither projected nor geographic.
    ParamError
        A singular, sheared or non-finite geotransform, a bad size or centre.

    Notes
    -----
    Geo triples are (x, y) of ``crs`` and a height that plays no part; :attr:`geocentric` is
    False. An orthoimage has no pose (:attr:`pose` None) and no parameters an adjustment
    refines. Refraction and terrain are in the image already: its geometry reads neither.
    """

    kind = "ortho"
    noun = "orthoimage"
    forward_method = False
    line_timed = False
    orthorectified = True
    #: An orthoimage has no pose (no projection centre, no attitude).
    pose = None
    geocentric = False

    def __init__(self, crs: Any, transform: Any, image_size: tuple[int, int], *,
                 centre: tuple[float, float] | None = None, source: str | None = None) -> None:
        self.crs = _horizontal(crs, "crs")
        self.transform = _affine(transform, "transform")
        w, h = image_size_pair(image_size)
        self._size = (w, h)
        if centre is None:
            centre = self.transform @ (0.5 * w, 0.5 * h)
        try:
            cx, cy = (float(v) for v in centre)
        except (TypeError, ValueError) as e:
            raise ParamError(f"centre must be (x, y), got {centre!r}") from e
        if not (math.isfinite(cx) and math.isfinite(cy)):
            raise ParamError(f"centre must be finite, got {centre!r}")
        self.centre = (cx, cy)
        self.source = source

    def __repr__(self) -> str:
        t = self.transform
        return (f"OrthoImage({self._size[0]} x {self._size[1]}, {self.crs.name!r}, pixel {t.a:.6g} x {t.e:.6g}"
                f"{', rotated' if t.b or t.d else ''}{', ' + repr(self.source) if self.source else ''})")

    image_size = property(lambda self: self._size, doc="(width, height) in pixels.")

    @property
    def resolution(self) -> tuple[float, float]:
        """The pixel's size on the ground (x, y) in CRS units: the lengths of the
        geotransform's column and row axes."""
        t = self.transform
        return math.hypot(t.a, t.d), math.hypot(t.b, t.e)

    @property
    def frame_crs(self) -> CRS:
        """The image's CRS made 3-D (its heights play no part)."""
        return self.crs.to_3d()

    @property
    def horizontal_crs(self) -> CRS:
        """The image's CRS."""
        return self.crs

    @property
    def positions(self) -> MapPositions:
        """Map positions in the image's CRS."""
        return MapPositions(self.crs)

    def reference_height(self) -> float:
        """0: no sensor position; the geometry builds no refraction table for an orthoimage."""
        return 0.0

    @property
    def kernels(self) -> SensorKernels:
        """The generic kernels (:func:`orthowarp.sensor.generic_kernels`)."""
        return generic_kernels()

    def _pack(self, device: wp.Device) -> OrthoData:
        import warp as wp

        from .kernels.orthoimage import OrthoData

        t, arg = self.transform, OrthoData()
        m = np.array([[t.a, t.b], [t.d, t.e]])
        arg.origin = wp.vec2d(t.c, t.f)
        arg.matrix = wp.mat22d(*m.ravel())
        arg.inverse = wp.mat22d(*np.linalg.inv(m).ravel())
        arg.axis_aligned = int(t.b == 0.0 and t.d == 0.0)
        return arg

    # -- host model ------------------------------------------------------------------------------

    def pixels(self, xy: ArrayLike) -> np.ndarray:
        """Horizontal coordinates (N, 2) of the image's CRS -> pixels (col, row) (N, 2), float64.

        Parameters
        ----------
        xy : array_like, shape (N, 2) or (2,)

        Returns
        -------
        ndarray, shape (N, 2)
        """
        from ._validate import points

        p = points(xy, 2, "xy")
        t = self.transform
        d = p - np.array([t.c, t.f])
        if t.b == 0.0 and t.d == 0.0:
            return np.stack([d[:, 0] / t.a, d[:, 1] / t.e], -1)
        return d @ np.linalg.inv(np.array([[t.a, t.b], [t.d, t.e]])).T

    def ground(self, pixels: ArrayLike) -> np.ndarray:
        """Pixels (col, row) (N, 2) -> horizontal coordinates (x, y) (N, 2) of the image's CRS.

        Parameters
        ----------
        pixels : array_like, shape (N, 2) or (2,)

        Returns
        -------
        ndarray, shape (N, 2)
        """
        from ._validate import points

        p = points(pixels, 2, "pixels")
        t = self.transform
        return np.stack([t.a * p[:, 0] + t.b * p[:, 1] + t.c, t.d * p[:, 0] + t.e * p[:, 1] + t.f], -1)

    def project(self, xyz: ArrayLike) -> np.ndarray:
        """Points (N, 3) of the image's CRS (x, y, any height) -> pixels (N, 2), float64.

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)

        Returns
        -------
        ndarray, shape (N, 2)
            Pixel (col, row); NaN rows for rows with NaN.
        """
        from ._validate import points

        return self.pixels(points(xyz, 3, "xyz")[:, :2])

    def project_jacobian(self, xyz: ArrayLike, *, wrt: tuple[str, ...] | None = None) -> tuple[np.ndarray, ...]:
        """:meth:`project` and its derivatives: none by parameters (an orthoimage has none), the
        inverse geotransform by the point (0 by the height).

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)
        wrt : tuple of str, optional
            Must be empty (or None).

        Returns
        -------
        pixels : ndarray, shape (N, 2)
        d_params : ndarray, shape (N, 2, 0)
        d_point : ndarray, shape (N, 2, 3)
        """
        from ._validate import points

        if wrt:
            self._check_names(wrt)
        pts = points(xyz, 3, "xyz")
        t = self.transform
        inv = np.linalg.inv(np.array([[t.a, t.b], [t.d, t.e]]))
        d_point = np.zeros((len(pts), 2, 3))
        d_point[:, :, :2] = inv
        pix = self.project(pts)
        d_point[~np.all(np.isfinite(pix), axis=1)] = np.nan
        return pix, np.zeros((len(pts), 2, 0)), d_point

    def parameters(self) -> dict[str, float]:
        """None: an orthoimage has no parameters an adjustment refines.

        Returns
        -------
        dict
            Empty.
        """
        return {}

    def with_parameters(self, **values: float) -> OrthoImage:
        """This orthoimage (it has no parameters: any name is refused).

        Parameters
        ----------
        **values : float
            None allowed.

        Returns
        -------
        OrthoImage
        """
        self._check_names(values)
        return self
