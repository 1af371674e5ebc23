import numpy as np
import pytest

from recon.errors import ReconError
from recon.evaluate import score


def test_scores_follow_the_benchmark_definition():
    gt = np.zeros((40, 40), np.float32)
    est = gt.copy()
    inner = est[15:25, 15:25]  # the 10x10 scored region
    inner[:5, :] = 0.05  # 50 px: bad at 0.03 and 0.01, good at 0.07
    inner[5:6, :] = 1.0  # 10 px: bad everywhere
    est[0, 0] = 100.0  # in the border: ignored
    s = score(est, gt)
    assert s["pixels"] == 100
    assert s["badpix_0.07"] == pytest.approx(10.0)
    assert s["badpix_0.03"] == pytest.approx(60.0)
    assert s["mse_x100"] == pytest.approx(100 * (50 * 0.05**2 + 10 * 1.0) / 100, rel=1e-5)


def test_non_finite_pixels_are_skipped_and_masks_restrict():
    gt = np.zeros((32, 32), np.float32)
    est = np.full_like(gt, 0.1)
    est[16, 16] = np.nan
    s = score(est, gt, border=0)
    assert s["pixels"] == 32 * 32 - 1 and s["badpix_0.07"] == 100.0
    mask = np.zeros_like(gt, bool)
    assert np.isnan(score(est, gt, border=0, mask=mask)["mse_x100"])


def test_mismatched_sizes_are_a_clear_error():
    with pytest.raises(ReconError, match="same resolution"):
        score(np.zeros((40, 40)), np.zeros((40, 41)))
