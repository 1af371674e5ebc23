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
