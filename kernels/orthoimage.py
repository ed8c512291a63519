"""An already orthorectified image as a sensor, device code: the float64 twin of
:class:`orthowarp.OrthoImage` (see :mod:`orthowarp.orthoimage`).

The image's ground -> image mapping is its own geotransform: a ground point's horizontal
coordinates (x, y) in the image's CRS go to the pixel (col, row) = A^-1 ((x, y) - origin), A
the geotransform's 2 x 2 matrix and origin the corner of its top-left pixel; the height plays
no part (the image lies on the ground already). A pixel within :data:`SNAP` pixels of a pixel
centre is put on it, so that a grid that coincides with the image's (the same CRS, pixel size
and alignment) samples its pixels exactly, whatever the last bits of the coordinates' float64
round-trip through the output grid (nearest and bilinear then return the input's values).

- :func:`ortho_pixel`: (x, y) -> pixel (col, row);
- :func:`ortho_ground`: pixel -> (x, y).

:class:`OrthoData` is the sensor's argument of the generic kernels
(:mod:`orthowarp.kernels.sensor`) and of the ortho's per-pixel chain
(:func:`orthowarp.kernels.ortho.source_pixel`); no refraction table, no DEM is read.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

#: Pixels within this distance of a pixel centre (in each of col and row) are put on it (px).
SNAP = wp.constant(wp.float64(1.0e-6))


@wp.struct
class OrthoData:
    """An orthoimage's geotransform packed for kernels: (x, y) = origin + matrix (col, row),
    and its inverse ``inverse``; ``axis_aligned`` (1: a north-up grid, matrix diagonal) takes
    the inverse by division, exact to the last bit where the coordinates are."""

    origin: wp.vec2d
    matrix: wp.mat22d
    inverse: wp.mat22d
    axis_aligned: wp.int32


@wp.func
def snap(p: wp.float64):
    """p, or the pixel centre (k + 0.5) within :data:`SNAP` of it."""
    c = wp.floor(p) + wp.float64(0.5)
    if wp.abs(p - c) < SNAP:
        return c
    return p


@wp.func
def ortho_pixel(o: OrthoData, x: wp.float64, y: wp.float64):
    """Horizontal coordinates (x, y) of the image's CRS -> pixel (col, row), snapped to the
    pixel centres within :data:`SNAP`."""
    dx = x - o.origin[0]
    dy = y - o.origin[1]
    col = wp.float64(0.0)
    row = wp.float64(0.0)
    if o.axis_aligned != 0:
        col = dx / o.matrix[0, 0]
        row = dy / o.matrix[1, 1]
    else:
        p = o.inverse * wp.vec2d(dx, dy)
        col = p[0]
        row = p[1]
    return wp.vec2d(snap(col), snap(row))


@wp.func
def ortho_ground(o: OrthoData, pix: wp.vec2d):
    """Pixel (col, row) -> horizontal coordinates (x, y) of the image's CRS."""
    return o.origin + o.matrix * pix
