"""recon.entropy.layout: the penalty volume laid out window by window holds the same values."""

from __future__ import annotations

import numpy as np




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


def _joint_inputs(rng, H, W, sizes=(3, 5, 15)):
    from recon.entropy.cost import set_view_counts
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


def test_window_major_penalty_layout():
    from recon.entropy.layout import RUN_GAP, window_major_penalty
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
