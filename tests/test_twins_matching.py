"""recon.entropy.matching: the line searches' compiled kernels give their readable twins' maps
(and the retired kernels of recon.entropy.legacy_matching, which the current ones must equal)."""

from __future__ import annotations

import numpy as np

from recon.entropy.cost import block_abs_diff, set_view_counts
from recon.entropy.legacy_matching import _compact_penalty, _compact_penalty_reference
from recon.entropy.matching import subpixel_argmin, subpixel_argmin_reference
from kernel_inputs import cost_volume, joint_inputs, penalty_volume, seeded


def test_subpixel_argmin_finds_the_vertex_of_a_parabola():
    cands = np.arange(-1, 1.0001, 0.1)
    true = np.array([[0.234, -0.51]])
    costs = (cands[:, None, None] - true[None]) ** 2
    d, _ = subpixel_argmin(costs.astype(np.float32), cands)
    np.testing.assert_allclose(d, true, atol=1e-4)


def test_subpixel_argmin_fast_is_bit_identical_to_reference():
    rng = np.random.default_rng(3)
    for D in (1, 2, 23):
        costs = cost_volume(rng, D=D) if D > 4 else rng.random((D, 5, 6)).astype(np.float32)
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


def test_joint_line_search_fast_matches_reference():
    from recon.entropy.matching import joint_line_search, joint_line_search_reference

    rng = seeded()
    gray = rng.random((3, 3, 9, 10)).astype(np.float32)
    windows = [(s, z) for s in range(11) for z in (3, 5)]
    penalty = rng.normal(0, 1, (9, 10, len(windows))).astype(np.float32)
    penalty[rng.random(penalty.shape) < 0.4] = np.inf
    penalty[..., 0] = 0.0  # every pixel keeps at least the 3x3 square
    occluded = rng.random((9, 10)) < 0.5
    penalty = np.ascontiguousarray(penalty.transpose(0, 2, 1))  # (H, K, W)
    cands = np.array([-0.6, -0.2, 0.1, 0.5])
    i_ref, obj_ref, k_ref = joint_line_search_reference(
        gray, cands, windows=windows, penalty=penalty, use_shape_set=occluded, intensity_scale=255.0)
    d, obj, k, _ = joint_line_search(gray, cands, windows=windows, penalty=penalty,
                                     use_shape_set=occluded, intensity_scale=255.0)
    np.testing.assert_allclose(obj, obj_ref, rtol=1e-4)
    assert np.array_equal(k, k_ref)
    assert (np.abs(d - cands[i_ref]) <= 0.5 * 0.4 + 1e-6).all()


def _joint_kernels(gray, candidates, rects, shapes, penalty, occluded, counts):
    """Each kernel's ``(objectives per candidate, least, window)`` at ``candidates``: the pixelwise
    twin over the summed-area tables of ``block_abs_diff`` and ``set_integrals``, and the
    row-stretch kernel over the views, in groups of one, two and three candidates (the last group
    short) and stretches of one, three and eight rows."""
    from recon.entropy.cost import set_sums_plan, view_lists, block_abs_diff, set_integrals
    from recon.entropy.layout import offer_runs, row_order
    from recon.entropy.legacy_matching import _joint_cost_pixelwise
    from recon.entropy.matching import _joint_group_kernel
    _, _, H, W = gray.shape
    starts, ks, pens = _compact_penalty(penalty)
    dense = np.ascontiguousarray(penalty.transpose(0, 2, 1))  # (H, K, W), inf: not offered
    run_start, runs = offer_runs(dense, occluded, shapes)
    order = row_order(H)
    views = view_lists((9, 9), None)
    plan = set_sums_plan(np.arange(11))
    disparities = np.asarray(candidates, np.float32)
    state = {}
    for name, group, rows in (("pixelwise", 1, 0), ("stretch", 1, 1), ("stretch", 3, 3), ("stretch", 2, 8)):
        least = np.full((H, W), np.inf, np.float32)
        best_k = np.full((H, W), -1, np.int64)
        outs = np.empty((len(candidates), H, W), np.float32)
        for i in range(0, len(candidates), group):
            if name == "pixelwise":
                tables = set_integrals(block_abs_diff(gray, candidates[i]), np.arange(11))
                _joint_cost_pixelwise(tables, occluded, rects, shapes, counts, starts, ks, pens,
                                      255.0, order, outs[i], least, best_k)
            else:
                _joint_group_kernel(gray, *views, disparities[i:i + group], *plan, occluded, rects, shapes, counts,
                                    dense, run_start, runs, 255.0, rows, outs[i:i + group], least, best_k)
        state[name if name == "pixelwise" else f"{name} {group} {rows}"] = (outs, least, best_k)
    return state


def test_joint_group_kernel_is_bit_identical_to_pixelwise_twin():
    from recon.entropy.layout import RUN_GAP
    rng = np.random.default_rng(13)
    # (6, 9): the 15-px windows wider and taller than the image; the widest: rows with several runs
    for H, W in ((21, 33), (6, 9), (7, RUN_GAP + 20)):
        gray = np.round(rng.random((9, 9, H, W)) * 8).astype(np.float32) / 8  # ties between candidates
        inputs = joint_inputs(rng, H, W)[1:]
        state = _joint_kernels(gray, np.array([-0.7, 0.0, 0.35, 1.1, 0.0]), *inputs)
        for name in ("stretch 1 1", "stretch 3 3", "stretch 2 8"):
            for a, b in zip(state["pixelwise"], state[name]):
                np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))
            assert (state[name][2] >= 0).all()


def test_joint_group_kernel_converts_large_window_totals_exactly():
    # grey values up to 1000 in the lower rows: window totals beyond 2^51 (the magic conversion's
    # limit) there, so that those stretches take the plain conversion, the upper ones the magic one;
    # the same maps as the twin's int64 -> float64 conversion
    rng = np.random.default_rng(17)
    H, W = 30, 40
    gray = rng.random((9, 9, H, W)).astype(np.float32)
    gray[:, :, H // 2:] *= 1000
    inputs = joint_inputs(rng, H, W)[1:]
    state = _joint_kernels(gray, np.array([-0.7, 0.1, 0.6]), *inputs)
    for name in ("stretch 1 1", "stretch 3 3", "stretch 2 8"):
        for a, b in zip(state["pixelwise"], state[name]):
            np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))


def test_compact_penalty_is_identical_to_reference():
    rng = np.random.default_rng(7)
    for shape in ((13, 17, 11), (1, 1, 1), (3, 40, 77)):
        pen = penalty_volume(rng, *shape)
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
