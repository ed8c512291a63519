"""pipeline.transforms: transformers made once per process and shared."""

import threading

import numpy as np
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
