"""Atmospheric refraction: standard atmosphere, layered trace, closed forms, table and kernel."""

import math

import numpy as np
import pytest
import warp as wp

from orthowarp import refraction
from orthowarp.errors import ParamError
from orthowarp.kernels.refraction import RefractionTable, refraction_q
from orthowarp.refraction import (
    RefractionModel,
    asprs_delta,
    refractive_index,
    saastamoinen_delta,
    standard_atmosphere,
    trace_delta,
)

R0_1976 = 6356766.0  # m, the 1976 standard atmosphere's radius for geopotential height


def geometric_from_geopotential(hgp):
    return R0_1976 * hgp / (R0_1976 - hgp)


def trapezoid(y, x):
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(x)))


# -- standard atmosphere and refractive index -----------------------------------------------

def test_standard_atmosphere_sea_level():
    p, t = standard_atmosphere(0.0)
    assert float(p) == pytest.approx(101325.0, abs=1e-6)
    assert float(t) == pytest.approx(288.15, abs=1e-9)


def test_standard_atmosphere_tropopause():
    z = geometric_from_geopotential(11000.0)
    assert z == pytest.approx(11019.07, abs=0.01)
    p, t = standard_atmosphere(z)
    assert float(t) == pytest.approx(216.65, abs=1e-6)
    assert float(p) == pytest.approx(22632.0, rel=0.01)
    # and the published value is met far tighter than 1 %: 22632.06 Pa (1976 tables)
    assert float(p) == pytest.approx(22632.06, rel=2e-4)


def test_standard_atmosphere_more_levels():
    # U.S. Standard Atmosphere 1976 tables (geopotential height -> T, P)
    for hgp, t_ref, p_ref in [(5000.0, 255.65, 54019.9), (20000.0, 216.65, 5474.89), (32000.0, 228.65, 868.02)]:
        p, t = standard_atmosphere(geometric_from_geopotential(hgp))
        assert float(t) == pytest.approx(t_ref, abs=1e-6)
        assert float(p) == pytest.approx(p_ref, rel=1e-3)
    z = np.array([-1000.0, 0.0, 3000.0, 11000.0, 25000.0, 60000.0])
    p, t = standard_atmosphere(z)
    assert p.shape == t.shape == z.shape
    assert np.all(np.diff(p) < 0.0)  # pressure decreases with altitude


def test_refractive_index():
    n0 = float(refractive_index(0.0))
    assert n0 - 1.0 == pytest.approx(77.6e-6 * 1013.25 / 288.15, rel=1e-12)  # ~2.729e-4
    z = np.linspace(-500.0, 85000.0, 200)
    n = refractive_index(z)
    assert np.all(np.diff(n) < 0.0) and np.all(n > 1.0)
    np.testing.assert_array_equal(refractive_index(np.array([86000.0, 100e3, 700e3])), 1.0)


# -- layered trace ---------------------------------------------------------------------------

THETA = np.radians(np.array([0.5, 5.0, 10.0, 20.0, 30.0, 40.0, 60.0]))


@pytest.mark.parametrize("n_const", [1.0, 1.0003])
def test_trace_constant_index_is_zero(monkeypatch, n_const):
    monkeypatch.setattr(refraction, "refractive_index",
                        lambda z: np.full(np.shape(z), n_const, dtype=np.float64))
    for hs, hg in [(1000.0, 0.0), (6000.0, 500.0), (30000.0, -200.0), (694000.0, 0.0)]:
        d = trace_delta(THETA, hs, hg)
        assert d.shape == THETA.shape
        # acos round-off summed over ~100 layers: ~1e-12 rad, 1e-7 of the real effect
        np.testing.assert_allclose(d, 0.0, rtol=0, atol=1e-11)
    # while the real atmosphere does bend the ray (tens of urad at 6 km, 40 deg)
    monkeypatch.undo()
    assert trace_delta(np.radians(40.0), 6000.0, 0.0) > 2e-5


def test_trace_basic_properties():
    d = trace_delta(THETA, 3000.0, 0.0)
    assert d[0] > 0.0 and np.all(np.diff(d) > 0.0)  # positive, grows with the nadir angle
    assert float(trace_delta(0.0, 3000.0, 0.0)) == 0.0
    # higher ground -> less atmosphere -> less refraction
    assert np.all(trace_delta(THETA, 3000.0, 1000.0) < d)
    # broadcasting theta (T, 1) with ground heights (1, K)
    grid = trace_delta(THETA[:, None], 3000.0, np.array([[0.0, 1000.0]]))
    assert grid.shape == (len(THETA), 2)
    np.testing.assert_allclose(grid[:, 0], d, rtol=1e-15)
    with pytest.raises(ParamError):
        trace_delta(THETA, 1000.0, 1000.0)
    with pytest.raises(ParamError):
        trace_delta(THETA[:2], 1000.0, np.array([0.0, 2000.0]))


def test_trace_misses_the_ground_is_nan():
    # from 694 km the horizon is at ~64.8 deg nadir angle
    d = trace_delta(np.radians(np.array([30.0, 70.0])), 694000.0, 0.0)
    assert np.isfinite(d[0]) and np.isnan(d[1])


@pytest.mark.parametrize("big_h", [1000.0, 2000.0, 3000.0, 4000.0, 5000.0, 6000.0])
def test_trace_vs_flat_atmosphere(big_h):
    """Flat layers, small angles: delta ~ tan(theta) mean_{z in [h, H]} (n(z) - n(H))."""
    theta = np.radians(np.array([5.0, 10.0, 20.0, 30.0, 40.0]))
    for h in (0.0, 500.0):
        z = np.linspace(h, big_h, 4001)
        mean_excess = trapezoid(refractive_index(z) - refractive_index(big_h), z) / (big_h - h)
        flat = np.tan(theta) * mean_excess
        np.testing.assert_allclose(trace_delta(theta, big_h, h), flat, rtol=0.03)


SAAS_CASES = [(big_h, h) for big_h in (1000.0, 2000.0, 3000.0, 4000.0, 5000.0, 6000.0) for h in (0.0, 500.0)]


def test_saastamoinen_formula():
    # 13 (H - h)(1 - 0.02 (2H + h)) tan(theta) urad, H, h in km: H = 3, h = 0, theta = 45 deg
    assert saastamoinen_delta(math.radians(45.0), 3000.0, 0.0) == pytest.approx(13e-6 * 3 * 0.88, rel=1e-12)


@pytest.mark.parametrize("big_h,h", SAAS_CASES)
def test_trace_vs_saastamoinen(big_h, h):
    # measured trace / Saastamoinen - 1: -0.1 % (1 km) ... -2.2 % (6 km) for h = 0,
    # -0.4 % ... -2.3 % for h = 500 m
    theta = np.radians(np.array([10.0, 15.0, 20.0, 30.0, 40.0]))
    np.testing.assert_allclose(trace_delta(theta, big_h, h), saastamoinen_delta(theta, big_h, h), rtol=0.05)


def test_asprs_formula():
    # K = 2410 H / (H^2 - 6 H + 250) - 2410 h^2 / ((h^2 - 6 h + 250) H) urad, H, h in km
    assert asprs_delta(math.radians(45.0), 3000.0) == pytest.approx(1e-6 * 2410 * 3 / 241, rel=1e-12)
    k = 2410 * 5 / (25 - 30 + 250) - 2410 * 0.25 / ((0.25 - 3 + 250) * 5)
    assert asprs_delta(math.radians(30.0), 5000.0, 500.0) == pytest.approx(1e-6 * k * math.tan(math.radians(30)),
                                                                          rel=1e-12)


# Measured deviation of the layered trace (1976 standard atmosphere) from the ASPRS closed form,
# trace / ASPRS - 1, the same for theta = 5..40 deg to 0.1 %:
#   H (km)        1       2       3       4      4.5      5      5.5      6
#   h = 0      +26.7%  +19.1%  +12.7%   +7.6%   +5.4%   +3.5%   +1.7%   +0.2%
#   h = 500 m  -16.8%   -6.1%   -4.7%   -5.7%   -6.4%   -7.3%   -8.0%   -8.8%
# The ASPRS K formula itself differs that much from Saastamoinen's (which the trace follows to
# ~2 %), so the 5 % of the issue only holds for h = 0 and H >= 5 km; assert that, and the
# measured envelope elsewhere.
ASPRS_THETA = np.radians(np.array([5.0, 10.0, 20.0, 30.0, 40.0]))


@pytest.mark.parametrize("big_h", [5000.0, 5500.0, 6000.0])
def test_trace_vs_asprs_within_5_percent(big_h):
    np.testing.assert_allclose(trace_delta(ASPRS_THETA, big_h, 0.0), asprs_delta(ASPRS_THETA, big_h, 0.0),
                               rtol=0.05)


@pytest.mark.parametrize("big_h", [1000.0, 2000.0, 3000.0, 4000.0, 4500.0, 5000.0, 5500.0, 6000.0])
def test_trace_vs_asprs_envelope(big_h):
    dev0 = trace_delta(ASPRS_THETA, big_h, 0.0) / asprs_delta(ASPRS_THETA, big_h, 0.0) - 1.0
    assert np.all((dev0 > -0.01) & (dev0 < 0.30)), dev0
    dev500 = trace_delta(ASPRS_THETA, big_h, 500.0) / asprs_delta(ASPRS_THETA, big_h, 500.0) - 1.0
    limit = 0.20 if big_h < 2000.0 else 0.10
    assert np.all(np.abs(dev500) < limit), dev500


# -- table (host twin) -----------------------------------------------------------------------

TABLE_CASES = [(1500.0, 0.0, 800.0), (3000.0, -50.0, 1200.0), (6000.0, 200.0, 2500.0), (12000.0, -100.0, 3000.0)]


@pytest.mark.parametrize("sensor,h_min,h_max", TABLE_CASES)
def test_table_vs_trace_aircraft(sensor, h_min, h_max):
    model = RefractionModel(sensor, h_min, h_max)
    assert model.heights[0] <= h_min and model.heights[-1] >= h_max
    theta = np.radians(np.linspace(0.0, 80.0, 97))
    heights = np.linspace(model.heights[0], model.heights[-1], 23)
    t, h = np.meshgrid(theta, heights, indexing="ij")
    got, ref = model.delta(t, h), trace_delta(t, sensor, h)
    assert np.all(np.isfinite(got))
    ok = (np.abs(got - ref) <= 5e-3 * np.abs(ref)) | (np.abs(got - ref) <= 1e-8)
    assert np.all(ok), np.abs(got - ref)[~ok]
    assert np.all(got[0] == 0.0)  # theta = 0


@pytest.mark.parametrize("sensor", [694000.0, 832000.0])
def test_table_vs_trace_satellite(sensor):
    # satellite viewing angles (SPOT-5 up to ~30 deg incidence); the table degrades towards the
    # horizon (measured at 832 km: 0.05 % at 55 deg, 0.8 % at 60 deg; horizon 62.3 deg)
    model = RefractionModel(sensor, -100.0, 3000.0)
    theta = np.radians(np.linspace(0.0, 45.0, 61))
    heights = np.linspace(model.heights[0], model.heights[-1], 11)
    t, h = np.meshgrid(theta, heights, indexing="ij")
    got, ref = model.delta(t, h), trace_delta(t, sensor, h)
    ok = (np.abs(got - ref) <= 5e-3 * np.abs(ref)) | (np.abs(got - ref) <= 1e-8)
    assert np.all(ok)
    # about 1 m on the ground from ~700 km at 25-30 deg (docs/design.md)
    d = float(trace_delta(np.radians(27.0), sensor, 0.0)) * sensor / math.cos(np.radians(27.0))
    assert 0.3 < d < 3.0


def test_table_disabled_is_zero():
    model = RefractionModel(3000.0, 0.0, 1000.0, enabled=False)
    theta = np.radians(np.array([0.0, 10.0, 45.0, 80.0]))
    np.testing.assert_array_equal(model.delta(theta, 500.0), 0.0)
    np.testing.assert_array_equal(model.q, 0.0)
    assert np.any(RefractionModel(3000.0, 0.0, 1000.0).delta(theta, 500.0) > 0.0)


# -- device lookup ---------------------------------------------------------------------------

@wp.kernel
def _lookup_kernel(tab: RefractionTable, theta: wp.array(dtype=wp.float64), h: wp.array(dtype=wp.float64),
                   out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = refraction_q(tab, theta[i], h[i]) * wp.tan(theta[i])  # the turn, as the frame kernels take it


@pytest.mark.parametrize("enabled", [True, False])
def test_kernel_lookup_matches_host(device, enabled):
    model = RefractionModel(3000.0, -50.0, 1200.0, enabled=enabled)
    rng = np.random.default_rng(3)
    theta = np.concatenate([np.radians(rng.uniform(0.0, 80.0, 200)), [0.0, model.theta[-1]]])
    h = np.concatenate([rng.uniform(model.heights[0], model.heights[-1], 200), model.heights[[0, -1]]])
    out = wp.empty(len(theta), dtype=wp.float64, device=device)
    wp.launch(_lookup_kernel, dim=len(theta), device=device,
              inputs=[model.to_struct(device), wp.array(theta, dtype=wp.float64, device=device),
                      wp.array(h, dtype=wp.float64, device=device), out])
    got = out.numpy()
    np.testing.assert_allclose(got, model.delta(theta, h), rtol=1e-12, atol=1e-18)
    if enabled:
        np.testing.assert_allclose(got, trace_delta(theta, 3000.0, h), rtol=5e-3, atol=1e-8)
    else:
        np.testing.assert_array_equal(got, 0.0)


def test_the_model_table_is_made_once_and_read_only():
    """Two models of the same sensor height and heights share one table, read-only, equal to
    the one traced for them (a mosaic builds an image's geometry several times)."""
    a = RefractionModel(1450.0, 400.0, 520.0)
    b = RefractionModel(1450.0, 400.0, 520.0)
    assert a.q is b.q and not a.q.flags.writeable
    th = np.maximum(a.theta, 1e-3)[:, None]
    np.testing.assert_array_equal(a.q, trace_delta(th, 1450.0, a.heights[None, :]) / np.tan(th))
    assert RefractionModel(1450.5, 400.0, 520.0).q is not a.q
    assert not RefractionModel(1450.0, 400.0, 520.0, enabled=False).q.any()


def _trace_by_layers_and_rays(theta, sensor_height, ground_height, radius=refraction.EARTH_RADIUS):
    """The trace as one sum over a layers x rays array per chunk of layers (each ray's
    segment in every layer: whole, partial at its stop, or zero below it), as trace_delta
    first computed it."""
    theta, hg = np.broadcast_arrays(np.asarray(theta, float), np.asarray(ground_height, float))
    rc = radius + sensor_height
    p = (refraction.refractive_index(sensor_height) * rc * np.sin(theta)).ravel()
    flat_hg, phi = hg.ravel(), np.zeros(theta.size)
    bnd = refraction._boundaries(sensor_height)
    bnd = bnd[: max(int(np.count_nonzero(bnd > flat_hg.min())) + 1, 2)]
    top, bot = bnd[:-1], bnd[1:]
    n_whole = refraction.refractive_index(0.5 * (top + bot))
    stop = np.clip(np.searchsorted(-bnd, -flat_hg, side="left") - 1, 0, len(top) - 1)
    n_stop = refraction.refractive_index(0.5 * (top[stop] + flat_hg))
    chunk = max(1, (1 << 20) // p.size)
    with np.errstate(invalid="ignore"):
        for i in range(0, len(top), chunk):
            t, b0 = top[i:i + chunk, None], bot[i:i + chunk, None]
            whole = b0 >= flat_hg
            b = p / np.where(whole, n_whole[i:i + chunk, None], n_stop)
            seg = np.arccos(b / (radius + t)) - np.arccos(b / (radius + np.where(whole, b0, flat_hg)))
            phi += np.where(t > flat_hg, seg, 0.0).sum(axis=0)
        rg = radius + flat_hg
        chord = np.arctan2(rg * np.sin(phi), rc - rg * np.cos(phi))
    return theta - chord.reshape(theta.shape)


@pytest.mark.parametrize("sensor", [1000.0, 2500.0, 12000.0, 832000.0])
def test_trace_equals_the_sum_over_layers_and_rays_to_the_last_bit(sensor):
    """trace_delta's running sums per distinct ray invariant give the layers x rays sum's
    values bit for bit: a table's rays, random rays (some missing the ground: NaN), stops on
    layer boundaries, and a satellite's several chunks of layers."""
    rng = np.random.default_rng(int(sensor))
    theta, heights = refraction._table_nodes(-50.0, min(sensor - 1.0, 900.0), 89.0)
    cases = [(np.maximum(theta, 1e-3)[:, None], heights[None, :]),
             (rng.uniform(0.0, 1.57, 400), rng.uniform(-100.0, min(sensor - 1.0, 3000.0), 400)),
             (rng.uniform(0.0, 1.5, (9, 1)), np.array([[0.0, 50.0, 100.0, 100.0, 950.0]]))]
    for th, h in cases:
        np.testing.assert_array_equal(trace_delta(th, sensor, h), _trace_by_layers_and_rays(th, sensor, h))
