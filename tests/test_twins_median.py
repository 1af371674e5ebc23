"""recon.entropy.median: the compiled median filter equals scipy's."""

from __future__ import annotations

import numpy as np




def test_median_filter_nearest_is_identical_to_scipy():
    from recon.entropy.median import median_filter_nearest, median_filter_nearest_reference
    rng = np.random.default_rng(9)
    image = np.round(rng.normal(size=(23, 31)) * 4) / 4  # many ties
    sparse = np.zeros((13, 13), bool)
    sparse[::3, ::3] = True
    for dtype in (np.float32, np.float64):
        im = image.astype(dtype)
        for fp in (np.ones((5, 5), bool), np.ones((1, 3), bool), np.ones((3, 1), bool),
                   np.ones((4, 4), bool), sparse, np.ones((40, 3), bool)):
            out = median_filter_nearest(im, footprint=fp)
            ref = median_filter_nearest_reference(im, footprint=fp)
            assert out.dtype == ref.dtype
            np.testing.assert_array_equal(out.view(np.uint8), ref.view(np.uint8))
    np.testing.assert_array_equal(median_filter_nearest(image, size=3),
                                  median_filter_nearest_reference(image, footprint=np.ones((3, 3), bool)))
    step = np.zeros((9, 9))
    step[:, 5:] = 1.0
    assert (median_filter_nearest(step, size=3) == step).all()  # a straight edge survives


def test_median_filter_nearest_across_column_blocks():
    # wider than MEDIAN_COLUMNS: the row goes through the network in blocks, borders in the first
    # and last
    from recon.entropy.median import MEDIAN_COLUMNS, median_filter_nearest, median_filter_nearest_reference
    rng = np.random.default_rng(10)
    image = (np.round(rng.normal(size=(9, 2 * MEDIAN_COLUMNS + 37)) * 8) / 8).astype(np.float32)
    for fp in (np.ones((5, 5), bool), np.ones((1, 3), bool), np.ones((3, 9), bool)):
        out = median_filter_nearest(image, footprint=fp)
        ref = median_filter_nearest_reference(image, footprint=fp)
        np.testing.assert_array_equal(out.view(np.uint32), ref.view(np.uint32))


def test_selection_network_selects_every_rank_of_every_zero_one_input():
    # the 0-1 principle: a compare-exchange network that puts the value of rank k at position k for
    # every input of zeros and ones does so for every input
    from recon.entropy.median import selection_network, sorting_network
    for n in range(1, 15):
        codes = np.arange(2 ** n, dtype=np.int64)
        bits = ((codes[None, :] >> np.arange(n)[:, None]) & 1).astype(np.int8)
        ones = bits.sum(axis=0)
        for rank in range(n):
            a = bits.copy()
            for i, j in selection_network(n, rank):
                a[i], a[j] = np.minimum(a[i], a[j]), np.maximum(a[i], a[j])
            np.testing.assert_array_equal(a[rank], (ones >= n - rank).astype(np.int8))
        assert all(i < j for i, j in sorting_network(n))
    assert len(selection_network(25, 12)) < len(sorting_network(25))  # cut to what the median needs
