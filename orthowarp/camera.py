"""Frame camera interior orientation (:class:`FrameCamera`)."""

from __future__ import annotations

import math
import numbers
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from . import brown
from ._device import quiet_warp, resolve_device, to_host
from ._validate import finite as _finite
from ._validate import points as _as_points
from .errors import GeometryError, ParamError
from .kernels.camera import FrameCameraData, camera_to_pixel_kernel, pixel_to_camera_kernel

if TYPE_CHECKING:  # annotations only
    from numpy.typing import ArrayLike

__all__ = ["FrameCamera"]

# Plausibility bounds (see FrameCamera._check_plausible): they catch unit mix-ups (a focal
# length in metres or micrometres, a pixel pitch in micrometres) before they turn into a
# misleading geometry message downstream.
MAX_FOCAL_LENGTH = 1e6  # mm (1 km; the longest Earth-imaging telescopes have ~10-60 m)
MIN_PIXEL_ANGLE = 1e-8  # rad (2 milliarcseconds): pixel_size / focal_length
MAX_OFF_AXIS = 85.0  # deg: the image corner farthest from the principal point
MAX_IMAGE_SIDE = 2**31 - 1  # pixels: Warp launches index with 32-bit integers
# The most a lens's distortion may move an image point, as a fraction of its (undistorted)
# distance from the principal point: strong wide-angle lenses stay within ~0.3.
MAX_DISTORTION = 0.5


def _focal_length(value: float) -> float:
    """The focal length (mm) as a float: finite, > 0 and at most MAX_FOCAL_LENGTH."""
    f = _finite("focal_length", value)
    if f <= 0.0:
        raise ParamError(f"focal_length must be > 0 mm, got {value!r}")
    if f > MAX_FOCAL_LENGTH:
        raise ParamError(f"focal_length {f:g} mm is implausible: more than {MAX_FOCAL_LENGTH:g} mm (1 km); "
                         "focal lengths are in mm")
    return f


def _image_side(name: str, v: float) -> int:
    """A positive integer image dimension (integral floats such as 4000.0 are accepted)."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (numbers.Integral, numbers.Real)):
        raise ParamError(f"{name} must be an integer number of pixels, got {v!r}")
    if isinstance(v, numbers.Integral):
        n = int(v)
    else:
        f = float(v)
        if not math.isfinite(f) or not f.is_integer():
            raise ParamError(f"{name} must be an integer number of pixels, got {v!r}")
        n = int(f)
    if not 1 <= n <= MAX_IMAGE_SIDE:
        raise ParamError(f"{name} must be between 1 and {MAX_IMAGE_SIDE} pixels, got {v!r}")
    return n


class FrameCamera:
    """Interior orientation of a frame camera (PATB axes, OpenCV-normalised Brown distortion).

    Parameters
    ----------
    focal_length : float
        Focal length (mm), > 0.
    pixel_size : float or (float, float)
        Pixel pitch (mm) in x and y, > 0.
    image_size : (int, int)
        (width, height) in pixels.
    principal_point : (float, float), optional
        Principal point offset (mm) from the image centre, x right, y up.
    k1, k2, k3, p1, p2 : float, optional
        Brown-Conrady coefficients acting on OpenCV-normalised coordinates
        ``(u, v) = (x / f, -y / f)``, undistorted -> distorted (as OpenCV, OpenSfM, ODM and
        orthority define them). Use :meth:`from_mm_coefficients` for mm-based y-up sets.

    Raises
    ------
    ParamError
        A parameter is not finite or out of range, or the parameters describe no camera: a
        focal length over 1 km, a pixel subtending less than 1e-8 rad, an image corner more
        than 85 deg off the optical axis (usually a unit mix-up: all lengths are in mm), an
        image size that is not a positive integer.
    GeometryError
        The distortion cannot be inverted everywhere in the image, or moves an image point by
        more than ``MAX_DISTORTION`` (half) of its distance from the principal point (no lens
        does: the coefficient is likely in other units).

    Notes
    -----
    Pixel (col, row) coordinates have their origin at the top-left corner of the top-left
    pixel; the centre of pixel (i, j) is (j + 0.5, i + 0.5). The undistorted ray of an image
    point (x, y) is (x, y, -f) in the camera frame (x right, y up, z backwards).
    """

    def __init__(self, focal_length: float, pixel_size: float | tuple[float, float], image_size: tuple[int, int], *,
                 principal_point: tuple[float, float] = (0.0, 0.0), k1: float = 0.0, k2: float = 0.0,
                 k3: float = 0.0, p1: float = 0.0, p2: float = 0.0) -> None:
        self.focal_length = _focal_length(focal_length)
        try:
            ps = np.broadcast_to(np.asarray(pixel_size, dtype=np.float64), (2,)).copy()
        except (TypeError, ValueError) as e:
            raise ParamError(f"pixel_size must be a number or (x, y) in mm, got {pixel_size!r}") from e
        if not np.all(np.isfinite(ps)) or np.any(ps <= 0.0):
            raise ParamError(f"pixel_size must be finite and > 0 mm, got {pixel_size!r}")
        self.pixel_size = (float(ps[0]), float(ps[1]))
        try:
            size = tuple(image_size)
        except TypeError as e:
            raise ParamError(f"image_size must be (width, height), got {image_size!r}") from e
        if len(size) != 2 or isinstance(image_size, (str, bytes)):
            raise ParamError(f"image_size must be (width, height), got {image_size!r}")
        self.image_size = (_image_side("image_size width", size[0]), _image_side("image_size height", size[1]))
        try:
            pp = tuple(principal_point)
        except TypeError as e:
            raise ParamError(f"principal_point must be (x0, y0) in mm, got {principal_point!r}") from e
        if len(pp) != 2:
            raise ParamError(f"principal_point must be (x0, y0) in mm, got {principal_point!r}")
        self.principal_point = tuple(_finite("principal_point", v) for v in pp)
        self._check_plausible()
        self.k1, self.k2, self.k3 = (_finite(n, v) for n, v in (("k1", k1), ("k2", k2), ("k3", k3)))
        self.p1, self.p2 = (_finite(n, v) for n, v in (("p1", p1), ("p2", p2)))
        self._check_invertible()

    @classmethod
    def from_mm_coefficients(cls, focal_length: float, pixel_size: float | tuple[float, float],
                             image_size: tuple[int, int], *, principal_point: tuple[float, float] = (0.0, 0.0),
                             k1: float = 0.0, k2: float = 0.0, k3: float = 0.0, p1: float = 0.0, p2: float = 0.0,
                             decentring: str = "fraser") -> FrameCamera:
        """Build from Brown coefficients in mm units for a y-up image frame ([P3]'s eq. 2).

        Parameters
        ----------
        focal_length, pixel_size, image_size, principal_point :
            As for :class:`FrameCamera` (mm, mm, pixels, mm).
        k1, k2, k3 : float, optional
            Radial coefficients, mm^-2, mm^-4, mm^-6.
        p1, p2 : float, optional
            Decentring coefficients, mm^-1, in the order ``decentring`` names.
        decentring : {"fraser", "opencv"}, optional
            Which decentring term each coefficient carries. "fraser" (default: the
            Fraser/Australis order of [P3]'s eq. 2, and of most photogrammetric calibration
            reports), with x, y in mm from the principal point, y up, r^2 = x^2 + y^2::

                dx = x (k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 x^2) + 2 p2 x y
                dy = y (k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 y^2)

            "opencv": the order OpenCV (and this class's normalised coefficients) use, p1 and p2
            exchanged::

                dx = x (k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
                dy = y (k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

        Notes
        -----
        The class applies (dx, dy) as forward distortion: a ray's undistorted image point (x, y)
        lands at (x + dx, y + dy). [P3] writes its model as the correction of a measured
        (distorted) point; the two readings agree to first order in the distortion only (they
        differ by terms in the products of coefficients: for a calibration estimated as a
        correction, re-estimate it as forward distortion, or expect differences of the order of
        the distortion times its gradient). The conversion to normalised coefficients is exact
        for the forward model: ``k1n = k1 f^2``, ``k2n = k2 f^4``, ``k3n = k3 f^6`` and, in
        OpenCV's order, ``p1n = -p1 f``, ``p2n = p2 f`` (the sign from the y-down normalised
        frame).
        """
        if decentring not in ("fraser", "opencv"):
            raise ParamError(f"decentring must be 'fraser' or 'opencv', got {decentring!r}")
        if decentring == "fraser":
            p1, p2 = p2, p1
        f = _focal_length(focal_length)
        mm = {n: _finite(n, v) for n, v in (("k1", k1), ("k2", k2), ("k3", k3), ("p1", p1), ("p2", p2))}
        powers = {"k1": f**2, "k2": f**4, "k3": f**6, "p1": -f, "p2": f}
        norm = {}
        for n, v in mm.items():
            norm[n] = v * powers[n]
            if not math.isfinite(norm[n]):
                raise ParamError(f"{n}={v:g} (mm units) with focal_length {f:g} mm is beyond the range of "
                                 "normalised coefficients")
        return cls(focal_length, pixel_size, image_size, principal_point=principal_point, **norm)

    def __repr__(self) -> str:
        return (f"FrameCamera(focal_length={self.focal_length!r}, pixel_size={self.pixel_size!r}, "
                f"image_size={self.image_size!r}, principal_point={self.principal_point!r}, "
                f"k1={self.k1!r}, k2={self.k2!r}, k3={self.k3!r}, p1={self.p1!r}, p2={self.p2!r})")

    @property
    def has_distortion(self) -> bool:
        """True when any of the Brown coefficients k1, k2, k3, p1, p2 is non-zero."""
        return any(v != 0.0 for v in (self.k1, self.k2, self.k3, self.p1, self.p2))

    # -- host reference (float64 NumPy) ------------------------------------------------------
    def distort(self, uv: ArrayLike) -> np.ndarray:
        """Undistorted -> distorted normalised coordinates, (N, 2) -> (N, 2), closed form.

        Parameters
        ----------
        uv : array_like, shape (N, 2) (or (..., 2))
            Undistorted OpenCV-normalised (u, v) (dimensionless: image coordinates over f).

        Returns
        -------
        ndarray, shape of ``uv``
            Distorted normalised (ud, vd), float64.
        """
        return brown.distort(uv, self.k1, self.k2, self.k3, self.p1, self.p2)[0]

    def _jacobian(self, uv: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        j = brown.distort(uv, self.k1, self.k2, self.k3, self.p1, self.p2)[1]
        return j[..., 0, 0], j[..., 0, 1], j[..., 1, 0], j[..., 1, 1]

    def undistort(self, uvd: ArrayLike, *, iterations: int = 30) -> np.ndarray:
        """Distorted -> undistorted normalised coordinates, (N, 2) -> (N, 2), Newton's method.

        Parameters
        ----------
        uvd : array_like, shape (N, 2) (or (..., 2))
            Distorted OpenCV-normalised (ud, vd).
        iterations : int, optional
            Most Newton steps; the iteration stops earlier once every step is below 1e-15.

        Returns
        -------
        ndarray, shape of ``uvd``
            Undistorted normalised (u, v), float64.
        """
        uvd = np.asarray(uvd, dtype=np.float64)
        uv = uvd.copy()
        for _ in range(iterations):
            f = self.distort(uv) - uvd
            j00, j01, j10, j11 = self._jacobian(uv)
            det = j00 * j11 - j01 * j10
            step = np.stack([(j11 * f[..., 0] - j01 * f[..., 1]) / det,
                             (j00 * f[..., 1] - j10 * f[..., 0]) / det], axis=-1)
            uv = uv - step
            if np.all(np.abs(step) < 1e-15):
                break
        return uv

    def pixel_to_normalized(self, pixels: ArrayLike) -> np.ndarray:
        """Pixel (col, row) (N, 2) -> distorted normalised (u, v) (N, 2).

        Parameters
        ----------
        pixels : array_like, shape (N, 2) (or (..., 2))
            Pixel (col, row), origin at the top-left corner of the top-left pixel.

        Returns
        -------
        ndarray, shape of ``pixels``
            Distorted OpenCV-normalised (u, v), float64.
        """
        return brown.pixel_to_normalized(pixels, self.focal_length, self.principal_point, self.pixel_size,
                                         self.image_size)

    def normalized_to_pixel(self, uv: ArrayLike) -> np.ndarray:
        """Distorted normalised (u, v) (N, 2) -> pixel (col, row) (N, 2).

        Parameters
        ----------
        uv : array_like, shape (N, 2) (or (..., 2))
            Distorted OpenCV-normalised (u, v).

        Returns
        -------
        ndarray, shape of ``uv``
            Pixel (col, row), float64.
        """
        return brown.normalized_to_pixel(uv, self.focal_length, self.principal_point, self.pixel_size,
                                         self.image_size)

    def _check_plausible(self) -> None:
        """ParamError for a focal length, pixel pitch or principal point no camera has.

        Checks, in this order: the focal length is at most 1 km; a pixel subtends at least
        1e-8 rad (``pixel_size / focal_length``); the image corner farthest from the principal
        point is less than 85 deg off the optical axis (a frame camera's rays must reach the
        ground in front of it).
        """
        f = self.focal_length
        ps = min(self.pixel_size)
        if ps / f < MIN_PIXEL_ANGLE:
            raise ParamError(f"focal_length {f:g} mm with pixel_size {ps:g} mm is implausible: a pixel would "
                             f"subtend {ps / f:.3g} rad (less than {MIN_PIXEL_ANGLE:g}); both are in mm")
        w, h = self.image_size
        x0, y0 = self.principal_point
        half_w, half_h = 0.5 * w * self.pixel_size[0], 0.5 * h * self.pixel_size[1]
        r = math.hypot(half_w + abs(x0), half_h + abs(y0))  # farthest corner from the principal point
        off_axis = math.degrees(math.atan2(r, f))
        if off_axis > MAX_OFF_AXIS:
            raise ParamError(
                f"The {w}x{h} image with pixel_size {self.pixel_size[0]:g} x {self.pixel_size[1]:g} mm and "
                f"principal_point ({x0:g}, {y0:g}) mm has a corner {r:.4g} mm from the principal point, "
                f"{off_axis:.2f} deg off the axis for focal_length {f:g} mm (more than {MAX_OFF_AXIS:g}): "
                "check that focal_length, pixel_size and principal_point are all in mm")

    def _check_invertible(self) -> None:
        """Check that distortion is a one-to-one map over the whole image.

        The inverse is solved on a grid of distorted points (dense along the border, where
        distortion is strongest); every solution must reproduce its point to 1e-6 px with a
        positive Jacobian determinant, and the determinant must stay positive along the
        segment from the principal point to the solution (no fold in between).
        """
        if not self.has_distortion:
            return
        w, h = self.image_size
        edge = np.linspace(0.0, 1.0, 129)
        grid = np.linspace(0.0, 1.0, 17)
        gx, gy = np.meshgrid(grid, grid)
        frac = np.concatenate([
            np.stack([edge, np.zeros_like(edge)], 1), np.stack([edge, np.ones_like(edge)], 1),
            np.stack([np.zeros_like(edge), edge], 1), np.stack([np.ones_like(edge), edge], 1),
            np.stack([gx.ravel(), gy.ravel()], 1),
        ])
        pix = frac * np.array([w, h], dtype=np.float64)
        uvd = self.pixel_to_normalized(pix)
        with np.errstate(all="ignore"):
            uv = self.undistort(uvd)
            back = self.normalized_to_pixel(self.distort(uv))
            err = np.hypot(*(back - pix).T)
            t = np.linspace(0.0, 1.0, 33)[:, None, None]
            j00, j01, j10, j11 = self._jacobian(t * uv[None])
            det = j00 * j11 - j01 * j10
        bad = ~(np.isfinite(err) & (err <= 1e-6)) | ~np.all(det > 0.0, axis=0)
        if np.any(bad):
            c, r = pix[np.argmax(bad)]
            raise GeometryError(
                f"Lens distortion (k1={self.k1}, k2={self.k2}, k3={self.k3}, p1={self.p1}, p2={self.p2}) "
                f"is not invertible over the {w}x{h} image (first failure at pixel ({c:.1f}, {r:.1f}))")
        # invertible, but no lens: a point moved by more than MAX_DISTORTION of its distance from
        # the principal point (k1 = 1e6 shrinks the field seen fourfold, say)
        radius = np.hypot(uv[:, 0], uv[:, 1])
        with np.errstate(all="ignore"):
            moved = np.where(radius > 0.0, np.hypot(*(uvd - uv).T) / radius, 0.0)
        if np.max(moved) > MAX_DISTORTION:
            k = int(np.argmax(moved))
            u, v = uv[k]
            r2 = u * u + v * v
            terms = {"k1": abs(self.k1) * r2, "k2": abs(self.k2) * r2**2, "k3": abs(self.k3) * r2**3,
                     "p1": abs(self.p1) * math.hypot(2 * u * v, r2 + 2 * v * v) / math.sqrt(r2),
                     "p2": abs(self.p2) * math.hypot(r2 + 2 * u * u, 2 * u * v) / math.sqrt(r2)}
            worst = max(terms, key=lambda n: terms[n])  # the coefficient moving the point most
            c, r = pix[k]
            raise GeometryError(
                f"Lens distortion {worst}={getattr(self, worst)} is implausible (not invertible in practice) over "
                f"the {w}x{h} image: it moves pixel ({c:.1f}, {r:.1f}) by {moved[k]:.3g} times its distance from the "
                f"principal point, a lens at most {MAX_DISTORTION:g}; check {worst} (OpenCV-normalised units)")

    # -- device --------------------------------------------------------------------------------
    def to_struct(self) -> FrameCameraData:
        """Pack into :class:`orthowarp.kernels.camera.FrameCameraData`.

        Returns
        -------
        FrameCameraData
            The Warp struct (host values: it holds no arrays, so it serves every device).
        """
        s = FrameCameraData()
        s.focal = self.focal_length
        s.pixel_size = wp.vec2d(*self.pixel_size)
        s.inv_pixel_size = wp.vec2d(1.0 / self.pixel_size[0], 1.0 / self.pixel_size[1])
        s.size = wp.vec2d(*map(float, self.image_size))
        s.pp = wp.vec2d(*self.principal_point)
        s.k1, s.k2, s.k3, s.p1, s.p2 = self.k1, self.k2, self.k3, self.p1, self.p2
        return s

    def pixel_to_camera(self, pixels: ArrayLike, *, device: wp.DeviceLike = None) -> np.ndarray:
        """Pixels (N, 2) (col, row) -> unit rays (N, 3) in the camera frame (kernel).

        Rows with NaN, or masked in a NumPy masked array, give NaN rays.

        Parameters
        ----------
        pixels : array_like, shape (N, 2) or (2,)
            Pixel (col, row).
        device : str or warp.context.Device, optional
            Where the kernel runs (default: the first CUDA device, else the CPU).

        Returns
        -------
        ndarray, shape (N, 3)
            Unit ray directions (x right, y up, z backwards), float64.
        """
        return self._per_row(pixel_to_camera_kernel, _as_points(pixels, 2, "pixels"), wp.vec2d, wp.vec3d, device)

    def camera_to_pixel(self, vectors: ArrayLike, *, device: wp.DeviceLike = None) -> np.ndarray:
        """Camera-frame directions (N, 3) -> pixels (N, 2); NaN rows for directions not in front
        and for rows with NaN or masked in a NumPy masked array.

        Parameters
        ----------
        vectors : array_like, shape (N, 3) or (3,)
            Camera-frame directions (any length; the camera looks along -z).
        device : str or warp.context.Device, optional
            Where the kernel runs (default: the first CUDA device, else the CPU).

        Returns
        -------
        ndarray, shape (N, 2)
            Pixel (col, row), float64.
        """
        return self._per_row(camera_to_pixel_kernel, _as_points(vectors, 3, "vectors"), wp.vec3d, wp.vec2d, device)

    def _per_row(self, kernel: wp.Kernel, rows: np.ndarray, in_type: type, out_type: type,
                 device: wp.DeviceLike) -> np.ndarray:
        """Launch ``kernel`` (camera struct, rows in, rows out) over ``rows`` (N, k) float64;
        NaN output rows where an input row is missing (NaN or masked)."""
        with quiet_warp():
            dev = resolve_device(device)
            out = wp.empty(len(rows), dtype=out_type, device=dev)
            if len(rows):
                wp.launch(kernel, dim=len(rows), device=dev,
                          inputs=[self.to_struct(), wp.array(rows, dtype=in_type, device=dev), out])
            res = to_host(out).reshape(len(rows), out_type._length_)
        res[~np.all(np.isfinite(rows), axis=1)] = np.nan
        return res

