"""Speed work of issue #14's fourth session: the joint search's penalty lists are built on every
core and give the very arrays of their readable twins; the penalty volume is the same bit for bit."""

from __future__ import annotations

import numpy as np

from recon.entropy.matching import _compact_penalty, _compact_penalty_reference


def _penalty(rng, H=13, W=17, K=11):
    pen = (rng.random((H, W, K)) * 4 - 3).astype(np.float32)
    pen[rng.random((H, W, K)) < 0.6] = np.inf  # most windows not offered
    if H < 8 or W < 3 or K < 4:
        return pen
    pen[2] = np.inf  # a row with nothing offered
    pen[4, 3] = np.inf  # a pixel with nothing offered
    pen[5, :, 0] = -0.0  # signed zeros kept as they are
    pen[6, 1, 2] = -np.inf  # not finite: not offered either
    pen[7, 2, 3] = np.nan
    return pen


def test_compact_penalty_is_identical_to_reference():
    rng = np.random.default_rng(7)
    for shape in ((13, 17, 11), (1, 1, 1), (3, 40, 77)):
        pen = _penalty(rng, *shape)
        for fast, ref in zip(_compact_penalty(pen), _compact_penalty_reference(pen)):
            assert fast.dtype == ref.dtype
            np.testing.assert_array_equal(fast.view(np.uint8), ref.view(np.uint8))


def test_compact_penalty_lists_each_pixels_finite_windows_in_order():
    pen = np.full((2, 3, 4), np.inf, np.float32)
    pen[0, 1, [3, 1]] = [-0.5, 2.0]
    pen[1, 2, 0] = 1.0
    starts, ks, pens = _compact_penalty(pen)
    np.testing.assert_array_equal(starts, [0, 0, 2, 2, 2, 2, 3])
    np.testing.assert_array_equal(ks, [1, 3, 0])
    np.testing.assert_array_equal(pens, np.array([2.0, -0.5, 1.0], np.float32))


def test_search_penalty_is_the_masked_float32_product():
    from recon.entropy.estimate import _search_penalty, make_options
    rng = np.random.default_rng(9)
    entropy = (rng.random((9, 11, 14)) * 6 - 1).astype(np.float32)
    entropy[rng.random(entropy.shape) < 0.5] = -np.inf
    nothing_flat = np.zeros((9, 11), bool)
    for lam in (1.0, 0.37, 0.0, 2.5):
        opts = make_options(lambda_entropy=lam, flat_windows="all")
        with np.errstate(invalid="ignore"):
            expected = np.where(np.isfinite(entropy), -lam * entropy, np.inf).astype(np.float32)
        got = _search_penalty(entropy, nothing_flat, opts, 7)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got.view(np.uint32), expected.view(np.uint32))
