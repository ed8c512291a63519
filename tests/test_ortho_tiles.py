"""The tile functions' source reads (orthowarp.pipeline.ortho.tiles): reduced windows averaged
on the device (``device_reduce``) against float64 NumPy block means, and the same pixels
whether the source is whole in device memory or read window by window, or mapped from
another process's device memory."""

import warnings

import numpy as np
import pytest
import rasterio
import warp as wp

from orthowarp.kernels import ortho as ortho_kernels
from orthowarp.pipeline.geometry import SensorGeometry
from orthowarp.pipeline.ortho import output_grid
from orthowarp.errors import RasterIOError
from orthowarp.pipeline.ortho import tiles as tiles_module
from orthowarp.pipeline.ortho.tiles import ImageTiles, SharedSources, SharedWholeSource, WholeSource
from orthowarp.sensor import FrameSensor
from test_ortho import scene, write_image


def block_means(data, valid, c0, r0, shape, f):
    """Reference: float64 means of the valid pixels of f x f blocks from (r0, c0), cut by the
    image's edge; valid where the block's centre pixel (r0 + i f + f // 2, clipped) is."""
    bands, rows, cols = data.shape
    out = np.zeros((bands, *shape))
    ok = np.zeros(shape, bool)
    for i in range(shape[0]):
        for j in range(shape[1]):
            rs, cs = slice(r0 + i * f, min(r0 + (i + 1) * f, rows)), slice(c0 + j * f, min(c0 + (j + 1) * f, cols))
            m = valid[rs, cs] > 0
            centre = valid[min(r0 + i * f + f // 2, rows - 1), min(c0 + j * f + f // 2, cols - 1)] > 0
            if centre and m.any():
                out[:, i, j] = data[:, rs, cs][:, m].astype(np.float64).mean(axis=1)
                ok[i, j] = True
    return out, ok


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "float32"])
@pytest.mark.parametrize("factor,c0,r0", [(1, 3, 5), (3, 0, 0), (4, 10, 7), (7, 22, 30)])
def test_reduce_window_kernel_is_the_block_mean(device, dtype, factor, c0, r0):
    rng = np.random.default_rng(factor + c0)
    rows, cols = 45, 53
    data = (rng.random((3, rows, cols)) * (250 if dtype == "uint8" else 60000 if dtype == "uint16" else 1.0))
    data = data.astype(dtype)
    valid = (rng.random((rows, cols)) > 0.2).astype(np.uint8)
    valid[:8, :] = 0  # a stretch without data
    shape = (-(-(rows - r0) // factor), -(-(cols - c0) // factor))  # up to the image's edge
    for masked in (1, 0):
        out = wp.empty((3, *shape), dtype=wp.float32, device=device)
        ok = wp.empty(shape, dtype=wp.uint8, device=device)
        wp.launch(ortho_kernels.reduce_window_kernel, dim=shape, device=device,
                  inputs=[wp.array(data, device=device), wp.array(valid, device=device), masked, c0, r0, factor],
                  outputs=[out, ok])
        ref, ref_ok = block_means(data, valid if masked else np.ones_like(valid), c0, r0, shape, factor)
        got, got_ok = out.numpy(), ok.numpy().astype(bool)
        np.testing.assert_array_equal(got_ok, ref_ok)
        np.testing.assert_allclose(got[:, got_ok], ref[:, ref_ok], rtol=1e-6, atol=0)
        assert (got[:, ~got_ok] == 0).all()


@pytest.mark.parametrize("method", ["backward", "forward"])
def test_device_reduced_windows_are_the_same_whole_or_not(tmp_path, monkeypatch, device, method):
    """An output four times coarser than the source: its tiles read reduced windows, averaged on
    the device from the whole source in device memory or from full-resolution window reads,
    give the same pixels; and those pixels are close to GDAL's reduced reads."""
    sc = scene("ins")
    src = write_image(tmp_path / "src.tif", sc.image(False) * 200.0 + 1.0, "uint8")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(src, "r+") as ds:  # a masked source
            ds.nodata = 0
            values = ds.read(1)
            values[:40, :60] = 0
            ds.write(values, 1)
    geom = SensorGeometry(FrameSensor(sc.camera, sc.pose), sc.dem, device=device, refraction=False)
    crs, transform, (rows, cols), res = output_grid(geom)
    coarse = transform @ transform.scale(4.0)
    rows, cols = -(-rows // 4), -(-cols // 4)
    kw = dict(count=1, out_dtype="uint8", resampling="bilinear", method=method, masked=True, src_dtype="uint8")

    def render(**reads):
        it = ImageTiles(src, geom, crs, coarse, **kw, **reads)
        try:
            tiles = [(r0, c0) for r0 in range(0, rows, 32) for c0 in range(0, cols, 32)]
            out = np.zeros((rows, cols), np.uint8)
            ok = np.zeros((rows, cols), bool)
            for r0, c0 in tiles:
                th, tw = min(32, rows - r0), min(32, cols - c0)
                v, m = it.render(r0, c0, th, tw, fill=True)
                out[r0:r0 + th, c0:c0 + tw] = v.numpy()[..., 0]
                ok[r0:r0 + th, c0:c0 + tw] = m.numpy() > 0
            return out, ok
        finally:
            it.close()

    calls = []
    reduced = ImageTiles._reduced_on_device
    monkeypatch.setattr(ImageTiles, "_reduced_on_device", lambda self, *a: calls.append(a[-1]) or reduced(self, *a))
    whole = WholeSource(src, wp.get_device(device), masked=True, dtype="uint8")
    a, va = render(source_reads="whole", whole=whole, device_reduce=True)
    assert whole.loaded
    b, vb = render(source_reads="tiles", device_reduce=True)
    np.testing.assert_array_equal(va, vb)
    np.testing.assert_array_equal(a, b)
    assert calls and min(calls) >= 3  # (factors: reduced windows were read)
    n = len(calls)
    g, vg = render(source_reads="tiles")  # GDAL's reduced reads: the same picture
    assert len(calls) == n
    both = va & vg
    assert both.mean() > 0.5 and (va != vg).mean() < 0.02
    diff = np.abs(a[both].astype(int) - g[both].astype(int))
    print(f"\n{method}: device vs GDAL reduced reads: mask differs on {(va != vg).mean():.4f}, |diff| median "
          f"{np.median(diff)}, p99 {np.percentile(diff, 99)}, max {diff.max()}")
    assert np.median(diff) <= 1 and np.percentile(diff, 99) <= 12, (np.median(diff), np.percentile(diff, 99))


def test_a_source_that_cannot_be_opened_is_named(tmp_path):
    """A whole-source read of a file that is no raster: RasterIOError naming the file (GDAL's
    reason), not rasterio's own error."""
    from orthowarp.errors import RasterIOError

    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00 not a TIFF")
    with pytest.raises(RasterIOError, match=r"Could not open image '.*bad\.tif'"):
        WholeSource(str(bad), wp.get_device("cpu"), masked=False, dtype="float32").get()


def test_a_shared_source_is_mapped_once_per_process_else_read_here(tmp_path, monkeypatch):
    """A SharedWholeSource: before any export came (an image built ahead of them), or for an
    image not exported, the source is read here, the same pixels as a WholeSource's; once
    exported it is mapped, once per process (CUDA maps a handle once), for every tile function
    of the image; one that is not the source as read here (dtype, mask) is refused."""
    sc = scene("ins")
    src = write_image(tmp_path / "src.tif", sc.image(False) * 200.0 + 1.0, "uint8")
    dev = wp.get_device("cpu")
    own, no_mask = WholeSource(src, dev, masked=False, dtype="uint8").get()
    shared = SharedSources()
    early = SharedWholeSource(src, dev, masked=False, dtype="uint8", shared=shared, k=3)
    data, valid = early.get()
    assert data is not own and valid is None and no_mask is None
    np.testing.assert_array_equal(data.numpy(), own.numpy())

    exported = {"values 3": own}
    mapped = []
    monkeypatch.setattr(tiles_module, "import_array", lambda e, device: mapped.append(e) or exported[e])
    shared.set({3: ("values 3", None)})
    other = SharedWholeSource(src, dev, masked=False, dtype="uint8", shared=shared, k=5)  # (not exported)
    assert other.get()[0] is not own and mapped == []
    late = SharedWholeSource(src, dev, masked=False, dtype="uint8", shared=shared, k=3)
    assert late.get() == (own, None) and early.get() == (own, None)
    assert mapped == ["values 3"]  # (early's own read is dropped for the mapping)
    with pytest.raises(RasterIOError, match=r"'.*src\.tif' shared by another process is not the source"):
        SharedWholeSource(src, dev, masked=True, dtype="uint8", shared=shared, k=3).get()
    with pytest.raises(RasterIOError, match="uint16"):
        SharedWholeSource(src, dev, masked=False, dtype="uint16", shared=shared, k=3).get()
    shared.close()  # unmapped: a later use maps it again
    late.get()
    assert mapped == ["values 3"] * 2
