"""recon.entropy.layout: the penalty volume laid out window by window holds the same values."""

from __future__ import annotations

import numpy as np

from kernel_inputs import joint_inputs


def test_window_major_penalty_layout():
    from recon.entropy.layout import RUN_GAP, window_major_penalty
    rng = np.random.default_rng(17)
    H, W = 9, RUN_GAP + 10
    _, _, shapes, penalty, occluded, _ = joint_inputs(rng, H, W)
    penalty[0, 0, 3] = np.nan  # not finite: not offered
    dense, run_start, runs = window_major_penalty(penalty, occluded, shapes)
    finite = np.isfinite(penalty)
    np.testing.assert_array_equal(dense, np.where(finite, penalty, np.inf).transpose(0, 2, 1))
    assert run_start[0] == 0 and run_start[-1] == len(runs) and (np.diff(run_start) >= 0).all()
    for k, shape in enumerate(shapes):
        for y in range(H):
            for pas in (0, 1):
                who = finite[y, :, k] & ((occluded[y] & (shape != 0)) == bool(pas))
                i = (y * len(shapes) + k) * 2 + pas
                mine = runs[run_start[i]:run_start[i + 1]]
                covered = np.zeros(W, bool)
                for lo, hi in mine:
                    assert lo < hi and who[lo] and who[hi - 1]  # a run starts and ends on its pixels
                    covered[lo:hi] = True
                assert (covered >= who).all()  # every offering pixel in a run
                assert (mine[1:, 0] - mine[:-1, 1] >= RUN_GAP).all()  # ascending, gaps kept apart
                if (k, y, pas) == (1, 1, 0):
                    np.testing.assert_array_equal(mine, [[0, 3], [W - 3, W - 1]])
