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
    from recon.entropy.options import make_options
    from recon.entropy.steps import _search_penalty
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


def _joint_inputs(rng, H, W, sizes=(3, 5, 15)):
    from recon.entropy.matching import set_view_counts
    from recon.entropy.windows import N_SHAPES, window_rect
    windows = [(s, z) for s in range(N_SHAPES) for z in sizes]
    rects = np.array([window_rect(s, z) for s, z in windows], np.int64)
    shapes = np.array([s for s, _ in windows], np.int64)
    penalty = rng.normal(0, 1, (H, W, len(windows))).astype(np.float32)
    penalty = np.round(penalty * 4) / 4  # coarse: exact ties between windows happen
    penalty[rng.random(penalty.shape) < 0.5] = np.inf
    penalty[..., 0] = np.where(rng.random((H, W)) < 0.9, 0.0, np.inf)  # the square mostly offered
    penalty[:, :, len(sizes):][:, W // 3] = np.inf  # a column offering squares only
    penalty[H // 2] = np.inf  # a row offering one window only
    penalty[H // 2, :, 1] = -0.25
    penalty[1, :, 1] = np.inf  # the 5x5 square offered at both ends of row 1 only: two runs if wide
    penalty[1, [0, 1, 2, W - 3, W - 2], 1] = 0.5
    occluded = rng.random((H, W)) < 0.3
    occluded[:, -3:] = True  # a run of occluded pixels at the right edge
    counts = set_view_counts((9, 9)).astype(np.float64)
    return windows, rects, shapes, penalty, occluded, counts


def test_joint_cost_kernel_is_bit_identical_to_pixelwise_twin():
    from recon.entropy.matching import (_joint_cost_kernel, _joint_cost_pixelwise, block_abs_diff_fast,
                                        row_order, set_integrals, window_major_penalty)
    rng = np.random.default_rng(13)
    from recon.entropy.matching import RUN_GAP
    # (6, 9): the 15-px windows wider than the image; the widest: rows with several runs
    for H, W in ((21, 33), (6, 9), (7, RUN_GAP + 20)):
        gray = np.round(rng.random((9, 9, H, W)) * 8).astype(np.float32) / 8
        windows, rects, shapes, penalty, occluded, counts = _joint_inputs(rng, H, W)
        starts, ks, pens = _compact_penalty(penalty)
        dense, run_start, runs = window_major_penalty(penalty, occluded, shapes)
        order = row_order(H)
        state = {}
        for name in ("pixelwise", "window-major"):
            least = np.full((H, W), np.inf, np.float32)
            best_k = np.full((H, W), -1, np.int64)
            outs = []
            for d in (-0.7, 0.0, 0.35, 1.1):
                blocks = block_abs_diff_fast(gray, d)
                integrals = set_integrals(blocks, np.arange(11))
                out = np.empty((H, W), np.float32)
                if name == "pixelwise":
                    _joint_cost_pixelwise(integrals, occluded, rects, shapes, counts, starts, ks, pens,
                                          255.0, order, out, least, best_k)
                else:
                    _joint_cost_kernel(integrals, occluded, rects, shapes, counts, dense, run_start,
                                       runs, 255.0, order, out, least, best_k)
                outs.append(out)
            state[name] = (np.stack(outs), least, best_k)
        for a, b in zip(state["pixelwise"], state["window-major"]):
            np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))
        assert (state["window-major"][2] >= 0).all()


def test_window_major_penalty_layout():
    from recon.entropy.matching import RUN_GAP, window_major_penalty
    rng = np.random.default_rng(17)
    H, W = 9, RUN_GAP + 10
    _, _, shapes, penalty, occluded, _ = _joint_inputs(rng, H, W)
    penalty[0, 0, 3] = np.nan  # not finite: not offered
    dense, run_start, runs = window_major_penalty(penalty, occluded, shapes)
    finite = np.isfinite(penalty)
    np.testing.assert_array_equal(dense, np.where(finite, penalty, np.inf).transpose(2, 0, 1))
    assert run_start[0] == 0 and run_start[-1] == len(runs) and (np.diff(run_start) >= 0).all()
    for k, shape in enumerate(shapes):
        for y in range(H):
            for pas in (0, 1):
                who = finite[y, :, k] & ((occluded[y] & (shape != 0)) == bool(pas))
                i = (k * H + y) * 2 + pas
                mine = runs[run_start[i]:run_start[i + 1]]
                covered = np.zeros(W, bool)
                for lo, hi in mine:
                    assert lo < hi and who[lo] and who[hi - 1]  # a run starts and ends on its pixels
                    covered[lo:hi] = True
                assert (covered >= who).all()  # every offering pixel in a run
                assert (mine[1:, 0] - mine[:-1, 1] >= RUN_GAP).all()  # ascending, gaps kept apart
                if (k, y, pas) == (1, 1, 0):
                    np.testing.assert_array_equal(mine, [[0, 3], [W - 3, W - 1]])


def _block_abs_diff_float32(gray, disparity, view_mask=None):
    """The compiled kernel's float32 arithmetic, written out with numpy (rows first, then x with
    one fraction per view; samples left and right of the image clamped to its first/last)."""
    from recon.entropy.matching import N_BLOCKS, _view_lists
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


def test_block_abs_diff_fast_is_bit_identical_to_its_float32_arithmetic():
    from recon.entropy.initial import initial_view_mask
    from recon.entropy.matching import block_abs_diff_fast
    rng = np.random.default_rng(19)
    gray = rng.random((9, 9, 7, 23)).astype(np.float32)
    for d in (-3.7, -0.52, 0.0, 0.37, 1.0, 2.96, 13.3):  # 13.3: every outer view clamped whole
        for mask in (None, initial_view_mask((9, 9))):
            fast = block_abs_diff_fast(gray, d, view_mask=mask)
            np.testing.assert_array_equal(fast.view(np.uint32), _block_abs_diff_float32(gray, d, mask).view(np.uint32))
