"""pipeline.transforms: transformers made once per process and shared."""

import threading

import numpy as np
import pytest
from pyproj import CRS, Transformer

from orthowarp.pipeline import transforms
from orthowarp.pipeline.transforms import transformer


def test_one_transformer_per_pair_of_crss_transforming_as_a_new_one():
    utm, lonlat = CRS.from_epsg(32632), CRS.from_epsg(4326)
    a = transformer(utm, lonlat)
    assert transformer(CRS.from_wkt(utm.to_wkt()), CRS.from_epsg(4326)) is a  # equal CRSs, other objects
    assert transformer(lonlat, utm) is not a
    x, y = np.array([500000.0, 612345.6]), np.array([5000000.0, 5123456.7])
    want = Transformer.from_crs(utm, lonlat, always_xy=True).transform(x, y)
    np.testing.assert_array_equal(a.transform(x, y), want)


def test_shared_between_threads():
    """Threads using one transformer at once get what each would alone."""
    tr = transformer(CRS.from_epsg(32632), CRS.from_epsg(4326))
    x = np.linspace(400000.0, 600000.0, 2001)
    y = np.linspace(4.9e6, 5.1e6, 2001)
    want = tr.transform(x, y)
    got = [None] * 8

    def one(i):
        got[i] = tr.transform(x, y)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for g in got:
        np.testing.assert_array_equal(g, want)


def test_the_least_recently_used_goes_first(monkeypatch):
    monkeypatch.setattr(transforms, "_KEPT", type(transforms._KEPT)())
    monkeypatch.setattr(transforms, "_MOST", 2)
    lonlat = CRS.from_epsg(4326)
    first = transformer(CRS.from_epsg(32632), lonlat)
    transformer(CRS.from_epsg(32633), lonlat)
    assert transformer(CRS.from_epsg(32632), lonlat) is first  # (now the most recent)
    transformer(CRS.from_epsg(32634), lonlat)  # drops 32633's
    assert len(transforms._KEPT) == 2
    assert transformer(CRS.from_epsg(32632), lonlat) is first


@pytest.mark.parametrize("code", [32632, 32615, 2056, 3857, 4326])
def test_a_transformer_between_one_crs_is_the_identity_to_the_bit(code):
    """is_identity says a transformer between one CRS and itself is PROJ's no-op, which gives
    back its input to the bit (so the forward maps skip it); not one between two CRSs."""
    from orthowarp.pipeline.transforms import is_identity

    crs = CRS.from_epsg(code)
    t = transformer(crs, crs)
    rng = np.random.default_rng(code)
    x, y = (rng.uniform(5, 10, 1000), rng.uniform(40, 50, 1000)) if code == 4326 else \
        (rng.uniform(4e5, 6e5, 1000), rng.uniform(4e6, 6e6, 1000))
    u, v = t.transform(x, y)
    assert is_identity(t) and np.array_equal(u, x) and np.array_equal(v, y)
    assert not is_identity(transformer(crs, CRS.from_epsg(32633 if code != 32633 else 32632)))
