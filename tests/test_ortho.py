"""Orthorectification against synthetic truth.

An independent float64 NumPy renderer (``tests/render.py``, sharing no code with orthowarp's
kernels, camera, pose or geometry) draws what a camera sees of an analytic, band-limited ground
texture T(x, y) draped over a DEM: for every pixel it casts rays (2 x 2 per pixel, averaged, like
a sensor's pixel area), intersects them with the DEM surface in float64 and reads T there. The
rendered image is written as an un-georeferenced GeoTIFF and orthorectified by
:func:`orthowarp.pipeline.ortho.orthorectify`; T evaluated at the orthoimage's pixel centres is
the truth. Misregistration between the two is measured by tiled phase correlation
(:func:`orthowarp.pipeline.registration.misregistration`), in orthoimage pixels.

The renderer reads the DEM as the same bilinear surface orthowarp reads from the grid
(``reference.GridDem``, the float32 heights orthowarp stores), in the pose's frame (lon/lat for
GNSS/INS poses, the map CRS for omega-phi-kappa poses), so terrain interpolation is no part of
the error budget; the texture lives in UTM 32N (EPSG:32632), which is also the orthoimages' CRS.

Cases: both pose conventions without refraction; an oblique, high scene with refraction of
more than a pixel, rendered with refraction and orthorectified with and without it (without,
the measured shift must be the refraction model's displacement); the four resampling kernels;
output types, nodata, COG/GTiff layout; and the error paths.
"""

import functools
import logging
import os
import warnings

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import Transformer

import orthowarp as ow
import scenes
from scenes import geo_dem
from orthowarp.errors import GeometryError, OrthowarpWarning, ParamError, RasterIOError
from orthowarp.pipeline.ortho import orthorectify
from orthowarp.pipeline.registration import misregistration
from orthowarp.sensor import FrameSensor

try:
    from . import reference as ref
    from . import render
except ImportError:  # default "prepend" import mode: tests/ is on sys.path
    import reference as ref
    import render

try:
    from conftest import DEVICES
except ImportError:  # pragma: no cover
    DEVICES = ["cpu"]

UTM32 = "EPSG:32632"
RMS_MAX = 0.1  # px (orthoimage pixels): required misregistration
TILE = 64  # px, phase-correlation tiles
SUPERSAMPLE = 2  # rays per pixel and axis in the renderer

_TO_UTM = Transformer.from_crs("EPSG:4326", UTM32, always_xy=True)
_TO_LONLAT = Transformer.from_crs(UTM32, "EPSG:4326", always_xy=True)


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------
def hills(e, n):
    """Rolling terrain (m) of east/north offsets (m) from the scene centre: ~60 m relief,
    slopes up to ~25 deg."""
    return (450.0 + 35.0 * np.exp(-((e - 60.0) ** 2 + (n + 40.0) ** 2) / (2 * 90.0**2))
            - 20.0 * np.exp(-((e + 90.0) ** 2 + (n - 70.0) ** 2) / (2 * 110.0**2))
            + 8.0 * np.sin(e / 45.0 + 0.3) * np.cos(n / 60.0 - 0.2))


def gentle(e, n):
    """Gentle terrain for the oblique scenes (slopes < 6 deg: no occlusion at 45 deg)."""
    return (480.0 + 12.0 * np.sin(e / 110.0 + 0.4) * np.cos(n / 140.0 - 0.3)
            + 6.0 * np.exp(-((e - 40.0) ** 2 + (n + 30.0) ** 2) / (2 * 80.0**2)))


def map_dem(func, xc, yc, ncells, cell):
    """(ow.Dem, reference.GridDem) of func(x - xc, y - yc) in UTM 32N, centred at (xc, yc)."""
    return scenes.map_dem(func, xc, yc, ncells, ncells, cell, crs=UTM32)


# A small aerial frame camera: 0.6 mrad pixels, ~0.57 m GSD from ~950 m above ground, a few
# pixels of distortion at the corners, principal point off the centre.
CAM_MAIN = dict(f=100.0, pixel=0.06, size=(400, 300), pp=(0.03, -0.02), k1=1.0, k2=-3.0, p1=1e-3, p2=-8e-4)
# A long lens for the oblique scenes: 50 urad pixels, ~0.4 m GSD at ~7 km slant range.
CAM_OBLIQUE = dict(f=200.0, pixel=0.01, size=(400, 300), pp=(0.01, 0.005), k1=10.0, p1=2e-3, p2=-1e-3)
OPK_X, OPK_Y = 463250.0, 5201480.0


class Scene:
    """Camera + pose + DEM as orthowarp objects and as reference objects, a texture, renderers."""

    def __init__(self, name, cam_kw, kind, pose_kw, terrain, *, min_period, max_period, seed):
        self.name, self.kind = name, kind
        k = {n: cam_kw.get(n, 0.0) for n in ("k1", "k2", "k3", "p1", "p2")}
        self.camera = ow.FrameCamera(cam_kw["f"], cam_kw["pixel"], cam_kw["size"], principal_point=cam_kw["pp"], **k)
        self.ref_camera = ref.RefCamera(cam_kw["f"], cam_kw["pixel"], cam_kw["size"], cam_kw["pp"], **k)
        self.size = cam_kw["size"]
        self.pose, self.ref_pose = scenes.make_poses(kind, pose_kw)
        # the DEM: centred where the central ray meets the terrain's base height
        centre = self._centre_ray_foot(terrain(0.0, 0.0))
        if kind == "ins":
            lon, lat = _TO_LONLAT.transform(*centre)
            self.dem, self.grid = geo_dem(terrain, lon, lat, 220, 2.0)
        else:
            self.dem, self.grid = map_dem(terrain, centre[0], centre[1], 220, 2.0)
        self.texture = render.Texture(centre, min_period=min_period, max_period=max_period, seed=seed)

    def _centre_ray_foot(self, h):
        """UTM x, y where the central ray meets height h (the renderer on a flat DEM)."""
        flat = render.Renderer(self.ref_camera, self.ref_pose, lambda x, y: np.full(np.shape(x), h),
                               (h, h), lambda x, y: 0.0 * x, UTM32)
        _, txy = flat.ground(np.array([[self.size[0] / 2.0, self.size[1] / 2.0]]))
        return txy[0]

    @functools.lru_cache(maxsize=None)
    def renderer(self, refraction):
        return render.Renderer(self.ref_camera, self.ref_pose, self.grid.sample, (self.grid.hmin, self.grid.hmax),
                               self.texture, UTM32, refraction=refraction)

    @functools.lru_cache(maxsize=None)
    def image(self, refraction):
        """The rendered image (rows, cols), float64."""
        img = self.renderer(refraction).render(SUPERSAMPLE)
        img.flags.writeable = False
        return img

    def heights(self, x, y):
        """DEM height at UTM x, y (the grid's bilinear surface)."""
        if self.kind == "ins":
            lon, lat = _TO_LONLAT.transform(x, y)
            return self.grid.sample(lon, lat)
        return self.grid.sample(x, y)

    def object_point(self, x, y):
        """Object-frame points (N, 3) (ECEF or map x/y/z) on the DEM at UTM x, y."""
        z = self.heights(x, y)
        if self.kind == "ins":
            lon, lat = _TO_LONLAT.transform(x, y)
            return ref.llh_to_ecef(lon, lat, z)
        return np.stack([x, y, z], axis=1)


@functools.lru_cache(maxsize=None)
def scene(name):
    if name == "opk":
        return Scene(name, CAM_MAIN, "opk", dict(x=OPK_X, y=OPK_Y, z=1400.0, omega=2.0, phi=-2.5, kappa=57.0),
                     hills, min_period=5.0, max_period=25.0, seed=1)
    if name == "ins":
        return Scene(name, CAM_MAIN, "ins",
                     dict(lat=46.95, lon=8.9, h=1400.0, roll=2.5, pitch=-3.0, yaw=30.0,
                          boresight=(0.05, -0.08, 0.3), lever_arm=(0.3, -0.15, -1.2)),
                     hills, min_period=5.0, max_period=25.0, seed=2)
    # oblique, high: refraction displaces the ground by more than a pixel
    if name == "ins_oblique":
        return Scene(name, CAM_OBLIQUE, "ins", dict(lat=47.2, lon=9.4, h=6000.0, roll=1.0, pitch=40.0, yaw=30.0),
                     gentle, min_period=4.0, max_period=20.0, seed=3)
    if name == "opk_oblique":
        return Scene(name, CAM_OBLIQUE, "opk", dict(x=OPK_X, y=OPK_Y, z=6000.0, omega=-1.5, phi=38.0, kappa=-20.0),
                     gentle, min_period=4.0, max_period=20.0, seed=4)
    raise KeyError(name)


# ------------------------------------------------------------------------------------------
# Helpers
# ------------------------------------------------------------------------------------------
def write_image(path, array, dtype="float32"):
    """Write a (rows, cols) array as an un-georeferenced single-band GeoTIFF."""
    arr = np.asarray(array)
    if dtype != "float32":
        info = np.iinfo(dtype)
        arr = np.clip(np.rint(arr), info.min, info.max)
    arr = arr.astype(dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path, "w", driver="GTiff", width=arr.shape[1], height=arr.shape[0], count=1,
                           dtype=dtype) as dst:
            dst.write(arr, 1)
    return path


def read_ortho(path):
    """(values float64 (rows, cols), valid bool (rows, cols), dataset facts)."""
    with rasterio.open(path) as ds:
        data = ds.read(1).astype(np.float64)
        if ds.dtypes[0] == "float32":
            valid = np.isfinite(data)
        else:
            valid = ds.dataset_mask() > 0
        facts = dict(dtype=ds.dtypes[0], crs=ds.crs, transform=ds.transform, nodata=ds.nodata,
                     overviews=ds.overviews(1), block_shapes=ds.block_shapes, profile=ds.profile,
                     mask_flags=ds.mask_flag_enums[0])
    return data, valid, facts


def pixel_centres(result):
    rows, cols = result.shape
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    return result.transform @ (jj, ii)


def truth(sc, result):
    """T at the orthoimage's pixel centres (the orthoimage's CRS is the texture's)."""
    x, y = pixel_centres(result)
    return sc.texture(x, y)


def ortho(sc, tmp_path, *, refraction_image, refraction, name="ortho.tif", src_dtype="float32", scale=1.0,
          offset=0.0, **kw):
    """Write the scene's rendered image (times scale, plus offset) and orthorectify it."""
    src = write_image(tmp_path / f"src_{name}", sc.image(refraction_image) * scale + offset, src_dtype)
    kw.setdefault("device", "cpu")
    result = orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / name, dem=sc.dem, refraction=refraction, **kw)
    return result


def measure(sc, result, *, scale=1.0, offset=0.0):
    data, valid, _ = read_ortho(result.path)
    t = truth(sc, result) * scale + offset
    return misregistration(t, data, valid=valid, tile=TILE), data, valid, t


def describe(m):
    return (f"RMS {m['rms']:.4f} px, mean (dy, dx) ({m['mean'][0]:+.4f}, {m['mean'][1]:+.4f}) px, "
            f"max {m['max']:.4f} px, {m['n_tiles']} tiles, peak {m['peak']:.3f}")


def assert_no_leftovers(folder, name):
    left = [f for f in os.listdir(folder) if f.startswith(name) or ".orthowarp-tmp-" in f]
    assert not left, f"left behind: {left}"


# ------------------------------------------------------------------------------------------
# 0. The renderer itself
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name,refraction", [("ins", False), ("opk", False), ("ins_oblique", True),
                                             ("opk_oblique", True)])
def test_renderer_matches_reference_ray_tracer(name, refraction):
    """The vectorised renderer's ground points are the per-ray reference's (tests/reference.py)
    to 1e-5 m, with refraction where the scene uses it."""
    sc = scene(name)
    w, h = sc.size
    pix = np.array([[0.25, 0.25], [w - 0.25, 0.25], [0.25, h - 0.25], [w - 0.25, h - 0.25],
                    [w / 2, h / 2], [123.75, 45.25], [301.25, 222.75]])
    got, _ = sc.renderer(refraction).ground(pix)
    expected = ref.RayTracer(sc.ref_pose, sc.grid, refraction).geolocate(sc.ref_camera, pix)
    assert np.all(np.isfinite(expected))
    err = np.linalg.norm(got - expected, axis=1)
    assert err.max() < 1e-5, f"max {err.max():.2e} m"


@pytest.mark.parametrize("name", ["ins", "opk"])
def test_scene_is_what_it_claims(name):
    """Distortion of a few pixels, a few degrees of tilt, GSD ~0.57 m, relief, no occlusion;
    the texture's shortest period is >= 8 GSD."""
    sc = scene(name)
    rc = sc.ref_camera
    w, h = sc.size
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    x, y = rc.image_mm(corners)
    u, v = rc.undistort(x / rc.f, -y / rc.f)
    assert np.max(np.hypot(u * rc.f - x, -v * rc.f - y)) / rc.px[0] > 3.0
    r = sc.renderer(False)
    theta = np.degrees(r.nadir_angle(r.rays(np.array([[w / 2, h / 2]]))))
    assert 2.0 < theta[0] < 6.0
    _, txy = r.ground(np.array([[w / 2, h / 2], [w / 2 + 1, h / 2], [w / 2, h / 2 + 1]]))
    (ax, ay), (bx, by) = txy[1] - txy[0], txy[2] - txy[0]
    gsd = np.sqrt(abs(ax * by - ay * bx))
    assert 0.5 < gsd < 0.65
    assert sc.texture.min_period >= 8 * gsd
    assert sc.grid.hmax - sc.grid.hmin > 40.0
    # no occlusion: tan(slope) tan(nadir angle) well below 1 everywhere
    cell_y = abs(sc.grid.dy) * (111132.0 if name == "ins" else 1.0)
    cell_x = abs(sc.grid.dx) * (111320.0 * np.cos(np.radians(46.95)) if name == "ins" else 1.0)
    gy, gx = np.gradient(sc.grid.z, cell_y, cell_x)
    corners_theta = r.nadir_angle(r.rays(corners))
    assert np.hypot(gx, gy).max() * np.tan(corners_theta.max()) < 0.2


# ------------------------------------------------------------------------------------------
# 1. Misregistration against the truth, no refraction
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["ins", "opk"])
def test_ortho_matches_truth(name, tmp_path, device):
    sc = scene(name)
    res = ortho(sc, tmp_path, refraction_image=False, refraction=False, device=device)
    assert res.crs.to_epsg() == 32632
    m, data, valid, t = measure(sc, res)
    print(f"\n[{name}, refraction off] {res.shape[1]} x {res.shape[0]} px at {res.resolution:.4f} m: {describe(m)}")
    assert m["n_tiles"] >= 8
    assert m["peak"] > 0.5
    assert m["rms"] <= RMS_MAX, describe(m)
    # and the values themselves: T up to the blur of pixel averaging and bilinear resampling
    err = (data - t)[valid]
    assert np.sqrt(np.mean(err**2)) < 0.15 * sc.texture.std


@pytest.mark.parametrize("name", ["ins", "opk", "ins_oblique"])
def test_forward_method_matches_truth_and_backward(name, tmp_path, device):
    """Seed 003's direct method: forward-geolocated source pixels, map inverted quad by quad."""
    sc = scene(name)
    refr = name.endswith("oblique")
    back = ortho(sc, tmp_path, refraction_image=refr, refraction=refr, name="back.tif", device=device)
    fwd = ortho(sc, tmp_path, refraction_image=refr, refraction=refr, name="fwd.tif", method="forward", device=device)
    assert fwd.shape == back.shape and fwd.transform == back.transform
    m, data_f, valid_f, _ = measure(sc, fwd)
    print(f"\n[{name}, forward] {describe(m)}")
    assert m["n_tiles"] >= 8 and m["rms"] <= RMS_MAX, describe(m)
    data_b, valid_b, _ = read_ortho(back.path)
    both = valid_f & valid_b
    # the forward footprint lacks only the outer half source pixel of the backward one
    assert both.sum() == valid_f.sum() and valid_f.sum() > 0.98 * valid_b.sum()
    mb = misregistration(data_b, data_f, valid=both, tile=TILE)
    print(f"[{name}, forward vs backward] {describe(mb)}")
    assert mb["rms"] <= 0.01 and abs(mb["mean"][0]) < 0.005 and abs(mb["mean"][1]) < 0.005, describe(mb)


def test_forward_method_leaves_hidden_ground_nodata(tmp_path):
    """A tall narrow ridge seen obliquely hides the ground behind it: the forward method leaves
    that ground nodata, the backward method fills it with the ridge (a ghost)."""
    cam = ow.FrameCamera(50.0, 0.1, (200, 150))  # +-11 degrees across
    pose = ow.Pose.from_opk(OPK_X - 500.0, OPK_Y, 1000.0, 0.0, -40.0, 0.0, crs=UTM32)  # looking east, 40 deg
    ridge = lambda e, n: 400.0 + 120.0 * np.exp(-0.5 * ((e - 0.0) / 6.0) ** 2) + 0.0 * n  # noqa: E731
    dem, _ = map_dem(ridge, OPK_X, OPK_Y, 700, 2.0)
    src = write_image(tmp_path / "src.tif", np.random.default_rng(1).integers(1, 255, (150, 200)), "uint8")
    kw = dict(dem=dem, refraction=False, device="cpu", resolution=4.0)
    back = orthorectify(src, FrameSensor(cam, pose), tmp_path / "back.tif", **kw)
    fwd = orthorectify(src, FrameSensor(cam, pose), tmp_path / "fwd.tif", method="forward", **kw)
    _, vb, _ = read_ortho(back.path)
    _, vf, _ = read_ortho(fwd.path)
    x, _ = pixel_centres(fwd)
    behind = (x > OPK_X + 20.0) & (x < OPK_X + 60.0)  # in the ridge's shadow as seen from the west
    assert vb[behind].mean() > 0.7  # the footprint is a trapezoid: not every row reaches there
    assert vf[behind].mean() < 0.05
    assert np.all(vb[vf])  # nothing the forward method keeps is missing from the backward one


def test_node_blocks_bound_the_nodes_in_a_box():
    """The forward method's node search by blocks gives the bounds a node-by-node search
    gives, for boxes inside, across and outside a rotated, warped node grid with holes: the
    source pixels exactly, the other values within float32's step of a block's spread."""
    from orthowarp.pipeline.ortho.forward import _NodeBlocks

    rng = np.random.default_rng(3)
    rows, cols = 53, 71  # not whole blocks
    j, i = np.meshgrid(np.arange(cols, dtype=float), np.arange(rows, dtype=float))
    a = np.radians(27.0)
    x = 16 * (np.cos(a) * j - np.sin(a) * i) + 3 * np.sin(i / 5.0)
    y = 16 * (np.sin(a) * j + np.cos(a) * i) + 2 * np.cos(j / 7.0)
    fields = np.stack([x, y, 16 * j, 16 * i, 100 + x / 3, -y / 3], -1)
    fields[rng.random((rows, cols)) < 0.1] = np.nan  # nodes that were not geolocated
    fields[10:30, 20:45] = np.nan  # and a hole
    nodes = _NodeBlocks(fields)
    flat = fields.reshape(-1, 6)
    for _ in range(200):
        x0, y0 = rng.uniform(-900, 1300, 2)
        x1, y1 = x0 + rng.uniform(0, 700), y0 + rng.uniform(0, 700)
        sel = (flat[:, 0] >= x0) & (flat[:, 0] <= x1) & (flat[:, 1] >= y0) & (flat[:, 1] <= y1)
        got = nodes.bounds(x0, y0, x1, y1)
        if not sel.any():
            assert got is None
            continue
        for g, want in ((got[0], flat[sel, 2:].min(axis=0)), (got[1], flat[sel, 2:].max(axis=0))):
            np.testing.assert_array_equal(g[:2], want[:2])  # source pixels: exact
            np.testing.assert_allclose(g[2:], want[2:], rtol=0, atol=200 * 2.0 ** -24)  # spread < 200


def test_forward_method_rejects_bad_method(tmp_path):
    sc = scene("opk")
    with pytest.raises(ParamError, match="method"):
        ortho(sc, tmp_path, refraction_image=False, refraction=False, method="sideways")


def source_position(sc, result):
    """Source pixel (col, row) of every orthoimage pixel centre by the reference's closed-form
    collinearity (no refraction) onto the DEM: (rows, cols, 2)."""
    x, y = pixel_centres(result)
    g = sc.object_point(x.ravel(), y.ravel())
    pix = sc.ref_camera.pixels((g - sc.ref_pose.center) @ sc.ref_pose.rotation)
    return pix.reshape(*result.shape, 2)


@pytest.mark.parametrize("name,resampling", [("ins", "bilinear"), ("opk", "nearest"), ("opk", "lanczos")])
def test_footprint_is_the_images(name, resampling, tmp_path):
    """Valid orthoimage pixels are those that see the image: none outside it, all that are
    0.5 px or more inside it (a kernel may drop a pixel whose valid taps weigh < 1/2 within
    half a pixel of the border), every one of them for nearest. And the orthoimage's
    bounds hold the whole footprint. Small tiles: many source windows, each bounded by its
    coarse nodes at the tile's extreme DEM heights, must each hold all their pixels' taps."""
    sc = scene(name)
    res = ortho(sc, tmp_path, refraction_image=False, refraction=False, resampling=resampling, tile_size=48)
    _, valid, _ = read_ortho(res.path)
    pix = source_position(sc, res)
    w, h = sc.size
    margin = np.minimum(np.minimum(pix[..., 0], w - pix[..., 0]), np.minimum(pix[..., 1], h - pix[..., 1]))
    assert not np.any(valid & (margin < -1e-3)), "data outside the image's footprint"
    deep = 1e-3 if resampling == "nearest" else 0.5
    assert np.all(valid[margin >= deep]), "nodata inside the image's footprint"
    # the ground of the image's border lies inside the orthoimage's bounds
    t = np.linspace(0.0, 1.0, 41)
    border = np.concatenate([np.stack([t * w, 0 * t], 1), np.stack([t * w, 0 * t + h], 1),
                             np.stack([0 * t, t * h], 1), np.stack([0 * t + w, t * h], 1)])
    _, txy = sc.renderer(False).ground(border)
    col, row = ~res.transform @ (txy[:, 0], txy[:, 1])
    assert np.all((col >= 0) & (col <= res.shape[1]) & (row >= 0) & (row <= res.shape[0]))


@pytest.mark.parametrize("name", ["ins", "opk"])
def test_output_grid_is_the_same_on_every_device(name):
    """output_grid computes on the CPU whatever the geometry's device, so that a device whose
    float64 results differ from the CPU's in the last bits (a GPU's) gives the same grid. Else
    the default resolution (the mean GSD) and the grid's alignment to whole pixels from the
    CRS's origin turn those bits into a shift of the whole grid: on an H100, 3.9e-10 of the GSD
    moved it by 0.02 px and changed 2.5 % of a nearest ortho's pixels (bench/api_agreement.py,
    bench/reference/api-agreement-h100.json)."""
    import copy

    from orthowarp.pipeline.ortho import grid as po
    from orthowarp.pipeline.geometry import SensorGeometry

    rng = np.random.default_rng(11)

    class OtherDevice(SensorGeometry):
        """The geometry as another device computes it: the CPU's results, last bits changed
        (within 64 ulp); its CPU twin is the geometry itself."""

        def geolocate_frame(self, pixels):
            g = super().geolocate_frame(pixels)
            return g * (1.0 + rng.integers(-64, 65, g.shape) * 2.0**-52)

        def on_device(self, device):
            twin = copy.copy(self)
            twin.__class__ = SensorGeometry
            return twin

    sc = scene(name)
    geom = SensorGeometry(FrameSensor(sc.camera, sc.pose), sc.dem, device="cpu", refraction=True)
    other = copy.copy(geom)
    other.__class__ = OtherDevice
    crs, transform, shape, res = po.output_grid(geom)
    assert po.output_grid(other) == (crs, transform, shape, res)
    # what those bits do to a grid computed from them: the GSD moves, and the grid with it
    to_out = Transformer.from_crs(geom.horizontal_crs, crs, always_xy=True)
    moved = po.output_grid(geom, resolution=po._mean_gsd(other, to_out))[1]
    shift = max(abs(moved.c - transform.c), abs(moved.f - transform.f)) / res
    print(f"{name}: GSD's last bits moved the grid by {shift:.2e} px")
    assert moved != transform


def test_tile_source_coords_are_the_orthos(tmp_path):
    """ImageTiles.source_coords (what bench/api_agreement.py compares between devices) gives
    the source pixels the public call samples: a nearest ortho is the source at them."""
    from orthowarp.pipeline import ortho as po
    from orthowarp.pipeline.geometry import SensorGeometry

    sc = scene("ins")
    res = ortho(sc, tmp_path, refraction_image=True, refraction=True, resampling="nearest", tile_size=64)
    data, valid, _ = read_ortho(res.path)
    src = sc.image(True).astype(np.float32)
    geom = SensorGeometry(FrameSensor(sc.camera, sc.pose), sc.dem, device="cpu", refraction=True)
    image = po.ImageTiles(str(tmp_path / "src_ortho.tif"), geom, res.crs, res.transform, count=1,
                          out_dtype="float32", resampling="nearest", masked=False)
    rows, cols = res.shape
    h, w = src.shape
    for r0 in range(0, rows, 64):
        for c0 in range(0, cols, 64):
            th, tw = min(64, rows - r0), min(64, cols - c0)
            coords = image.source_coords(r0, c0, th, tw)[0]
            ok = np.isfinite(coords).all(-1)
            np.testing.assert_array_equal(ok, valid[r0:r0 + th, c0:c0 + tw])
            c = np.clip(np.floor(coords[ok, 0]).astype(int), 0, w - 1)
            r = np.clip(np.floor(coords[ok, 1]).astype(int), 0, h - 1)
            np.testing.assert_array_equal(src[r, c], data[r0:r0 + th, c0:c0 + tw][ok])
    image.close()


def test_tile_height_range_from_dem_blocks():
    """A tile's height range from the DEM's block minima and maxima holds the exact range of
    the cells under it (and one around); no heights there -> None; a constant DEM -> its
    height."""
    from orthowarp.pipeline.dem import Dem
    from orthowarp.pipeline.ortho.tiles import _height_range

    rng = np.random.default_rng(3)
    z = rng.normal(500.0, 80.0, (150, 230)).astype(np.float32)
    z[100:, 150:] = np.nan
    dem = Dem(z, Affine(2.0, 0.0, 1000.0, 0.0, -2.0, 5000.0), "EPSG:32632")
    blocks = (16, dem.block_range(16))
    for _ in range(200):
        c0, r0 = rng.uniform(0, 220), rng.uniform(0, 140)
        c1, r1 = c0 + rng.uniform(0.5, 40), r0 + rng.uniform(0.5, 40)
        uv = np.array([[[1000 + 2 * c0, 5000 - 2 * r0], [1000 + 2 * c1, 5000 - 2 * r1]]])
        exact = z[max(int(np.floor(r0)) - 1, 0):int(np.ceil(r1)) + 1, max(int(np.floor(c0)) - 1, 0):int(np.ceil(c1)) + 1]
        got = _height_range(dem, blocks, uv)
        if np.isfinite(exact).any():
            assert got[0] <= np.nanmin(exact) and got[1] >= np.nanmax(exact)
    assert _height_range(dem, blocks, np.array([[[1000 + 2 * 200, 5000 - 2 * 130]]])) is None
    assert _height_range(Dem.constant(250.0), None, np.zeros((2, 2, 2))) == (250.0, 250.0)


@pytest.mark.parametrize("name", ["ins", "opk"])
def test_refraction_from_the_nodes_matches_the_per_pixel_turn(name):
    """The refraction turn interpolated from the coarse grid's nodes (the CPU's path, see
    kernels.ortho.CoarseGrid) gives every pixel of a tile the source coordinates of the
    per-pixel turn (the GPU's path) within 1e-6 px, over hills with tens of metres of relief
    per tile, and refraction moves them by far more than that."""
    import warp as wp
    from orthowarp.kernels import ortho as ok
    from orthowarp.pipeline.geometry import SensorGeometry
    from orthowarp.pipeline.ortho import coarse_grid, coarse_struct, output_grid
    from orthowarp.pipeline.ortho.tiles import _height_range

    sc = scene(name)
    geoms = {r: SensorGeometry(FrameSensor(sc.camera, sc.pose), sc.dem, device="cpu", refraction=r) for r in (True, False)}
    geom = geoms[True]
    out_crs, transform, shape, _ = output_grid(geom)
    to_frame = Transformer.from_crs(out_crs, geom.horizontal_crs, always_xy=True)
    blocks = (4, geom.dem.block_range(4))
    w, h_img = sc.size
    size, worst, moved, tiles = 64, 0.0, 0.0, 0
    for r0 in range(0, shape[0] - size, 2 * size):
        for c0 in range(0, shape[1] - size, 2 * size):
            uv = coarse_grid(transform, to_frame, r0, c0, size, size)
            heights = _height_range(geom.dem, blocks, uv)
            if heights is None:
                continue
            coords = {}
            for key, g in (("pixel", geom), ("nodes", geom), ("none", geoms[False])):
                arg, refr = g.sensor_structs()
                grid = coarse_struct(uv, g.geocentric, "cpu", pose=g.sensor.pose)
                if key == "nodes":
                    grid.refr_a = wp.empty(uv.shape[:2], dtype=wp.vec3d, device="cpu")
                    grid.refr_b = wp.empty(uv.shape[:2], dtype=wp.vec3d, device="cpu")
                    wp.launch(ok.frame_node_refraction_kernel, dim=uv.shape[:2], device="cpu",
                              inputs=[refr, grid, wp.vec2d(*heights), grid.refr_a, grid.refr_b])
                    grid.refr_nodes = 1
                out = wp.empty((size, size), dtype=wp.vec2d, device="cpu")
                wp.launch(ok.source_coords_kernel, dim=(size, size), device="cpu",
                          inputs=[arg, refr, g.dem_struct(), grid, wp.float64(w), wp.float64(h_img), out])
                coords[key] = out.numpy()
            a, b = coords["pixel"], coords["nodes"]
            np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
            ok_ = np.isfinite(a).all(-1)
            if ok_.any():
                tiles += 1
                worst = max(worst, float(np.abs(a[ok_] - b[ok_]).max()))
                both = ok_ & np.isfinite(coords["none"]).all(-1)
                moved = max(moved, float(np.abs(a[both] - coords["none"][both]).max()))
    print(f"{name}: {tiles} tiles, nodes vs per-pixel turn {worst:.2e} px, refraction moves {moved:.3f} px")
    assert tiles >= 4
    assert worst < 1e-6, worst
    assert moved > 1e-3, moved  # refraction matters here: the comparison is not between zeros


@pytest.mark.parametrize("name", ["ins", "opk"])
def test_tile_windows_hold_every_source_pixel(name):
    """The source window of a tile (its coarse nodes projected at the lowest and highest DEM
    height under it, then a 1 px margin: no resampling radius, no curvature margin) holds the
    exact source pixel of every pixel of the tile: the ground point on the DEM projected by
    ``orthowarp.project``. Over these hills a tile spans up to ~25 m of relief, which moves
    source pixels by several pixels."""
    import warp as wp
    from orthowarp.kernels import ortho as ok
    from orthowarp.pipeline.geometry import SensorGeometry
    from orthowarp.pipeline.ortho import coarse_grid, coarse_struct, output_grid
    from orthowarp.pipeline.ortho.tiles import _height_range, _rows_window

    sc = scene(name)
    geom = SensorGeometry(FrameSensor(sc.camera, sc.pose), sc.dem, device="cpu", refraction=True)
    out_crs, transform, shape, _ = output_grid(geom)
    frame_crs = geom.horizontal_crs
    to_frame = Transformer.from_crs(out_crs, frame_crs, always_xy=True)
    arg, refr, _, _ = geom.structs()
    size, spans, checked = 64, [], 0
    blocks = (4, geom.dem.block_range(4))
    for r0 in range(0, shape[0] - size, 3 * size):
        for c0 in range(0, shape[1] - size, 3 * size):
            uv = coarse_grid(transform, to_frame, r0, c0, size, size)
            heights = _height_range(geom.dem, blocks, uv)
            if heights is None:  # off the DEM
                continue
            nodes = wp.empty((2, *uv.shape[:2]), dtype=wp.vec2d, device="cpu")
            wp.launch(ok.node_pixels_kernel, dim=nodes.shape, device="cpu",
                      inputs=[arg, refr, coarse_struct(uv, geom.geocentric, "cpu"), wp.vec2d(*heights), nodes])
            w, h_img = sc.size
            rows = wp.empty((2, nodes.shape[1], 8), dtype=wp.float64, device="cpu")
            wp.launch(ok.node_window_rows_kernel, dim=rows.shape[:2], device="cpu", inputs=[nodes, rows])
            window = _rows_window(rows.numpy(), nodes.size, 0, w, h_img, margin=0)
            jj, ii = np.meshgrid(np.arange(c0, c0 + size) + 0.5, np.arange(r0, r0 + size) + 0.5)
            u, v = to_frame.transform(*(transform @ (jj.ravel(), ii.ravel())))
            h = geom.dem.sample(np.asarray(u), np.asarray(v))
            pix = ow.project(FrameSensor(sc.camera, sc.pose), np.stack([u, v, h], 1), crs=frame_crs, refraction=True, device="cpu")
            pix = pix[np.isfinite(pix).all(axis=1)]
            pix = pix[(pix[:, 0] >= 0) & (pix[:, 0] <= w) & (pix[:, 1] >= 0) & (pix[:, 1] <= h_img)]  # on the image
            if window is None:
                assert len(pix) == 0, (r0, c0)
                continue
            c_lo, r_lo, c_hi, r_hi = window
            assert np.all((pix[:, 0] >= c_lo) & (pix[:, 0] <= c_hi) & (pix[:, 1] >= r_lo) & (pix[:, 1] <= r_hi)), (r0, c0)
            n = nodes.numpy()
            spans.append(np.nanmax(np.hypot(*(n[1] - n[0]).reshape(-1, 2).T)))  # px between the two heights
            checked += len(pix)
    assert checked > 10000 and max(spans) > 3.0, (checked, max(spans))


@pytest.mark.parametrize("name,crs,resolution", [("ins", "EPSG:32633", 0.56), ("opk", "EPSG:4326", 0.56 / 111000.0)])
def test_other_output_crs(name, crs, resolution, tmp_path):
    """An output CRS other than the pose's and the texture's (the next UTM zone, rotated by the
    meridian convergence; geographic degrees): the truth is T at the pixel centres taken to
    UTM 32N, and the misregistration (in output pixels) stays within the requirement."""
    sc = scene(name)
    res = ortho(sc, tmp_path, refraction_image=False, refraction=False, crs=crs, resolution=resolution,
                tile_size=128)
    assert res.crs.equals(crs) and res.resolution == resolution
    data, valid, facts = read_ortho(res.path)
    assert facts["crs"].to_epsg() == int(crs.split(":")[1])
    x, y = pixel_centres(res)
    tx, ty = Transformer.from_crs(crs, UTM32, always_xy=True).transform(x, y)
    m = misregistration(sc.texture(tx, ty), data, valid=valid, tile=TILE)
    print(f"\n[{name} -> {crs}] {res.shape[1]} x {res.shape[0]} px: {describe(m)}")
    assert m["n_tiles"] >= 8
    assert m["rms"] <= RMS_MAX, describe(m)


def test_tiles_and_threads_do_not_change_the_result(tmp_path):
    """Small output tiles on two threads give the single-tile result (geocentric pose, Lanczos:
    the widest kernel, whose source windows must reach 3 px past each tile's footprint)."""
    sc = scene("ins")
    one = ortho(sc, tmp_path, refraction_image=False, refraction=False, resampling="lanczos", name="one.tif")
    many = ortho(sc, tmp_path, refraction_image=False, refraction=False, resampling="lanczos", name="many.tif",
                 tile_size=48, workers=2)
    assert one.shape == many.shape and one.transform == many.transform and max(one.shape) > 4 * 48
    a, va, _ = read_ortho(one.path)
    b, vb, _ = read_ortho(many.path)
    np.testing.assert_array_equal(va, vb)
    np.testing.assert_allclose(a[va], b[vb], rtol=0, atol=1e-3)


@pytest.mark.parametrize("src_dtype,dtype,method,resampling,nodata,resolution", [
    ("float32", None, "backward", "lanczos", None, None), ("uint8", None, "backward", "bilinear", 0, None),
    ("uint8", "float32", "backward", "bicubic", None, None), ("uint16", None, "forward", "bilinear", None, None),
    ("uint16", None, "backward", "bilinear", 0, 2.5), ("uint16", "uint8", "backward", "bilinear", None, None)])
def test_whole_source_reads_write_the_same_pixels(tmp_path, device, src_dtype, dtype, method, resampling, nodata,
                                                   resolution):
    """source_reads="whole" (the source read once, by strips on threads, into device memory)
    writes exactly the pixels and mask of per-tile window reads: masked sources, a widened
    integer source, the forward method, and an output coarser than the source (its tiles
    read reduced windows either way)."""
    sc = scene("ins")
    scale = {"uint8": 200.0, "uint16": 3000.0, "float32": 1.0}[src_dtype]
    src = write_image(tmp_path / "src.tif", sc.image(False) * scale + 1.0, src_dtype)
    if nodata is not None:  # a nodata value: the source is masked
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            ds = rasterio.open(src, "r+")
        with ds:
            values = ds.read(1)
            values[:40, :60] = nodata
            ds.write(values, 1)
            ds.nodata = nodata
    tile = 32 if resolution else 96
    kw = dict(dem=sc.dem, refraction=False, device=device, method=method, resampling=resampling, tile_size=tile,
              workers=2, **({"dtype": dtype} if dtype else {}), **({"resolution": resolution} if resolution else {}))
    sensor = FrameSensor(sc.camera, sc.pose)
    with warnings.catch_warnings(record=True) as seen:  # a narrower output: clipped values counted both ways
        warnings.simplefilter("always", OrthowarpWarning)
        tiles = orthorectify(src, sensor, tmp_path / "tiles.tif", source_reads="tiles", **kw)
        whole = orthorectify(src, sensor, tmp_path / "whole.tif", source_reads="whole", **kw)
    clipped = [str(w.message) for w in seen if "were clipped" in str(w.message)]
    assert len(clipped) == (2 if dtype == "uint8" else 0), clipped
    assert tiles.profile["source_reads"] == "tiles" and whole.profile["source_reads"] == "whole"
    if not resolution:  # read whole, by strips
        assert whole.profile["whole_source_strips"] >= 1 and "whole_source_strips" not in tiles.profile
    with rasterio.open(tiles.path) as a, rasterio.open(whole.path) as b:
        assert max(a.shape) > 2 * tile
        np.testing.assert_array_equal(a.dataset_mask(), b.dataset_mask())
        np.testing.assert_array_equal(a.read(), b.read())
        if nodata is not None:
            assert 0 < (a.dataset_mask() == 0).mean() < 1


def test_source_reads_is_checked(tmp_path):
    sc = scene("ins")
    src = write_image(tmp_path / "src.tif", sc.image(False))
    with pytest.raises(ParamError, match="source_reads"):
        orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / "o.tif", dem=sc.dem, source_reads="all")
    assert not os.path.exists(tmp_path / "o.tif")


@pytest.mark.parametrize("src_dtype,scale,tile,codec", [("uint8", 200.0, 512, "hybrid"), ("float32", 1.0, 1024, "hybrid"),
                                                         ("uint16", 3000.0, 256, "hybrid"), ("uint8", 200.0, 512, "warp")])
def test_block_codecs_write_the_same_pixels(tmp_path, device, src_dtype, scale, tile, codec):
    """Blocks encoded in Warp kernels (block_codec "hybrid": predictor, masks and overviews on
    the device; libdeflate here, nvCOMP too on a GPU that has it; "warp": deflated by
    orthowarp's kernels too) decode to exactly the host writer's pixels and masks at every
    level, tiles without data included."""
    sc = scene("ins")
    kw = dict(refraction_image=False, refraction=False, src_dtype=src_dtype, scale=scale, tile_size=tile, device=device,
              resolution=0.05)
    host = ortho(sc, tmp_path, name="host.tif", block_codec="host", **kw)
    dev = ortho(sc, tmp_path, name="dev.tif", block_codec=codec, **kw)
    assert dev.profile["block_codec"] in (("device", "hybrid") if codec == "hybrid" else ("warp",))
    if codec == "warp":
        assert set(dev.profile["blocks_by_codec"]) == {"warp"}
        assert os.path.getsize(dev.path) <= 1.10 * os.path.getsize(host.path)
    if tile % 512 == 0:  # tiles of whole 512-pixel blocks are encoded on the device; others mostly on the host
        assert sum(dev.profile["blocks_by_codec"].values()) > 0
    with rasterio.open(host.path) as a:
        levels = len(a.overviews(1)) + 1
        factors, shape0 = a.overviews(1), a.shape
        assert levels >= 3 and max(a.shape) > 2 * tile
    for k in range(levels):
        kw = {"overview_level": k - 1} if k else {}
        with rasterio.open(host.path, **kw) as a, rasterio.open(dev.path, **kw) as b:
            np.testing.assert_array_equal(a.dataset_mask(), b.dataset_mask())
            np.testing.assert_array_equal(a.read(), b.read())
            structure = b.tags(ns="IMAGE_STRUCTURE")
            assert structure == a.tags(ns="IMAGE_STRUCTURE") and structure["COMPRESSION"] == "DEFLATE"
            assert b.block_shapes == a.block_shapes and b.profile["tiled"]
            if k == 0:
                assert structure["LAYOUT"] == "COG"
            else:
                # GDAL states the layout of the file, on its full-resolution image only; an
                # overview level is the full image reduced by its factor (rounded up)
                assert "LAYOUT" not in structure
                assert b.shape == tuple(-(-s // factors[k - 1]) for s in shape0)


@pytest.mark.parametrize("is_cuda,nvcomp,level,want", [
    (True, True, 1, "nvcomp"), (True, True, 4, "nvcomp"), (True, True, 6, "hybrid"), (True, False, 1, "hybrid"),
    (True, False, 6, "hybrid"), (False, True, 6, "host"), (False, False, 1, "host")])
def test_auto_block_codec(monkeypatch, is_cuda, nvcomp, level, want):
    """block_codec "auto": nvCOMP at levels 1-4 where it is installed, else on a GPU the device
    kernels with the host cores ("hybrid"); on the CPU the host path."""
    from types import SimpleNamespace

    from orthowarp.pipeline.ortho import sink as po

    monkeypatch.setattr(po, "nvcomp_available", lambda: nvcomp)
    assert po.choose_block_codec("auto", SimpleNamespace(is_cuda=is_cuda), True, level) == want
    assert po.choose_block_codec("auto", SimpleNamespace(is_cuda=is_cuda), False, level) == "host"  # not a deflate COG


def test_hybrid_codecs_without_nvcomp_are_warp_and_host(monkeypatch):
    """block_codec "hybrid" without nvCOMP (or at levels 5-12): orthowarp's deflate kernels on
    the device, at the level's search depth, and libdeflate on the host cores."""
    import warp as wp

    from orthowarp.pipeline.ortho import sink as po
    from orthowarp.pipeline.raster.device import HostDeflate, WarpDeflate

    monkeypatch.setattr(po, "nvcomp_available", lambda: False)
    for level, depth in ((1, 4), (6, 32), (9, 128)):
        gpu, host = po.device_codecs("hybrid", level, wp.get_device("cpu"))
        assert isinstance(gpu, WarpDeflate) and gpu.depth == depth
        assert isinstance(host, HostDeflate) and host.level == level
        host.close()


def _levels(path):
    """(pixels, mask, IMAGE_STRUCTURE) of the full resolution and each overview of a file."""
    with rasterio.open(path) as ds:
        n = len(ds.overviews(1))
    out = []
    for k in range(n + 1):
        with rasterio.open(path, **({"overview_level": k - 1} if k else {})) as ds:
            out.append((ds.read(), ds.dataset_mask(), ds.tags(ns="IMAGE_STRUCTURE")))
    return out


@pytest.mark.parametrize("src_dtype,scale", [("uint16", 20.0), ("float32", 1.0)])
def test_zstd_cog_streams_with_the_deflate_pixels(tmp_path, monkeypatch, src_dtype, scale):
    """compress="zstd" streams through orthowarp's COG writer (GDAL's COG driver is not
    called: no second write) and decodes to the deflate COG's pixels and masks at every level;
    GDAL reads a ZSTD COG, with the predictor for integer data."""
    import orthowarp.pipeline.ortho as po

    sc = scene("opk")
    kw = dict(refraction_image=False, refraction=False, resolution=0.25, src_dtype=src_dtype, scale=scale)
    deflate = ortho(sc, tmp_path, name="deflate.tif", **kw)

    def no_copy(*args, **kwargs):
        raise AssertionError("a streamed COG is not copied by GDAL")

    monkeypatch.setattr(po, "finish", no_copy)
    zstd = ortho(sc, tmp_path, name="zstd.tif", compress="zstd", **kw)
    assert zstd.profile["block_codec"] == "host"
    a, b = _levels(deflate.path), _levels(zstd.path)
    assert len(a) == len(b) >= 2
    for (da, ma, _), (db, mb, structure) in zip(a, b):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)  # NaN == NaN here
        assert structure["COMPRESSION"] == "ZSTD"
        assert structure.get("PREDICTOR") == ("2" if src_dtype == "uint16" else None)
    assert b[0][2]["LAYOUT"] == "COG"
    assert_no_leftovers(tmp_path, "zstd.tif.")


@pytest.mark.parametrize("is_cuda,nvcomp,choice,want", [
    (True, True, "auto", "host"), (True, False, "auto", "host"), (False, True, "auto", "host"),
    (True, True, "host", "host"), (True, True, "nvcomp", "nvcomp"), (False, False, "host", "host")])
def test_zstd_block_codec(monkeypatch, is_cuda, nvcomp, choice, want):
    """block_codec for a zstd COG: "auto" and "host" are the host writer's threads; nvCOMP's
    Zstd on request on a CUDA device where nvCOMP is installed."""
    from types import SimpleNamespace

    from orthowarp.pipeline.ortho import sink as po

    monkeypatch.setattr(po, "nvcomp_available", lambda: nvcomp)
    device = SimpleNamespace(is_cuda=is_cuda)
    assert po.choose_block_codec(choice, device, True, None, compress="zstd") == want
    assert po.choose_block_codec(choice, device, False, None, compress="zstd") == "host"  # not streamed


def test_zstd_block_codec_errors(tmp_path, monkeypatch):
    """Block codecs "warp" and "hybrid" compress deflate only: refused with zstd before any work, naming
    block_codec; "nvcomp" needs a CUDA device and nvCOMP; a host zstd codec for the device
    encoder takes the level."""
    import warp as wp
    from types import SimpleNamespace

    from orthowarp.errors import DeviceError
    from orthowarp.pipeline.ortho import sink as po
    from orthowarp.pipeline.raster.device import HostZstd

    for codec in ("warp", "hybrid"):
        with pytest.raises(ParamError, match=f"block_codec '{codec}' compresses deflate blocks only"):
            po.choose_block_codec(codec, SimpleNamespace(is_cuda=True), True, None, compress="zstd")
    with pytest.raises(ParamError, match="CUDA"):
        po.choose_block_codec("nvcomp", SimpleNamespace(is_cuda=False), True, None, compress="zstd")
    monkeypatch.setattr(po, "nvcomp_available", lambda: False)
    with pytest.raises(DeviceError, match="nvCOMP"):
        po.choose_block_codec("nvcomp", SimpleNamespace(is_cuda=True), True, None, compress="zstd")
    (codec,) = po.device_codecs("device", 3, wp.get_device("cpu"), "zstd")
    assert isinstance(codec, HostZstd) and codec.level == 3
    codec.close()
    (codec,) = po.device_codecs("device", None, wp.get_device("cpu"), "zstd")
    assert codec.level == 9
    codec.close()
    sc = scene("opk")
    src = write_image(tmp_path / "src.tif", sc.image(False))
    with pytest.raises(ParamError, match="block_codec 'warp'"):
        orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / "o.tif", dem=sc.dem, compress="zstd",
                     block_codec="warp")
    assert not os.path.exists(tmp_path / "o.tif")


@pytest.mark.skipif(not DEVICES or not any(d.startswith("cuda") for d in DEVICES), reason="needs a CUDA device")
def test_zstd_on_the_gpu_writes_the_host_pixels(tmp_path):
    """On a CUDA device a zstd COG's blocks are made there and compressed by nvCOMP's Zstd
    (block_codec "auto", where nvCOMP is installed; else the host writer): the file decodes to
    the host path's pixels and masks at every level."""
    from orthowarp.pipeline.raster.device import nvcomp_available

    sc = scene("ins")
    kw = dict(refraction_image=False, refraction=False, src_dtype="uint8", scale=200.0, tile_size=512,
              resolution=0.05, compress="zstd", device="cuda:0")
    host = ortho(sc, tmp_path, name="host.tif", block_codec="host", **kw)
    dev = ortho(sc, tmp_path, name="dev.tif", **kw)
    want = "nvcomp" if nvcomp_available() else "host"
    assert dev.profile["block_codec"] == want
    if want == "nvcomp":
        assert dev.profile["blocks_by_codec"]["nvcomp"] > 0
    a, b = _levels(host.path), _levels(dev.path)
    assert len(a) == len(b) >= 3
    for (da, ma, sa), (db, mb, sb) in zip(a, b):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)
        assert sa == sb and sb["COMPRESSION"] == "ZSTD"


def test_measurement_detects_a_known_error(tmp_path):
    """The yardstick works: orthorectifying with the camera moved by (+0.3, -0.2) pixels east
    and north yields a measured shift of (dy, dx) = (+0.2, +0.3) (the texture appears moved by
    the camera's error) to 0.03 px (terrain relief makes the error not quite a translation)."""
    sc = scene("opk")
    res_m = 0.56
    p = sc.pose.params
    moved = ow.Pose.from_opk(p["x"] + 0.3 * res_m, p["y"] - 0.2 * res_m, p["z"], p["omega"], p["phi"], p["kappa"],
                             crs=UTM32)
    src = write_image(tmp_path / "src.tif", sc.image(False))
    res = orthorectify(src, FrameSensor(sc.camera, moved), tmp_path / "o.tif", dem=sc.dem, refraction=False, resolution=res_m,
                       device="cpu")
    m, _, _, _ = measure(sc, res)
    print(f"\n[opk, camera moved by (+0.3, -0.2) px east/north] {describe(m)}")
    assert m["n_tiles"] >= 8
    assert m["mean"] == pytest.approx((0.2, 0.3), abs=0.03)
    assert m["rms"] == pytest.approx(np.hypot(0.2, 0.3), abs=0.03)


# ------------------------------------------------------------------------------------------
# 2. Refraction
# ------------------------------------------------------------------------------------------
OBLIQUE = ["ins_oblique", "opk_oblique"]


@pytest.mark.parametrize("name", OBLIQUE)
def test_ortho_with_refraction_matches_truth(name, tmp_path, device):
    sc = scene(name)
    res = ortho(sc, tmp_path, refraction_image=True, refraction=True, device=device)
    m, _, _, _ = measure(sc, res)
    print(f"\n[{name}, refraction on/on] {res.shape[1]} x {res.shape[0]} px at {res.resolution:.4f} m: {describe(m)}")
    assert m["n_tiles"] >= 8
    assert m["rms"] <= RMS_MAX, describe(m)


def predicted_refraction_shift(sc, result, centers):
    """Shift (dy, dx) (ortho px) that ignoring refraction causes at ortho pixels (row, col).

    The orthoimage made without refraction shows at ground point G the source pixel
    p = straight-ray projection of G, whose refracted ray (as rendered) meets the ground at G';
    so ortho(G) = T(G + D), D = G' - G, i.e. the texture moved by -D: in pixels
    (dy, dx) = (D_north, -D_east) / resolution.
    """
    x, y = result.transform @ (centers[:, 1], centers[:, 0])
    g = sc.object_point(x, y)
    cam_dirs = (g - sc.ref_pose.center) @ sc.ref_pose.rotation  # R^T (G - C), row-wise
    pix = sc.ref_camera.pixels(cam_dirs)
    _, txy = sc.renderer(True).ground(pix)
    d = txy - np.stack([x, y], axis=1)
    return np.stack([d[:, 1], -d[:, 0]], axis=1) / result.resolution, pix


@pytest.mark.parametrize("name", OBLIQUE)
def test_ignoring_refraction_shifts_by_the_model(name, tmp_path, device):
    """Orthorectifying the refraction-rendered image with refraction=False: the measured shift is
    the refraction displacement, tile by tile, within 0.05 px (< 10 % of it)."""
    sc = scene(name)
    res = ortho(sc, tmp_path, refraction_image=True, refraction=False, device=device)
    m, _, _, _ = measure(sc, res)
    pred, pix = predicted_refraction_shift(sc, res, m["centers"])
    mag = np.hypot(*pred.T)
    print(f"\n[{name}, rendered with refraction, ortho without] {describe(m)}; predicted "
          f"{mag.min():.3f}..{mag.max():.3f} px, mean (dy, dx) ({pred[:, 0].mean():+.4f}, {pred[:, 1].mean():+.4f})")
    assert m["n_tiles"] >= 8
    assert mag.min() > 0.2, "refraction must displace the ground by several tenths of a pixel"
    # the prediction agrees with orthowarp's own refraction displacement at those pixels
    on = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=sc.dem, crs=UTM32, refraction=True, device="cpu")
    off = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=sc.dem, crs=UTM32, refraction=False, device="cpu")
    d = on[:, :2] - off[:, :2]
    pred_ow = np.stack([d[:, 1], -d[:, 0]], axis=1) / res.resolution
    np.testing.assert_allclose(pred_ow, pred, atol=0.01)
    diff = np.hypot(*(m["shifts"] - pred).T)
    print(f"  measured - predicted per tile: RMS {np.sqrt(np.mean(diff**2)):.4f} px, max {diff.max():.4f} px")
    # 0.05 px per tile (the stricter of "0.05 px or 10 %" here, where the shift is ~1 px)
    worst = int(np.argmax(diff))
    assert diff.max() <= 0.05, (f"tile at {m['centers'][worst]}: measured {m['shifts'][worst]}, "
                                f"predicted {pred[worst]}")


# ------------------------------------------------------------------------------------------
# 3. Resampling, data types, nodata, layout
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("resampling", ["nearest", "bilinear", "bicubic", "lanczos"])
def test_resampling_methods(resampling, tmp_path):
    sc = scene("opk")
    res = ortho(sc, tmp_path, refraction_image=False, refraction=False, resampling=resampling)
    m, data, valid, t = measure(sc, res)
    # away from the footprint's edge, where kernels lose taps
    inner = valid.copy()
    for ax in (0, 1):
        for sh in (-3, 3):
            inner &= np.roll(valid, sh, axis=ax)
    rel = np.sqrt(np.mean((data - t)[inner] ** 2)) / sc.texture.std
    print(f"\n[opk, {resampling}] relative RMS error {rel:.4f}; {describe(m)}")
    assert m["n_tiles"] >= 8
    if resampling == "nearest":
        assert rel < 0.5 and m["rms"] <= 0.2
    else:
        assert rel < 0.12
        assert m["rms"] <= RMS_MAX


def test_sharper_kernels_are_closer_to_the_truth(tmp_path):
    sc = scene("opk")
    errs = {}
    for method in ("nearest", "bilinear", "bicubic", "lanczos"):
        res = ortho(sc, tmp_path, refraction_image=False, refraction=False, resampling=method, name=f"{method}.tif")
        data, valid, _ = read_ortho(res.path)
        t = truth(sc, res)
        inner = valid & np.roll(valid, 4, 0) & np.roll(valid, -4, 0) & np.roll(valid, 4, 1) & np.roll(valid, -4, 1)
        errs[method] = np.sqrt(np.mean((data - t)[inner] ** 2))
    assert errs["bicubic"] < errs["bilinear"] < errs["nearest"]
    assert errs["lanczos"] < errs["bilinear"]


def test_bilinear_ortho_is_the_bilinear_source(tmp_path):
    """Every valid pixel of a bilinear orthoimage is the source's bilinear interpolation, written
    out here, at the source position the reference's closed-form collinearity gives for the
    pixel's centre on the scene's DEM surface (no refraction): to 1e-3 of the texture's
    spread (seen: 3e-6 of it, float32 rounding of values of a few hundred, and the kernels'
    interpolation of positions between coarse nodes). A wrong weight, tap or half-pixel or
    half-DEM-cell offset shows at once."""
    sc = scene("opk")
    res = ortho(sc, tmp_path, refraction_image=False, refraction=False, resampling="bilinear")
    data, valid, _ = read_ortho(res.path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(tmp_path / "src_ortho.tif") as s:
            img = s.read(1).astype(np.float64)
    pix = source_position(sc, res)
    x, y = pix[..., 0] - 0.5, pix[..., 1] - 0.5  # pixel centres at half-integers
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    rows, cols = img.shape
    ok = valid & (x0 >= 0) & (y0 >= 0) & (x0 + 1 < cols) & (y0 + 1 < rows)  # all four taps inside
    assert ok.sum() > 0.9 * valid.sum()
    fx, fy, r, c = (x - x0)[ok], (y - y0)[ok], y0[ok], x0[ok]
    want = ((1 - fy) * ((1 - fx) * img[r, c] + fx * img[r, c + 1])
            + fy * ((1 - fx) * img[r + 1, c] + fx * img[r + 1, c + 1]))
    err = np.abs(data[ok] - want)
    assert err.max() < 1e-3 * img.std(), f"max {err.max():.3g} (spread {img.std():.3g})"


@pytest.mark.parametrize("src_dtype,dtype,expected", [
    ("uint8", None, "uint8"), ("uint16", None, "uint16"), ("float32", None, "float32"),
    ("uint16", "float32", "float32"), ("float32", "uint16", "uint16"), ("uint8", "uint16", "uint16"),
])
def test_output_dtype_and_nodata(src_dtype, dtype, expected, tmp_path):
    sc = scene("opk")
    scale, offset = {"uint8": (0.3, -172.0), "uint16": (20.0, 0.0), "float32": (1.0, 0.0)}[src_dtype]
    res = ortho(sc, tmp_path, refraction_image=False, refraction=False, src_dtype=src_dtype, name="o.tif",
                scale=scale, offset=offset, **({} if dtype is None else {"dtype": dtype}))
    data, valid, facts = read_ortho(res.path)
    assert facts["dtype"] == expected
    assert facts["crs"].to_epsg() == 32632 and facts["transform"] == res.transform
    rows, cols = res.shape
    assert data.shape == (rows, cols)
    # the footprint is a rotated quadrilateral: its bounding box has nodata corners
    assert not valid[0, 0] and not valid[-1, -1] and valid[rows // 2, cols // 2]
    assert 0.5 < valid.mean() < 0.95
    with rasterio.open(res.path) as ds:
        raw = ds.read(1)
        mask = ds.dataset_mask()
    if expected == "float32":
        assert np.all(np.isnan(raw[~valid])) and np.all(np.isfinite(raw[valid]))
    else:
        assert np.all(mask[~valid] == 0) and np.all(mask[valid] == 255)
        assert np.all(raw[~valid] == 0)
    # the values are the texture's, in the source's units
    t = truth(sc, res) * scale + offset
    inner = valid & np.roll(valid, 3, 0) & np.roll(valid, -3, 0) & np.roll(valid, 3, 1) & np.roll(valid, -3, 1)
    rel = np.sqrt(np.mean((data - t)[inner] ** 2)) / (sc.texture.std * scale)
    assert rel < 0.12
    m, _, _, _ = measure(sc, res, scale=scale, offset=offset)
    assert m["rms"] <= RMS_MAX


def test_cog_has_overviews_and_tiles(tmp_path):
    sc = scene("opk")
    # half the GSD: an orthoimage > 512 px, enough for an overview level
    res = ortho(sc, tmp_path, refraction_image=False, refraction=False, resolution=0.25, src_dtype="uint16",
                scale=20.0, name="cog.tif")
    assert max(res.shape) > 1024
    with rasterio.open(res.path) as ds:
        assert ds.driver == "GTiff"
        assert ds.profile.get("tiled") and ds.block_shapes[0][0] == ds.block_shapes[0][1] < ds.height
        assert len(ds.overviews(1)) >= 1
        assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT", "").upper() == "COG"
        assert ds.mask_flag_enums[0] == [rasterio.enums.MaskFlags.per_dataset]
        # the overview's mask follows the full resolution one
        ov = ds.dataset_mask(out_shape=(ds.height // 2, ds.width // 2))
        assert ov.min() == 0 and ov.max() == 255


def test_gtiff_driver_matches_cog(tmp_path):
    sc = scene("opk")
    src = write_image(tmp_path / "src.tif", sc.image(False) * 20.0, "uint16")
    a = orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / "a.tif", dem=sc.dem, refraction=False, device="cpu")
    b = orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / "b.tif", dem=sc.dem, refraction=False, device="cpu",
                     driver="GTiff")
    assert a.transform == b.transform and a.shape == b.shape
    with rasterio.open(a.path) as da, rasterio.open(b.path) as db:
        assert db.profile.get("tiled")
        np.testing.assert_array_equal(da.read(), db.read())
        np.testing.assert_array_equal(da.dataset_mask(), db.dataset_mask())
        assert da.mask_flag_enums[0] == db.mask_flag_enums[0] == [rasterio.enums.MaskFlags.per_dataset]
    # internal masks: no sidecar (.msk, .aux.xml) and no temporary files
    assert sorted(os.listdir(tmp_path)) == ["a.tif", "b.tif", "src.tif"]


@pytest.mark.parametrize("driver,compress", [("COG", "deflate"), ("GTiff", "deflate"), ("COG", "zstd")])
def test_compress_level(driver, compress, tmp_path):
    """The level reaches the codec (other bytes, the same pixels); out-of-range levels and
    levels for codecs without one are errors."""
    sc = scene("opk")
    src = write_image(tmp_path / "src.tif", sc.image(False) * 20.0, "uint16")
    kw = dict(dem=sc.dem, refraction=False, device="cpu", driver=driver, compress=compress)
    a = orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / "a.tif", compress_level=1, **kw)
    b = orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / "b.tif", compress_level=12 if compress == "deflate" else 22,
                     **kw)
    assert os.path.getsize(b.path) != os.path.getsize(a.path)
    with rasterio.open(a.path) as da, rasterio.open(b.path) as db:
        np.testing.assert_array_equal(da.read(), db.read())
    for level, comp in [(0, "deflate"), (13, "deflate"), (23, "zstd"), (5, "lzw")]:
        with pytest.raises(ParamError, match="compress_level"):
            orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / "c.tif", compress_level=level,
                         **{**kw, "compress": comp})
    assert not os.path.exists(tmp_path / "c.tif")


def test_source_nodata_is_honoured(tmp_path):
    """Source pixels marked nodata (here 0 in a uint16 image with nodata=0) give nodata in the
    orthoimage wherever they would be sampled, and never a 0 value."""
    sc = scene("opk")
    img = np.clip(np.rint(sc.image(False) * 20.0), 1, 65535).astype(np.uint16)
    img[100:150, 200:260] = 0
    src = tmp_path / "nd.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(src, "w", driver="GTiff", width=400, height=300, count=1, dtype="uint16", nodata=0) as dst:
            dst.write(img, 1)
    res = orthorectify(src, FrameSensor(sc.camera, sc.pose), tmp_path / "o.tif", dem=sc.dem, refraction=False, device="cpu")
    data, valid, _ = read_ortho(res.path)
    pix = source_position(sc, res)
    hole = (pix[..., 0] > 200.5) & (pix[..., 0] < 259.5) & (pix[..., 1] > 100.5) & (pix[..., 1] < 149.5)
    assert hole.sum() > 1000
    assert not np.any(valid & hole)
    assert not np.any(valid & (data == 0))


# ------------------------------------------------------------------------------------------
# 4. Bad input
# ------------------------------------------------------------------------------------------
SMALL = dict(f=100.0, pixel=0.06, size=(64, 48))


def small_setup(tmp_path, *, dtype="uint8"):
    """A nadir 64 x 48 camera over a flat-ish map DEM, and a random source image."""
    cam = ow.FrameCamera(SMALL["f"], SMALL["pixel"], SMALL["size"])
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 1400.0, 0.0, 0.0, 0.0, crs=UTM32)
    dem, _ = map_dem(lambda e, n: 450.0 + 0.01 * e + 0.0 * n, OPK_X, OPK_Y, 100, 2.0)
    rng = np.random.default_rng(0)
    src = write_image(tmp_path / "src.tif", rng.integers(1, 255, (48, 64)), dtype)
    return cam, pose, dem, src


def test_small_setup_works(tmp_path):
    cam, pose, dem, src = small_setup(tmp_path)
    res = orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=dem, device="cpu")
    assert not [f for f in os.listdir(tmp_path) if ".orthowarp-tmp-" in f]
    # what was written: a georeferenced single-band image of the source's type whose valid
    # pixels are the source's (values 1-254, none made up), around the camera's nadir
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)  # a camera image
        with rasterio.open(src) as s:
            source = s.read(1)
    with rasterio.open(res.path) as o:
        assert o.crs == rasterio.crs.CRS.from_user_input(UTM32) and o.count == 1 and o.dtypes[0] == "uint8"
        data, valid = o.read(1), o.dataset_mask() > 0
        nadir_row, nadir_col = o.index(OPK_X, OPK_Y)
    assert 0.3 < valid.mean() < 1.0 and valid[nadir_row, nadir_col]
    assert source.min() <= data[valid].min() and data[valid].max() <= source.max()
    assert abs(float(data[valid].mean()) - float(source.mean())) < 10.0


def test_missing_source(tmp_path):
    cam, pose, dem, _ = small_setup(tmp_path)
    missing = tmp_path / "nope.tif"
    with pytest.raises(RasterIOError, match="nope.tif"):
        orthorectify(missing, FrameSensor(cam, pose), tmp_path / "out.tif", dem=dem, device="cpu")
    assert_no_leftovers(tmp_path, "out.tif")


def test_corrupt_source(tmp_path):
    cam, pose, dem, _ = small_setup(tmp_path)
    bad = tmp_path / "bad.tif"
    bad.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(RasterIOError, match="bad.tif"):
        orthorectify(bad, FrameSensor(cam, pose), tmp_path / "out.tif", dem=dem, device="cpu")
    assert_no_leftovers(tmp_path, "out.tif")


def test_truncated_source(tmp_path):
    sc = scene("opk")
    full = write_image(tmp_path / "full.tif", sc.image(False) * 20.0, "uint16")
    data = full.read_bytes()
    (tmp_path / "trunc.tif").write_bytes(data[:len(data) // 2])  # header and first strips only
    full.unlink()
    with pytest.raises(RasterIOError) as info:
        orthorectify(tmp_path / "trunc.tif", FrameSensor(sc.camera, sc.pose), tmp_path / "out.tif", dem=sc.dem,
                     refraction=False, device="cpu")
    assert_no_leftovers(tmp_path, "out.tif")
    assert "trunc.tif" in str(info.value) and ".orthowarp-tmp-" not in str(info.value), str(info.value)


def test_image_size_mismatch(tmp_path):
    _, pose, dem, src = small_setup(tmp_path)
    cam = ow.FrameCamera(SMALL["f"], SMALL["pixel"], (60, 48))
    with pytest.raises(ParamError, match="64 x 48"):
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=dem, device="cpu")
    assert_no_leftovers(tmp_path, "out.tif")


def test_existing_output_needs_overwrite(tmp_path):
    cam, pose, dem, src = small_setup(tmp_path)
    dst = tmp_path / "out.tif"
    dst.write_bytes(b"precious")
    with pytest.raises(RasterIOError, match="out.tif"):
        orthorectify(src, FrameSensor(cam, pose), dst, dem=dem, device="cpu")
    assert dst.read_bytes() == b"precious"
    assert not [f for f in os.listdir(tmp_path) if ".orthowarp-tmp-" in f]
    orthorectify(src, FrameSensor(cam, pose), dst, dem=dem, device="cpu", overwrite=True)
    with rasterio.open(dst) as ds:
        assert ds.width > 0


def test_unwritable_output_folder(tmp_path):
    cam, pose, dem, src = small_setup(tmp_path)
    blocker = tmp_path / "afile"
    blocker.write_text("not a folder")
    with pytest.raises(RasterIOError, match="afile"):
        orthorectify(src, FrameSensor(cam, pose), blocker / "out.tif", dem=dem, device="cpu")
    assert blocker.read_text() == "not a folder"
    assert_no_leftovers(tmp_path, "out.tif")


def test_dem_not_covering_the_footprint(tmp_path):
    cam, pose, _, src = small_setup(tmp_path)
    far, _ = map_dem(lambda e, n: 450.0 + 0.0 * e, OPK_X + 5000.0, OPK_Y - 3000.0, 50, 2.0)
    with pytest.raises(GeometryError, match="DEM"):
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=far, device="cpu")
    assert_no_leftovers(tmp_path, "out.tif")


def test_dem_covering_part_of_the_footprint(tmp_path, caplog):
    """A DEM west of x = OPK_X - 5 m only: a warning, nodata east of its edge, data west."""
    cam, pose, _, src = small_setup(tmp_path)
    edge = OPK_X - 5.0
    z = np.full((100, 60), 450.0, np.float32)
    west = ow.Dem(z, Affine(2.0, 0.0, edge - 120.0, 0.0, -2.0, OPK_Y + 100.0), UTM32)
    with caplog.at_level(logging.WARNING):
        res = orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=west, device="cpu")
    assert any(r.levelno == logging.WARNING and "DEM" in r.getMessage() for r in caplog.records), caplog.text
    data, valid, _ = read_ortho(res.path)
    x, y = pixel_centres(res)
    # the nadir footprint: (H - h) / f * image half-size = 950 / 100 * (1.92, 1.44) mm
    inside = (np.abs(x - OPK_X) < 18.24 - 1.0) & (np.abs(y - OPK_Y) < 13.68 - 1.0)
    assert np.all(~valid[x > edge + 0.5])
    assert np.all(valid[inside & (x < edge - 1.0)])
    assert valid.sum() > 0.2 * inside.sum()


def test_camera_seeing_the_horizon(tmp_path):
    """A wide camera pitched 80 deg up sees the sky: GeometryError, nothing written."""
    cam = ow.FrameCamera(3.0, 0.06, (64, 48))
    pose = ow.Pose.from_ins(46.95, 8.9, 1400.0, 0.0, 80.0, 0.0)
    rng = np.random.default_rng(0)
    src = write_image(tmp_path / "src.tif", rng.integers(1, 255, (48, 64)), "uint8")
    dem, _ = geo_dem(lambda e, n: 450.0 + 0.0 * e, 8.9, 46.95, 50, 20.0)
    with pytest.raises(GeometryError, match="horizon"):
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=dem, device="cpu")
    assert_no_leftovers(tmp_path, "out.tif")


def _checkerboard_job(tmp_path, size=(1600, 1200)):
    """A nadir frame over flat ground (GSD 0.12 m) whose source is a one-pixel 0/200
    checkerboard: any output coarser than the source aliases it unless it is area-averaged."""
    cam = ow.FrameCamera(focal_length=50.0, pixel_size=0.01, image_size=size)
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 700.0, 0.0, 0.0, 0.0, crs=UTM32)
    jj, ii = np.meshgrid(np.arange(size[0]), np.arange(size[1]))
    src = write_image(tmp_path / "checker.tif", ((ii + jj) % 2) * 200, "uint8")
    return cam, pose, src


@pytest.mark.parametrize("method", ["backward", "forward"])
@pytest.mark.parametrize("resampling", ["nearest", "bilinear", "lanczos"])
def test_coarse_output_reads_reduced_and_area_averaged(tmp_path, monkeypatch, method, resampling):
    cam, pose, src = _checkerboard_job(tmp_path)
    reads = []
    real_read = rasterio.io.DatasetReader.read

    def read(self, *args, **kwargs):
        out = real_read(self, *args, **kwargs)
        reads.append(out.nbytes)
        return out

    monkeypatch.setattr(rasterio.io.DatasetReader, "read", read)
    res = orthorectify(src, FrameSensor(cam, pose), tmp_path / "coarse.tif", dem=100.0, resolution=1.2, refraction=False,
                       method=method, resampling=resampling, device="cpu")
    monkeypatch.undo()
    data, valid, _ = read_ortho(res.path)
    assert abs(res.shape[0] - 120) <= 2 and abs(res.shape[1] - 160) <= 2  # 192 m x 144 m at 1.2 m
    inner = valid & np.roll(valid, 2, 0) & np.roll(valid, -2, 0) & np.roll(valid, 2, 1) & np.roll(valid, -2, 1)
    assert inner.mean() > 0.8
    # the checkerboard's mean, 100, everywhere: 10 x 10 source pixels per output pixel,
    # averaged (without it, the output is all 0 or all 200 or a moire of them)
    np.testing.assert_allclose(data[inner], 100.0, atol=3.0)
    # the one 512 x 512 output tile covers the whole 1600 x 1200 image (1.9 MB at full
    # resolution): read reduced 10 x, about 20 kB (plus the resampling's margin)
    assert reads and max(reads) < 40_000, reads


def test_coarse_output_of_a_float_source_matches_block_means(tmp_path):
    """Area averaging is the mean of the source pixels under an output pixel: a smooth ramp
    plus the checkerboard, at 8 source pixels per output pixel."""
    cam = ow.FrameCamera(focal_length=50.0, pixel_size=0.01, image_size=(800, 640))
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 700.0, 0.0, 0.0, 0.0, crs=UTM32)
    jj, ii = np.meshgrid(np.arange(800), np.arange(640))
    image = 0.25 * jj + ((ii + jj) % 2) * 40.0
    src = write_image(tmp_path / "ramp.tif", image, "float32")
    res = orthorectify(src, FrameSensor(cam, pose), tmp_path / "o.tif", dem=100.0, resolution=0.96, refraction=False,
                       resampling="bilinear", device="cpu", tile_size=32)
    data, valid, _ = read_ortho(res.path)
    inner = valid & np.roll(valid, 2, 0) & np.roll(valid, -2, 0) & np.roll(valid, 2, 1) & np.roll(valid, -2, 1)
    # the truth at an output pixel centre: the ramp there plus the checkerboard's mean; the
    # source column of an output pixel comes from projecting its centre (nadir, kappa 0:
    # x = east, source col = (x - X0) / GSD + width / 2)
    x, _ = res.transform @ (np.arange(res.shape[1]) + 0.5, np.zeros(res.shape[1]))
    col = (np.asarray(x) - OPK_X) / 0.12 + 400.0
    expected = np.broadcast_to(0.25 * (col - 0.5) + 20.0, res.shape)
    np.testing.assert_allclose(data[inner], expected[inner], atol=0.8)


@pytest.mark.parametrize("src_dtype,dtype,values,clipped", [
    ("uint16", "uint8", [10, 300], 0.5), ("float32", "uint8", [-5.0, 100.0], 0.5),
    ("float32", "uint16", [1.0, 70000.0], 0.5), ("uint16", "uint8", [10, 250], 0.0),
    ("uint8", "uint8", [10, 250], 0.0)])
def test_narrowing_dtype_warns_with_the_clipped_fraction(tmp_path, src_dtype, dtype, values, clipped):
    cam = ow.FrameCamera(focal_length=50.0, pixel_size=0.01, image_size=(64, 48))
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 700.0, 0.0, 0.0, 0.0, crs=UTM32)
    jj, _ = np.meshgrid(np.arange(64), np.arange(48))
    src = write_image(tmp_path / "s.tif", np.where(jj < 32, values[0], values[1]), src_dtype)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = orthorectify(src, FrameSensor(cam, pose), tmp_path / "o.tif", dem=100.0, refraction=False, dtype=dtype,
                           resampling="nearest", device="cpu")
    ours = [w for w in caught if issubclass(w.category, ow.errors.OrthowarpWarning)]
    if not clipped:
        assert ours == []
        return
    assert len(ours) == 1
    msg = str(ours[0].message)
    assert "s.tif" in msg and f"outside the {dtype} range [0, {np.iinfo(dtype).max}]" in msg and "o.tif" in msg
    frac = float(msg.split("%")[0].split(": ")[-1]) / 100
    assert abs(frac - clipped) < 0.08, msg  # source windows overlap a little at tile edges
    data, valid, _ = read_ortho(res.path)
    top = np.iinfo(dtype).max
    assert data[valid].min() == np.clip(values[0], 0, top) and data[valid].max() == np.clip(values[1], 0, top)


def test_partial_dem_cover_warning_names_the_image(tmp_path, caplog):
    """A DEM that covers only part of the footprint: the ortho is written, and the warning
    says which image."""
    from rasterio.transform import from_origin

    cam = ow.FrameCamera(50.0, 0.01, (64, 48))
    pose = ow.Pose.from_opk(500000.0, 5200000.0, 600.0, 1.0, -2.0, 30.0, crs="EPSG:32632")
    src = tmp_path / "tiny.tif"
    with rasterio.open(src, "w", driver="GTiff", width=64, height=48, count=1, dtype="uint8") as dst:
        dst.write(np.full((1, 48, 64), 100, np.uint8))
    dem = tmp_path / "half.tif"  # 0.5 m cells over x < 500017.5 only (the footprint: x 500013.5-500021.4)
    with rasterio.open(dem, "w", driver="GTiff", width=40, height=40, count=1, dtype="float32", crs="EPSG:32632",
                       transform=from_origin(499997.5, 5200020.0, 0.5, 0.5)) as dst:
        dst.write(np.full((1, 40, 40), 100.0, np.float32))
    with caplog.at_level(logging.WARNING, logger="orthowarp"):
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "o.tif", dem=str(dem), device="cpu", refraction=False)
    msgs = [r.getMessage() for r in caplog.records if "only partly" in r.getMessage()]
    assert msgs and "tiny.tif" in msgs[0], [r.getMessage() for r in caplog.records]


def _rgb_frame(tmp_path):
    """A uint8 RGB frame of 320 x 240 (smooth stripes) and its camera and pose: (source path,
    camera, pose)."""
    cam = ow.FrameCamera(50.0, 0.01, (320, 240))
    pose = ow.Pose.from_opk(500000.0, 5200000.0, 600.0, 1.0, -2.0, 30.0, crs="EPSG:32632")
    src = tmp_path / "rgb.tif"
    y, x = np.mgrid[0:240, 0:320]
    rgb = np.stack([128 + 60 * np.sin(x / 9.0), 128 + 60 * np.cos(y / 7.0), 128 + 40 * np.sin((x + y) / 13.0)])
    with rasterio.open(src, "w", driver="GTiff", width=320, height=240, count=3, dtype="uint8") as dst:
        dst.write(rgb.astype(np.uint8))
    return src, cam, pose


@pytest.mark.parametrize("compress, quality", [("jpeg", None), ("jpeg", 75), ("webp", 60)])
def test_lossy_outputs_for_rgb(tmp_path, compress, quality):
    """JPEG / WebP in a COG for uint8 RGB: the quality stated (default 90), an internal mask,
    the pixels close to the lossless ortho's, the file much smaller; refused for other data."""
    src, cam, pose = _rgb_frame(tmp_path)
    kw = dict(dem=100.0, device="cpu", refraction=False)
    ref = orthorectify(src, FrameSensor(cam, pose), tmp_path / "lossless.tif", **kw)
    lossy = orthorectify(src, FrameSensor(cam, pose), tmp_path / "lossy.tif", compress=compress, quality=quality, **kw)
    assert lossy.shape == ref.shape
    with rasterio.open(tmp_path / "lossless.tif") as a, rasterio.open(tmp_path / "lossy.tif") as b:
        tags = b.tags(ns="IMAGE_STRUCTURE")
        assert b.profile["compress"] == compress and tags.get("LAYOUT") == "COG"
        if compress == "jpeg":
            assert tags["JPEG_QUALITY"] == str(quality or 90)
        else:
            assert tags["WEBP_LEVEL"] == str(quality)
        ma, mb = a.dataset_mask() > 0, b.dataset_mask() > 0
        assert (ma == mb).mean() > 0.999
        diff = np.abs(a.read().astype(float) - b.read())[:, ma & mb]
        assert np.mean(diff) < (3.0 if (quality or 90) >= 75 else 6.0), np.mean(diff)
    assert os.path.getsize(tmp_path / "lossy.tif") < 0.6 * os.path.getsize(tmp_path / "lossless.tif")
    with pytest.raises(ParamError, match="quality"):
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "q.tif", quality=80, **kw)  # deflate has no quality
    with pytest.raises(ParamError, match="uint8"):
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "f.tif", compress=compress, dtype="float32", **kw)


def test_jpeg_encoded_by_the_device_kernels(tmp_path):
    """block_codec="warp" for a JPEG ortho: its blocks and overviews made on the device and
    encoded by orthowarp's JPEG kernels: the host writer's file, byte for byte."""
    src, cam, pose = _rgb_frame(tmp_path)
    kw = dict(dem=100.0, device="cpu", refraction=False, compress="jpeg", quality=85, resolution=0.04,
              creation_options={"BLOCKSIZE": 128})
    host = orthorectify(src, FrameSensor(cam, pose), tmp_path / "host.tif", block_codec="host", **kw)
    dev = orthorectify(src, FrameSensor(cam, pose), tmp_path / "dev.tif", block_codec="warp", **kw)
    assert dev.profile["block_codec"] == "warp" and dev.profile["blocks_by_codec"]["warpjpeg"] > 0
    with open(host.path, "rb") as a, open(dev.path, "rb") as b:
        assert a.read() == b.read()
    levels = _levels(dev.path)
    assert len(levels) >= 2 and levels[0][2]["COMPRESSION"] == "YCbCr JPEG" and levels[0][2]["JPEG_QUALITY"] == "85"


def test_coarse_grid_is_the_transformed_pixel_centres():
    """coarse_grid: the output pixel centres every step pixels (the last at or past the tile's
    end), through the output transform (rotated here) and the transformer, bit for bit as
    affine's own product and pyproj give them."""
    from orthowarp.pipeline.ortho import coarse_grid

    transform = Affine(0.1, 0.02, 500000.0, 0.015, -0.1, 5200000.0)
    to_geo = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    got = coarse_grid(transform, to_geo, 100, 37, 50, 33, step=16)
    rows, cols = 100 + np.array([0, 16, 32, 48, 64]) + 0.5, 37 + np.array([0, 16, 32]) + 0.5
    jj, ii = np.meshgrid(cols, rows)
    want = np.stack(to_geo.transform(*(transform @ (jj, ii))), -1)
    assert got.shape == (5, 3, 2) and got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)


def _reference_decimation(pixels: np.ndarray, step: int = 16) -> int:
    """The NumPy reference of the tiles' reduction factor (tiles._rows_decimation, from the
    nodes reduced on the device): the whole number of source pixels per output
    pixel (at least 1) along the coarse grid's rows and columns, from its nodes' source pixels
    ``pixels`` (rows, cols, 2) every ``step`` output pixels; the smaller of the two, so that the
    reduced source is never coarser than the output."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows or columns
        d = [np.nanmin(np.hypot(*np.diff(pixels, axis=ax).reshape(-1, 2).T)) if pixels.shape[ax] > 1 else np.nan
             for ax in (0, 1)]
    ratio = np.nanmin(d) / step if np.isfinite(d).any() else 1.0
    return max(int(np.floor(ratio)), 1)


def _reference_window(nodes: np.ndarray, radius: int, width: int, height: int, margin: int = 2,
                 factor: int = 1) -> tuple[int, int, int, int] | None:
    """The NumPy reference of a tile's source window (tiles._rows_window, from the nodes
    reduced on the device): (col0, row0, col1, row1) from its coarse nodes' source
    pixels at its lowest and highest DEM heights (``nodes`` (2, rows, cols, 2)): their
    bounding box grown by the resampling ``radius`` + 1 and ``margin`` pixels (the
    projection's curvature within a cell is far below a pixel), and by one cell's extent
    where some nodes have no pixel (a tile pixel near them may still have one), clipped to
    the image; None where that is empty. Read reduced by ``factor``, the resampling's reach
    and the margin are in reduced pixels."""
    pix = nodes.reshape(-1, 2)
    ok = np.isfinite(pix).all(axis=1)
    if not ok.any():
        return None
    lo, hi = pix[ok].min(axis=0), pix[ok].max(axis=0)
    grow = (radius + 1 + margin) * factor
    if not ok.all():
        steps = [np.hypot(*np.diff(nodes, axis=ax).reshape(-1, 2).T) for ax in (1, 2)]
        steps = np.concatenate(steps)
        grow += float(np.nanmax(steps)) if np.isfinite(steps).any() else 0.0
    c0, r0 = max(int(np.floor(lo[0] - grow)), 0), max(int(np.floor(lo[1] - grow)), 0)
    c1, r1 = min(int(np.ceil(hi[0] + grow)), width), min(int(np.ceil(hi[1] + grow)), height)
    if c0 >= c1 or r0 >= r1:
        return None
    return c0, r0, c1, r1


@pytest.mark.parametrize("case", ["all", "holes", "edge", "none", "one_row", "one_col", "uneven"])
def test_node_window_reduced_on_the_device_is_the_hosts(device, case):
    """A tile's source window and read reduction from its node pixels reduced per row on the
    device (node_window_rows_kernel, then _rows_window / _rows_decimation) are those of the
    NumPy references from the whole node array, with nodes missing in holes, at an edge, all of
    them, and for grids of one row or column."""
    import warp as wp
    from orthowarp.kernels import ortho as ok
    from orthowarp.pipeline.ortho.tiles import _rows_decimation, _rows_window

    rng = np.random.default_rng(3)
    rows, cols = {"one_row": (1, 9), "one_col": (9, 1)}.get(case, (17, 13))
    jj, ii = np.meshgrid(np.arange(cols) * 37.3, np.arange(rows) * 41.9)
    scale = np.array([1.0, 1.7])[:, None, None] if case == "uneven" else 1.0
    nodes = np.stack([np.stack([jj + 5 * k, ii - 3 * k], -1) * (scale[k] if case == "uneven" else 1.0)
                      + rng.normal(0, 2, (rows, cols, 2)) for k in range(2)])
    if case == "holes":
        nodes[rng.random(nodes.shape[:3]) < 0.3] = np.nan
    elif case == "edge":
        nodes[:, :, : cols // 2] = np.nan
    elif case == "none":
        nodes[:] = np.nan
    d = wp.array(nodes, dtype=wp.vec2d, device=device)
    part = wp.empty((2, rows, 8), dtype=wp.float64, device=device)
    wp.launch(ok.node_window_rows_kernel, dim=(2, rows), device=device, inputs=[d, part])
    part = part.numpy()
    assert _rows_decimation(part[0], rows, cols) == _reference_decimation(nodes[0])
    for radius, factor, size in ((1, 1, (5000, 4000)), (3, 2, (200, 150)), (0, 4, (10, 10))):
        assert _rows_window(part, nodes.shape[0] * rows * cols, radius, *size, factor=factor) == \
            _reference_window(nodes, radius, *size, factor=factor)


@pytest.mark.parametrize("geocentric,with_pose", [(True, True), (False, True), (True, False)])
def test_coarse_fields_on_the_device_match_float64_numpy(device, geocentric, with_pose):
    """coarse_struct's fields, computed by coarse_fields_kernel from the uploaded uv, against
    the same quantities from orthowarp.geodesy in float64 NumPy: ECEF points and normals of
    geocentric grids, camera-frame lines R^T (x(0) - C) and R^T up given a pose."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from orthowarp.geodesy import geodetic_to_ecef, geodetic_up
    from orthowarp.pipeline.ortho import coarse_struct

    rng = np.random.default_rng(5)
    if geocentric:
        uv = np.stack([rng.uniform(7.5, 8.5, (17, 23)), rng.uniform(46.0, 47.0, (17, 23))], -1)
        x0, up = geodetic_to_ecef(uv[..., 1], uv[..., 0], 0.0), geodetic_up(uv[..., 1], uv[..., 0])
        centre = geodetic_to_ecef(46.5, 8.0, 2400.0)
    else:
        uv = np.stack([rng.uniform(4.6e5, 4.61e5, (17, 23)), rng.uniform(5.2e6, 5.201e6, (17, 23))], -1)
        x0, up = np.concatenate([uv, np.zeros(uv.shape[:-1] + (1,))], -1), np.broadcast_to([0.0, 0.0, 1.0], (17, 23, 3))
        centre = np.array([460500.0, 5200500.0, 1500.0])
    rot = Rotation.from_euler("xyz", [2.0, -3.0, 40.0], degrees=True).as_matrix()
    pose = SimpleNamespace(rotation=rot, center=centre, up=np.array([0.6, 0.3, 0.74])) if with_pose else None
    g = coarse_struct(np.ascontiguousarray(uv), geocentric, device, pose=pose)
    np.testing.assert_array_equal(g.uv.numpy(), uv)
    if geocentric:
        np.testing.assert_allclose(g.xyz0.numpy(), x0, rtol=0, atol=1e-8)  # metres
        np.testing.assert_allclose(g.up.numpy(), up, rtol=0, atol=1e-15)
    else:
        assert g.xyz0 is None and g.up is None
    if with_pose:
        np.testing.assert_allclose(g.cam_a.numpy(), (x0 - centre) @ rot, rtol=0, atol=1e-8)
        np.testing.assert_allclose(g.cam_b.numpy(), up @ rot, rtol=0, atol=1e-15)
        np.testing.assert_allclose(np.array(g.cam_up), pose.up @ rot, rtol=0, atol=1e-15)
    else:
        assert g.cam_a is None and g.cam_b is None


def test_orthos_at_once_share_one_progress_bar(tmp_path):
    """progress=<bar>: each call adds its tiles to the bar's total and advances it, so two orthos
    run at once report on one bar (the CLI's batch); the bar is left open for its owner."""
    import threading

    cam, pose, dem, src = small_setup(tmp_path)

    class Bar:
        def __init__(self):
            self.total, self.n, self.closed, self.lock = 0, 0, False, threading.Lock()

        def update(self, k=1):
            with self.lock:
                self.n += k

        def refresh(self):
            pass

        def close(self):
            self.closed = True

    bar = Bar()
    runs = [threading.Thread(target=orthorectify, args=(src, FrameSensor(cam, pose), tmp_path / f"o{k}.tif"),
                             kwargs=dict(dem=dem, device="cpu", tile_size=16, progress=bar)) for k in range(2)]
    for t in runs:
        t.start()
    for t in runs:
        t.join()
    with rasterio.open(tmp_path / "o0.tif") as o:
        tiles = -(-o.height // 16) * -(-o.width // 16)
    assert tiles > 4 and bar.total == bar.n == 2 * tiles and not bar.closed
    with pytest.raises(ParamError, match="progress must be True or False or a progress bar"):
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "x.tif", dem=dem, device="cpu", progress="yes")


def test_cli_batch_shows_no_bar_off_a_terminal(tmp_path):
    """orthowarp ortho off a terminal (a log, a pipe): no progress bar in what it writes."""
    from click.testing import CliRunner

    from orthowarp.cli import main

    cam, pose, dem, src = small_setup(tmp_path)
    (tmp_path / "camera.yaml").write_text(
        f"cam:\n  type: pinhole\n  im_size: [64, 48]\n  focal_len: {SMALL['f']}\n"
        f"  sensor_size: [{64 * SMALL['pixel']}, {48 * SMALL['pixel']}]\n")
    (tmp_path / "ext.csv").write_text(f"filename,x,y,z,omega,phi,kappa\nsrc,{OPK_X},{OPK_Y},1400,0,0,0\n")
    res = CliRunner().invoke(main, ["ortho", str(src), "--int-param", str(tmp_path / "camera.yaml"), "--ext-param",
                                    str(tmp_path / "ext.csv"), "--crs", str(UTM32), "--height", "450",
                                    "--out-dir", str(tmp_path / "out"), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert "tile/s" not in res.output and "\r" not in res.output, res.output
