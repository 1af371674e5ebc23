"""Compiled twins of the nine-view search's last steps (arg-min with its parabola, cost ambiguity)
give the very maps of their numpy references, bit for bit: ties, NaN, ends of the range."""

from __future__ import annotations

import numpy as np

from recon.entropy.matching import (cost_ambiguity, cost_ambiguity_reference, subpixel_argmin,
                                    subpixel_argmin_reference)


def _volume(rng, D=23, H=17, W=19):
    # Quantised costs make exact ties (the first minimum must win) and flat stretches common.
    costs = np.round(rng.random((D, H, W)) * 8).astype(np.float32) / 8
    costs[:, 0, 0] = np.nan  # all NaN
    costs[3, 1, 1] = np.nan  # NaN after a minimum: np.argmin takes the NaN
    costs[:, 2, 2] = 1.0  # all tied: first candidate, no parabola
    costs[:, 3, 3] = np.linspace(1, 0, D)  # minimum at the last candidate
    costs[:, 4, 4] = np.inf
    return costs


def test_subpixel_argmin_fast_is_bit_identical_to_reference():
    rng = np.random.default_rng(3)
    for D in (1, 2, 23):
        costs = _volume(rng, D=D) if D > 4 else rng.random((D, 5, 6)).astype(np.float32)
        for cands in (-0.7 + 0.05 * np.arange(D), (0.2 + 0.1 * np.arange(D)).astype(np.float32)):
            d_ref, c_ref = subpixel_argmin_reference(costs, cands)
            d_fast, c_fast = subpixel_argmin(costs, cands)
            assert d_fast.dtype == np.float32 and c_fast.dtype == np.float32
            np.testing.assert_array_equal(d_fast.view(np.uint32), d_ref.view(np.uint32))
            np.testing.assert_array_equal(c_fast.view(np.uint32), c_ref.view(np.uint32))


def test_subpixel_argmin_takes_the_first_of_tied_minima():
    costs = np.ones((5, 1, 1), np.float32)
    costs[1] = costs[3] = 0.0
    d, c = subpixel_argmin(costs, np.arange(5.0))
    assert c[0, 0] == 0.0 and d[0, 0] == 1.0 - 0.0  # parabola 1, 0, 1 has its vertex at 1


def test_cost_ambiguity_fast_is_identical_to_reference():
    rng = np.random.default_rng(5)
    costs = _volume(rng, D=31, H=40, W=21)
    for delta in (0.0, 0.125, 0.3, 2.0):
        np.testing.assert_array_equal(cost_ambiguity(costs, delta), cost_ambiguity_reference(costs, delta))
    assert cost_ambiguity(costs, 0.0)[2, 2] == 31  # a plateau: every candidate ties
    assert cost_ambiguity(costs, 0.0)[0, 0] == 0  # NaN least cost: nothing comes within it


def test_min_window_cost_kernel_is_bit_identical_to_reference():
    from recon.entropy.matching import (_min_window_cost_kernel, block_abs_diff_fast,
                                        min_window_cost_reference, set_integrals, set_view_counts)
    from recon.entropy.initial import initial_view_mask
    from recon.entropy.windows import window_rect
    rng = np.random.default_rng(11)
    gray = rng.random((9, 9, 23, 29)).astype(np.float32)
    mask = initial_view_mask((9, 9))
    windows = [(s, 5, s) for s in range(11)] + [(0, 3, 0), (4, 7, 0)]
    sets = np.unique([w[2] for w in windows])
    window_set = np.searchsorted(sets, [w[2] for w in windows]).astype(np.int64)
    rects = np.array([window_rect(w[0], w[1]) for w in windows], np.int64)
    counts = set_view_counts((9, 9), mask)[[w[2] for w in windows]].astype(np.float64)
    integrals = set_integrals(block_abs_diff_fast(gray, 0.37, view_mask=mask), sets)
    for allowed in (np.ones((1, 1, len(windows)), bool), rng.random((23, 29, len(windows))) < 0.3):
        out = np.empty((23, 29), np.float32)
        _min_window_cost_kernel(integrals, window_set, rects, counts, allowed, out)
        ref = min_window_cost_reference(integrals, window_set, rects, counts, allowed)
        np.testing.assert_array_equal(out.view(np.uint32), ref.view(np.uint32))
    assert np.isinf(ref[~allowed.any(axis=2)]).all()  # no window allowed: 1e300, inf in float32


def test_set_integrals_kernel_is_identical_to_reference_for_any_thread_count():
    import numba
    from recon.entropy.matching import set_integrals, set_integrals_reference
    rng = np.random.default_rng(2)
    threads = numba.get_num_threads()
    try:
        for H in (1, 2, 3, 17):
            blocks = rng.random((9, H, 13)).astype(np.float32)
            for sets in (np.arange(11), np.array([0, 4, 9])):
                ref = set_integrals_reference(blocks, sets)
                for n in sorted({1, threads}):
                    numba.set_num_threads(n)
                    np.testing.assert_array_equal(set_integrals(blocks, sets), ref)
    finally:
        numba.set_num_threads(threads)


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
