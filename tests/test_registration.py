"""Phase correlation and tiled misregistration (orthowarp.pipeline.registration).

Known sub-pixel shifts of a band-limited random texture, applied exactly in the Fourier
domain, must be recovered to < 0.01 px; the sign convention is pinned by integer rolls and
crops; tiles with nodata are excluded.
"""

import numpy as np
import pytest

from orthowarp.pipeline.registration import misregistration, phase_correlation


def texture(n, seed=0, fc=0.08):
    """Band-limited random texture, (n, n) spectrum: white noise times a Gaussian of sigma fc
    (cycles/px), nothing beyond 0.25 cycles/px (periods < 4 px)."""
    rng = np.random.default_rng(seed)
    fy, fx = np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :]
    spec = np.fft.fft2(rng.normal(size=(n, n))) * np.exp(-(fx**2 + fy**2) / (2 * fc**2))
    spec[np.hypot(fx, fy) > 0.25] = 0.0
    return spec


def image(spec, dy=0.0, dx=0.0):
    """The texture moved by (+dy, +dx) px (exact band-limited shift): image(x) = tex(x - s)."""
    n = spec.shape[0]
    fy, fx = np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :]
    return np.fft.ifft2(spec * np.exp(-2j * np.pi * (fy * dy + fx * dx))).real


SHIFTS = [(0.0, 0.0), (0.25, -0.4), (-0.137, 0.871), (0.5, 0.5), (-0.93, -0.061), (1.37, -2.62), (0.013, 0.004)]


@pytest.mark.parametrize("window", [True, "tukey", False])
@pytest.mark.parametrize("shift", SHIFTS)
def test_recovers_known_subpixel_shifts_circular(shift, window):
    """Circular (exact Fourier) shifts of a whole 128 x 128 texture."""
    spec = texture(128, seed=3)
    dy, dx, peak = phase_correlation(image(spec), image(spec, *shift), window=window)
    assert abs(dy - shift[0]) < 0.01 and abs(dx - shift[1]) < 0.01, (dy, dx)
    assert peak > 0.95


@pytest.mark.parametrize("size", [64, 96])
@pytest.mark.parametrize("seed", range(6))
def test_recovers_known_subpixel_shifts_in_windows(size, seed):
    """Windows cut from a larger texture and its shifted copy (content enters and leaves at
    the edges, as in real tiles): < 0.01 px with the default Hann window."""
    rng = np.random.default_rng(seed)
    shift = rng.uniform(-1.5, 1.5, 2)
    spec = texture(4 * size, seed=seed)
    a, b = image(spec), image(spec, *shift)
    r0, c0 = rng.integers(size, 2 * size, 2)
    dy, dx, peak = phase_correlation(a[r0:r0 + size, c0:c0 + size], b[r0:r0 + size, c0:c0 + size])
    assert abs(dy - shift[0]) < 0.01 and abs(dx - shift[1]) < 0.01, (shift, dy, dx)
    assert peak > 0.9


def test_common_window_bias_is_removed():
    """One common window biases the estimate toward 0 by a few % of the shift (64 px tiles);
    the iterations with the moving window remove it."""
    spec = texture(256, seed=11)
    s = (0.8, -0.9)
    a, b = image(spec)[64:128, 64:128], image(spec, *s)[64:128, 64:128]
    dy0, dx0, _ = phase_correlation(a, b, iterations=0)
    dy, dx, _ = phase_correlation(a, b)
    assert max(abs(dy0 - s[0]), abs(dx0 - s[1])) > 0.01  # the bias this guards against
    assert max(abs(dy - s[0]), abs(dx - s[1])) < 0.005


def test_sign_convention():
    """moving = reference with its content moved right by 3 and down by 2 -> (dy, dx) = (2, 3)."""
    ref = image(texture(128, seed=5))
    dy, dx, peak = phase_correlation(ref, np.roll(ref, (2, 3), axis=(0, 1)))
    assert (dy, dx) == pytest.approx((2.0, 3.0), abs=1e-6) and peak > 0.99
    dy, dx, _ = phase_correlation(ref, np.roll(ref, (-1, -4), axis=(0, 1)), upsample=1)
    assert (dy, dx) == (-1.0, -4.0)
    # the same with crops: moving's pixel (r, c) shows reference's (r - 1, c + 2)
    big = image(texture(256, seed=6))
    a = big[100:164, 100:164]
    b = big[99:163, 102:166]
    dy, dx, _ = phase_correlation(a, b)
    assert (dy, dx) == pytest.approx((1.0, -2.0), abs=0.01)
    # and sub-pixel: content moved +0.3 px along x -> dx = +0.3
    spec = texture(128, seed=7)
    dy, dx, _ = phase_correlation(image(spec), image(spec, 0.0, 0.3))
    assert dx == pytest.approx(0.3, abs=0.005) and dy == pytest.approx(0.0, abs=0.005)


def test_identical_and_unrelated_images():
    a = image(texture(64, seed=1))
    assert phase_correlation(a, a) == pytest.approx((0.0, 0.0, 1.0), abs=1e-9)
    peaks = [phase_correlation(image(texture(64, seed=s)), image(texture(64, seed=100 + s)))[2] for s in range(20)]
    assert max(peaks) < 0.5  # misregistration's default min_peak rejects them


def test_noise_robustness():
    """Independent noise of 20 % of the texture's standard deviation in each image: < 0.1 px."""
    spec = texture(256, seed=8)
    s = (0.37, -0.55)
    a, b = image(spec)[64:128, 64:128], image(spec, *s)[64:128, 64:128]
    rng = np.random.default_rng(0)
    sd = 0.2 * a.std()
    dy, dx, peak = phase_correlation(a + rng.normal(0, sd, a.shape), b + rng.normal(0, sd, b.shape))
    assert np.hypot(dy - s[0], dx - s[1]) < 0.1 and peak > 0.9


def test_bad_input():
    a = np.zeros((16, 16))
    with pytest.raises(ValueError):
        phase_correlation(a, np.zeros((16, 17)))
    with pytest.raises(ValueError):
        phase_correlation(np.zeros(16), np.zeros(16))
    b = a.copy()
    b[3, 3] = np.nan
    with pytest.raises(ValueError):
        phase_correlation(a, b)
    with pytest.raises(ValueError):
        phase_correlation(a, a, window="kaiser")
    dy, dx, peak = phase_correlation(a, a)  # constant images: nothing to correlate
    assert np.isnan(dy) and np.isnan(dx) and peak == 0.0
    with pytest.raises(ValueError):
        misregistration(a, a, valid=np.ones((4, 4), bool))


# ------------------------------------------------------------------------------------------
# misregistration
# ------------------------------------------------------------------------------------------
def test_misregistration_uniform_shift():
    spec = texture(512, seed=9)
    s = (0.31, -0.47)
    a, b = image(spec)[:256, :320], image(spec, *s)[:256, :320]
    m = misregistration(a, b, tile=64)
    assert m["n_tiles"] == 20 and m["rejected"] == 0
    assert m["shifts"].shape == (20, 2) and m["centers"].shape == (20, 2) and m["peaks"].shape == (20,)
    np.testing.assert_allclose(m["shifts"], np.tile(s, (20, 1)), atol=0.01)
    assert m["mean"] == pytest.approx(s, abs=0.005)
    assert m["rms"] == pytest.approx(np.hypot(*s), abs=0.005)
    assert m["max"] == pytest.approx(np.hypot(*s), abs=0.01)
    assert m["peak"] > 0.95
    assert (m["centers"][0] == (32.0, 32.0)).all() and (m["centers"][-1] == (224.0, 288.0)).all()


def test_misregistration_follows_a_shift_field():
    """A shift that grows across the image: each tile reports the shift at its centre."""
    from scipy.ndimage import map_coordinates

    spec = texture(512, seed=10, fc=0.06)
    tex = image(spec)
    rows, cols = 192, 256
    ii, jj = np.mgrid[0:rows, 0:cols].astype(float)
    sx = 0.2 + 0.6 * jj / cols  # content moved right by sx(col)
    sy = -0.3 + 0.4 * ii / rows
    a = tex[100:100 + rows, 100:100 + cols]
    b = map_coordinates(tex, [100 + ii - sy, 100 + jj - sx], order=5, mode="wrap")
    m = misregistration(a, b, tile=64)
    assert m["n_tiles"] == 12
    r, c = m["centers"].T
    expected = np.stack([-0.3 + 0.4 * (r - 0.5) / rows, 0.2 + 0.6 * (c - 0.5) / cols], axis=1)
    np.testing.assert_allclose(m["shifts"], expected, atol=0.02)


def test_misregistration_excludes_nodata_tiles():
    spec = texture(512, seed=12)
    s = (-0.2, 0.35)
    a, b = image(spec)[:256, :256].copy(), image(spec, *s)[:256, :256].copy()
    valid = np.ones(a.shape, bool)
    b[0:64, 0:64] = np.nan  # a whole tile of NaN in moving
    valid[64:128, 128:192] = False  # a tile masked out, filled with garbage
    b[64:128, 128:192] = 1e6 * np.random.default_rng(0).normal(size=(64, 64))
    a[200:210, 200:256] = np.nan  # 10 x 56 px of NaN in the reference: < 95 % valid
    valid[130:132, 0:64] = False  # 2 x 64 px: 96.9 % valid, still used (filled)
    b[130:132, 0:64] = -5e5
    m = misregistration(a, b, valid=valid, tile=64)
    centers = {tuple(c) for c in m["centers"]}
    assert m["n_tiles"] == 13
    assert (32.0, 32.0) not in centers and (96.0, 160.0) not in centers and (224.0, 224.0) not in centers
    assert (160.0, 32.0) in centers
    np.testing.assert_allclose(m["shifts"], np.tile(s, (13, 1)), atol=0.02)
    # nothing valid: no tiles, NaN statistics
    m = misregistration(a, b, valid=np.zeros(a.shape, bool))
    assert m["n_tiles"] == 0 and np.isnan(m["rms"]) and np.isnan(m["peak"]) and m["shifts"].shape == (0, 2)


def test_misregistration_rejects_unrelated_tiles():
    spec = texture(512, seed=13)
    a, b = image(spec)[:128, :128].copy(), image(spec, 0.1, 0.1)[:128, :128].copy()
    b[:64, :64] = image(texture(512, seed=99))[:64, :64]  # different content in one tile
    m = misregistration(a, b, tile=64)
    assert m["n_tiles"] == 3 and m["rejected"] == 1
    np.testing.assert_allclose(m["shifts"], 0.1, atol=0.01)
