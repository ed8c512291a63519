"""pipeline.mosaic.balance: overlap statistics made as the reduced pass's images come in."""

import numpy as np
import pytest

from orthowarp.pipeline.mosaic.balance import OverlapStats, overlap_boxes, radiometric_balance


def _block(n_rows=6, n_cols=8, seed=3):
    """Reduced windows of overlapping images, each a common texture through its own gain and
    offset, one of them with nothing on the grid and one partly invalid."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:200, 0:240]
    base = np.stack([80 + 40 * np.sin(xx / 7.0) * np.cos(yy / 5.0), 120 + 30 * np.cos(xx / 4.0 - yy / 9.0)],
                    -1).astype(np.float32)
    coarse = []
    for r in range(n_rows):
        for c in range(n_cols):
            r0, c0 = r * 25 + int(rng.integers(0, 5)), c * 25 + int(rng.integers(0, 5))
            g, o = rng.uniform(0.8, 1.2, 2), rng.uniform(-10, 10, 2)
            v = ((base[r0:r0 + 40, c0:c0 + 40] - o) / g).astype(np.float32)
            ok = np.ones(v.shape[:2], bool)
            coarse.append((r0, c0, v, ok))
    coarse[5] = None
    coarse[9][3][:20] = False
    coarse[9][2][:20] = 0.0
    return coarse


@pytest.mark.parametrize("sparse_from", [10**6, 10])
@pytest.mark.parametrize("seed", [0, 1])
def test_statistics_made_as_the_images_come_give_the_same_balance(sparse_from, seed):
    """The images added in any order (None for the one without a window): every overlapping
    pair's statistics made, and the balance from them equal, bit for bit, to the balance that
    makes its own (dense and sparse paths)."""
    coarse = _block()
    stats = OverlapStats(len(coarse))
    try:
        for k in np.random.default_rng(seed).permutation(len(coarse)):
            stats.add(int(k), coarse[k])
        made = stats.result()
    finally:
        stats.close()
    boxes = list(overlap_boxes(coarse, sparse_from=sparse_from))
    assert {b[:2] for b in boxes} <= set(made)
    assert all(made[b[:2]][0] == b for b in boxes)
    want = radiometric_balance(coarse, 2, None, sparse_from=sparse_from)
    got = radiometric_balance(coarse, 2, None, sparse_from=sparse_from, pair_stats=made)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_statistics_missing_or_stale_are_made_again():
    """A pair missing from ``pair_stats``, or given for another box, is made by the balance
    itself: the same result."""
    coarse = _block()
    want = radiometric_balance(coarse, 2, 0)
    boxes = list(overlap_boxes(coarse))
    stale = {b[:2]: ((b[0], b[1], 0, 1, 0, 1), None) for b in boxes[::2]}
    got = radiometric_balance(coarse, 2, 0, pair_stats=stale)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
