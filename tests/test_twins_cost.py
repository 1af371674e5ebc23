"""recon.entropy.cost: each compiled function gives its readable twin's map (bit for bit where the
search depends on it: ties, NaN, ends of the range), and each does its maths on tiny inputs."""

from __future__ import annotations

import numpy as np

from recon.entropy.cost import (WindowCost, block_abs_diff, block_abs_diff_reference, cost_ambiguity,
                                cost_ambiguity_reference, set_view_counts, window_cost_reference)
from kernel_inputs import cost_volume, seeded


def _block_abs_diff_float32(gray, disparity, view_mask=None):
    """The compiled kernel's float32 arithmetic, written out with numpy (rows first, then x with
    one fraction per view; samples left and right of the image clamped to its first/last)."""
    from recon.entropy.cost import N_BLOCKS, view_lists
    U, V, H, W = gray.shape
    vu, vv, vdu, vdv, vblock = view_lists((U, V), view_mask)
    d = np.float32(disparity)
    out = np.zeros((N_BLOCKS, H, W), np.float32)
    for y in range(H):
        centre = gray[U // 2, V // 2, y]
        for k in range(len(vu)):
            img = gray[vu[k], vv[k]]
            sy = min(max(float(y) - float(vdu[k] * d), 0.0), H - 1.0)
            y0 = max(min(int(np.floor(sy)), H - 2), 0)
            fy = np.float32(sy - y0)
            rv = (np.float32(1) - fy) * img[y0] + fy * img[min(y0 + 1, H - 1)]
            base = -vdv[k] * d
            fl = np.floor(base)
            fx = base - fl
            xs = np.arange(W) + int(fl)
            inner = (np.float32(1) - fx) * rv[np.clip(xs, 0, W - 1)] + fx * rv[np.clip(xs + 1, 0, W - 1)]
            s = np.where(xs < 0, rv[0], np.where(xs >= W - 1, rv[W - 1], inner))
            out[vblock[k], y] += np.abs(centre - s)
    return out


def test_block_abs_diff_matches_reference():
    gray = seeded().random((5, 5, 11, 13)).astype(np.float32)
    mask = np.ones((5, 5), bool)
    mask[0, 1] = False
    for d in (-1.3, 0.0, 0.37):
        ref = block_abs_diff_reference(gray, d, view_mask=mask)
        fast = block_abs_diff(gray, d, view_mask=mask)
        np.testing.assert_allclose(fast, ref, atol=1e-5)


def test_block_abs_diff_is_zero_at_the_true_disparity_of_a_shifted_ramp():
    # View (u, v) shows the centre point p at p - (du, dv) d, i.e. I_uv(q) = I_c(q + (du, dv) d);
    # bilinear interpolation reproduces a linear ramp exactly away from the border.
    U = V = 5
    y, x = np.mgrid[0:16, 0:16].astype(np.float32)
    d = 0.4
    gray = np.stack([np.stack([0.01 * (x + (v - 2) * d) + 0.02 * (y + (u - 2) * d)
                               for v in range(V)]) for u in range(U)])
    ad = block_abs_diff(gray, d).sum(0)
    assert ad[3:-3, 3:-3].max() < 1e-5


def test_block_abs_diff_is_bit_identical_to_its_float32_arithmetic():
    from recon.entropy.initial import initial_view_mask
    from recon.entropy.cost import block_abs_diff
    rng = np.random.default_rng(19)
    gray = rng.random((9, 9, 7, 23)).astype(np.float32)
    for d in (-3.7, -0.52, 0.0, 0.37, 1.0, 2.96, 13.3):  # 13.3: every outer view clamped whole
        for mask in (None, initial_view_mask((9, 9))):
            fast = block_abs_diff(gray, d, view_mask=mask)
            np.testing.assert_array_equal(fast.view(np.uint32), _block_abs_diff_float32(gray, d, mask).view(np.uint32))


def test_window_cost_fast_matches_reference():
    rng = seeded()
    blocks = rng.random((9, 12, 10)).astype(np.float32)
    shape = rng.integers(0, 11, (12, 10))
    size = rng.choice([3, 5, 7], (12, 10))
    sets = np.where(rng.random((12, 10)) < 0.5, shape, 0)
    counts = set_view_counts((9, 9))
    ref = window_cost_reference(blocks, shape, size, sets, counts)
    fast = WindowCost(shape, size, sets, counts)(blocks)
    np.testing.assert_allclose(fast, ref, rtol=1e-5)


def test_set_integrals_kernel_is_identical_to_reference_for_any_thread_count():
    import numba
    from recon.entropy.cost import set_integrals, set_integrals_reference
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


def test_ring_table_rows_are_the_reference_tables_rows():
    # the joint search's rings of summed-area table rows, a stretch of rows at a time, made in runs
    # of block rows (the ring just long enough, or the whole table)
    from recon.entropy.cost import N_BLOCKS, ring_table_rows, set_sums_plan, view_lists, block_set_integrals_reference
    from recon.entropy.initial import initial_view_mask
    rng = np.random.default_rng(3)
    for H, W in ((1, 7), (3, 5), (17, 21)):
        gray = np.round(rng.random((9, 9, H, W)) * 8).astype(np.float32) / 8  # ties in the sums
        for d, sets, mask in ((-0.7, np.arange(11), None), (0.35, np.array([0, 4, 9]), None),
                              (1.1, np.arange(11), initial_view_mask((9, 9)))):
            ref = block_set_integrals_reference(gray, d, sets=sets, view_mask=mask)
            S = len(sets)
            for R, stretch, run in ((H + 1, H, H), (4, 3, 2), (2, 1, 1)):
                ring = np.empty((R, S, W + 1), np.int64)
                ring[0] = 0
                scratch = (np.empty((run, N_BLOCKS, W), np.float32), np.empty((2, W), np.float32),
                           np.empty((S, W), np.float64), np.empty(W, np.int64))
                for y in range(0, H, stretch):
                    y1 = min(y + stretch, H)
                    ring_table_rows(gray, *view_lists((9, 9), mask), np.float32(d), *set_sums_plan(sets), y, y1,
                                    ring, *scratch)
                    for r in range(y + 1, y1 + 1):
                        np.testing.assert_array_equal(ring[r % R], ref[:, r])


def test_set_integrals_converts_large_set_values_exactly():
    # set values just below and above the vectorised conversion's limit (2^51 units of
    # 1 / FIXED_POINT), with fractions that round half up: the reference's int64 values
    from recon.entropy.cost import FIXED_LIMIT, set_integrals, set_integrals_reference
    rng = np.random.default_rng(5)
    blocks = rng.random((9, 6, 21)).astype(np.float32)
    blocks[:, 1] = np.float32(FIXED_LIMIT / 9) * (1 - rng.random((9, 21)).astype(np.float32) * 1e-6)
    blocks[:, 3] = np.float32(FIXED_LIMIT / 9) * np.float32(1.01)  # set 0 over the limit: row 3
    blocks[:, 4] = np.round(blocks[:, 4] * 2 ** 29) / 2 ** 29  # ties of the rounding
    sets = np.arange(11)
    np.testing.assert_array_equal(set_integrals(blocks, sets), set_integrals_reference(blocks, sets))


def _min_window_inputs(windows, grid=(9, 9), view_mask=None):
    from recon.entropy.cost import set_view_counts
    from recon.entropy.windows import window_rect
    sets = np.unique([w[2] for w in windows])
    window_set = np.searchsorted(sets, [w[2] for w in windows]).astype(np.int64)
    rects = np.array([window_rect(w[0], w[1]) for w in windows], np.int64)
    counts = set_view_counts(grid, view_mask)[[w[2] for w in windows]].astype(np.float64)
    return dict(sets=sets, window_set=window_set, rects=rects, counts=counts)


def test_min_window_costs_is_bit_identical_to_reference_for_any_thread_count():
    import numba
    from recon.entropy.cost import min_window_costs, min_window_costs_reference
    from recon.entropy.initial import initial_view_mask
    rng = np.random.default_rng(11)
    mask = initial_view_mask((9, 9))
    windows = [(s, 5, s) for s in range(11)] + [(0, 3, 0), (4, 7, 0), (9, 3, 9)]
    shared = _min_window_inputs(windows, view_mask=mask)
    threads = numba.get_num_threads()
    try:
        for H, W in ((23, 29), (1, 9), (2, 1), (5, 6)):
            gray = np.round(rng.random((9, 9, H, W)) * 8).astype(np.float32) / 8  # ties between windows
            K = len(windows)
            for allowed in (np.ones((K, 1, 1), bool), rng.random((K, H, W)) < 0.1, np.eye(K, 1, 3, bool)[:, :, None]):
                disparities = (0.37, -2.6, 9.0)  # 9.0: the outer views clamped whole
                ref = [min_window_costs_reference(gray, d, allowed=allowed, view_mask=mask, **shared)
                       for d in disparities]
                for n in sorted({1, threads}):
                    numba.set_num_threads(n)
                    for group in (disparities, disparities[1:], disparities[:1]):  # each with every group
                        fast = min_window_costs(gray, np.array(group), allowed=allowed, view_mask=mask, **shared)
                        for i, d in enumerate(group):
                            expected = ref[disparities.index(d)]
                            np.testing.assert_array_equal(fast[i].view(np.uint32), expected.view(np.uint32))
                nothing = ~allowed.any(axis=0) & np.ones((H, W), bool)
                assert np.isinf(fast[0][nothing]).all()  # no window allowed: 1e300, inf in float32
    finally:
        numba.set_num_threads(threads)


def test_min_window_costs_on_every_view_of_another_grid():
    from recon.entropy.cost import min_window_costs, min_window_costs_reference
    rng = np.random.default_rng(12)
    windows = [(s, 3, s) for s in range(11)] + [(s, 7, 0) for s in (0, 5, 10)]
    shared = _min_window_inputs(windows, grid=(5, 7))
    gray = rng.random((5, 7, 17, 19)).astype(np.float32)
    allowed = rng.random((len(windows), 17, 19)) < 0.5
    fast = min_window_costs(gray, np.array([0.0, 1.3]), allowed=allowed, **shared)
    for i, d in enumerate((0.0, 1.3)):
        ref = min_window_costs_reference(gray, d, allowed=allowed, **shared)
        np.testing.assert_array_equal(fast[i].view(np.uint32), ref.view(np.uint32))


def test_min_window_line_search_keeps_the_int64_sums_where_float64_would_not_hold_them():
    # Grey values of 2^20 (window sums of 2^20 * 9 views * 2^28 * 25 pixels, beyond 2^53, where
    # float64 rounds integers) and NaN views (undefined as integers): the search sums the int64
    # tables of min_window_costs_reference, as it did before the fused kernel.
    from recon.entropy.cost import EXACT_FLOAT_SUM, min_window_costs_reference, window_sum_bound
    from recon.entropy.initial import initial_view_mask
    from recon.entropy.matching import min_window_line_search
    rng = np.random.default_rng(13)
    mask = initial_view_mask((9, 9))
    windows = [(s, 5, s) for s in range(11)]
    shared = _min_window_inputs(windows, view_mask=mask)
    large = (rng.random((9, 9, 12, 14)) * 2 ** 20).astype(np.float32)
    holed = rng.random((9, 9, 12, 14)).astype(np.float32)
    holed[0, 4, 5, 6] = np.nan
    candidates = np.array([-0.5, 0.0, 0.5])
    for gray in (large, holed):
        assert window_sum_bound(gray, rects=shared["rects"], view_mask=mask) >= EXACT_FLOAT_SUM
        with np.errstate(invalid="ignore"):  # NaN as int64
            _, best = min_window_line_search(gray, candidates, windows=windows, view_mask=mask)
            ref = np.min([min_window_costs_reference(gray, d, allowed=np.ones((11, 1, 1), bool), view_mask=mask,
                                                     **shared) for d in candidates], axis=0)
        np.testing.assert_array_equal(best.view(np.uint32), ref.view(np.uint32))


def test_cost_ambiguity_fast_is_identical_to_reference():
    rng = np.random.default_rng(5)
    costs = cost_volume(rng, D=31, H=40, W=21)
    for delta in (0.0, 0.125, 0.3, 2.0):
        np.testing.assert_array_equal(cost_ambiguity(costs, delta), cost_ambiguity_reference(costs, delta))
    assert cost_ambiguity(costs, 0.0)[2, 2] == 31  # a plateau: every candidate ties
    assert cost_ambiguity(costs, 0.0)[0, 0] == 0  # NaN least cost: nothing comes within it
