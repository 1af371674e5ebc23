"""Inputs the twin tests of the estimator's kernels share: seeded, with the cases that break a
kernel (ties, NaN, inf, signed zeros, rows or pixels offered nothing)."""

from __future__ import annotations

import numpy as np


def seeded():
    """The generator most twin tests draw from."""
    return np.random.default_rng(7)


def cost_volume(rng, D=23, H=17, W=19):
    """``(D, H, W)`` float32 costs with the cases a search must get right."""
    # Quantised costs make exact ties (the first minimum must win) and flat stretches common.
    costs = np.round(rng.random((D, H, W)) * 8).astype(np.float32) / 8
    costs[:, 0, 0] = np.nan  # all NaN
    costs[3, 1, 1] = np.nan  # NaN after a minimum: np.argmin takes the NaN
    costs[:, 2, 2] = 1.0  # all tied: first candidate, no parabola
    costs[:, 3, 3] = np.linspace(1, 0, D)  # minimum at the last candidate
    costs[:, 4, 4] = np.inf
    return costs


def penalty_volume(rng, H=13, W=17, K=11):
    """``(H, W, K)`` float32 window penalties, most not offered (inf), with odd rows and values."""
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


def joint_inputs(rng, H, W, sizes=(3, 5, 15)):
    """``(windows, rects, shapes, penalty, occluded, counts)`` of a joint line search, with ties,
    runs and rows that offer one window."""
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
