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
    from recon.entropy.cost import N_BLOCKS, _view_lists
    U, V, H, W = gray.shape
    vu, vv, vdu, vdv, vblock = _view_lists((U, V), view_mask)
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


def test_min_window_cost_is_bit_identical_to_reference():
    from recon.entropy.cost import (block_abs_diff, min_window_cost, min_window_cost_reference, set_integrals,
                                    set_view_counts)
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
    integrals = set_integrals(block_abs_diff(gray, 0.37, view_mask=mask), sets)
    for allowed in (np.ones((1, 1, len(windows)), bool), rng.random((23, 29, len(windows))) < 0.3):
        out = np.empty((23, 29), np.float32)
        min_window_cost(integrals, window_set, rects, counts, allowed, out=out)
        ref = min_window_cost_reference(integrals, window_set, rects, counts, allowed)
        np.testing.assert_array_equal(out.view(np.uint32), ref.view(np.uint32))
    assert np.isinf(ref[~allowed.any(axis=2)]).all()  # no window allowed: 1e300, inf in float32


def test_cost_ambiguity_fast_is_identical_to_reference():
    rng = np.random.default_rng(5)
    costs = cost_volume(rng, D=31, H=40, W=21)
    for delta in (0.0, 0.125, 0.3, 2.0):
        np.testing.assert_array_equal(cost_ambiguity(costs, delta), cost_ambiguity_reference(costs, delta))
    assert cost_ambiguity(costs, 0.0)[2, 2] == 31  # a plateau: every candidate ties
    assert cost_ambiguity(costs, 0.0)[0, 0] == 0  # NaN least cost: nothing comes within it
