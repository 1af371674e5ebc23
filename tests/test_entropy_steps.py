"""The estimator's steps (recon/entropy/steps.py): their arithmetic on options."""

from __future__ import annotations

import numpy as np


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
