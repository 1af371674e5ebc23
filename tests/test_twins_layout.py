"""The joint search's penalty laid out window by window (recon.entropy.volume.SparseVolume.window_major)
holds the values of the dense volume, and recon.entropy.layout finds its runs of offering pixels."""

from __future__ import annotations

import numpy as np

from kernel_inputs import joint_inputs


def test_window_major_is_the_dense_penalty_moved():
    # Against the two steps it replaces: the dense volume's float32 product with the scale, its
    # entries that are not finite inf, then moved to (H, K, W); over whole volumes and bands.
    from recon.entropy.volume import SparseVolume
    rng = np.random.default_rng(3)
    entropy = (rng.random((13, 17, 21)) * 6 - 1).astype(np.float32)
    entropy[rng.random(entropy.shape) < 0.6] = -np.inf
    entropy[2, 3, 4] = np.nan
    entropy[5, 6, 7] = 3e38  # times 2.5: inf, not offered
    packed = SparseVolume.pack(entropy)
    for scale in (-1.0, -0.37, 0.0, -2.5):
        for a, b in ((0, 13), (3, 9), (-2, 20), (12, 13)):
            dense = packed.rows(a, b)
            with np.errstate(invalid="ignore", over="ignore"):
                product = np.multiply(dense, np.float32(scale), dtype=np.float32)
            expected = np.where(np.isfinite(product), product, np.inf).transpose(0, 2, 1)
            got = packed.window_major(a, b, scale=scale)
            assert got.dtype == np.float32 and got.flags.c_contiguous
            np.testing.assert_array_equal(got.view(np.uint32), expected.view(np.uint32))


def test_offer_runs():
    from recon.entropy.layout import RUN_GAP, offer_runs
    rng = np.random.default_rng(17)
    H, W = 9, RUN_GAP + 10
    _, _, shapes, penalty, occluded, _ = joint_inputs(rng, H, W)
    finite = np.isfinite(penalty)
    run_start, runs = offer_runs(np.ascontiguousarray(penalty.transpose(0, 2, 1)), occluded, shapes)
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
