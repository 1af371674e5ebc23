"""Memory layouts the joint line search reads fast: the penalty volume window by window, the rows
in the order the threads take them.

Twins follow the rule of :mod:`recon.entropy`: ``name`` compiled, ``name_reference`` readable.
"""

from __future__ import annotations

import numba
import numpy as np

#: Two runs of pixels that offer a window closer than this many columns are one run for the joint
#: kernel: the pixels between cost a vectorised evaluation each, a new run its set-up and a vector
#: loop's ends. Per candidate, one thread: slanted-v1 (offers scattered) 29.7 / 25.4 / 24.1 / 24.0
#: ms at 8 / 32 / 64 / 128, one span per row ~27.5; backgammon 23.0 / 22.2 / 21.8 / 21.6, ~22.2.
RUN_GAP = 64


@numba.njit(cache=True)
def _offer_runs(dense, pixel_set, y, k, pas, shaped, runs, n):
    # Runs of row y's pixels that offer window k in pass pas (see _joint_cost_kernel; dense is the
    # (K, H, W) penalty, inf = not offered), gaps below RUN_GAP closed; written to runs[n:] if runs
    # has rows, else only counted. Returns n + count.
    W = dense.shape[2]
    lo = -1
    hi = -1
    row = dense[k, y]
    for x in range(W):
        if row[x] == np.inf or (shaped and pixel_set[y, x]) != (pas == 1):
            continue
        if lo >= 0 and x - hi >= RUN_GAP:
            if runs.shape[0] > 0:
                runs[n, 0] = lo
                runs[n, 1] = hi
            n += 1
            lo = -1
        if lo < 0:
            lo = x
        hi = x + 1
    if lo >= 0:
        if runs.shape[0] > 0:
            runs[n, 0] = lo
            runs[n, 1] = hi
        n += 1
    return n


@numba.njit(cache=True, parallel=True)
def _window_major_kernel(penalty, pixel_set, window_shape, out):
    # Row by row (a row of the (H, W, K) volume stays in cache), each window's row written along x;
    # the runs counted per (window, row, pass), then laid out in that order and written.
    H, W, K = penalty.shape
    count = np.zeros(K * H * 2 + 1, np.int64)
    none = np.empty((0, 2), np.int32)
    for y in numba.prange(H):
        for k in range(K):
            for x in range(W):
                v = penalty[y, x, k]
                out[k, y, x] = v if np.isfinite(v) else np.inf
            shaped = window_shape[k] != 0
            for pas in range(2):
                count[(k * H + y) * 2 + pas + 1] = _offer_runs(out, pixel_set, y, k, pas, shaped,
                                                               none, 0)
    for i in range(K * H * 2):
        count[i + 1] += count[i]
    runs = np.empty((count[K * H * 2], 2), np.int32)
    for y in numba.prange(H):
        for k in range(K):
            shaped = window_shape[k] != 0
            for pas in range(2):
                _offer_runs(out, pixel_set, y, k, pas, shaped, runs, count[(k * H + y) * 2 + pas])
    return count, runs


def window_major_penalty(penalty: np.ndarray, use_shape_set: np.ndarray, window_shape: np.ndarray):
    """The joint search's layout of its ``(H, W, K)`` penalty: ``(K, H, W)`` float32 (``inf`` where
    the entry is not finite: window not offered) and the column runs of the pixels that offer each
    window, per window ``k``, row ``y`` and pass (0: pixels matched over all views, every pixel for
    a square window, shape 0; 1: shaped windows at ``use_shape_set`` pixels, matched over the
    window's visible set): ``runs[run_start[i]:run_start[i + 1]]`` with ``i = (k * H + y) * 2 +
    pass``, ``(n, 2)`` int32 ``[lo, hi)`` ascending, each starting and ending at an offering pixel,
    runs closer than :data:`RUN_GAP` joined. Returns ``(penalty, run_start, runs)``."""
    H, W, K = penalty.shape
    out = np.empty((K, H, W), np.float32)
    run_start, runs = _window_major_kernel(np.ascontiguousarray(penalty, dtype=np.float32),
                                           np.ascontiguousarray(use_shape_set, dtype=np.bool_),
                                           np.ascontiguousarray(window_shape, dtype=np.int64), out)
    return out, run_start, runs


def row_order(H: int) -> np.ndarray:
    """Rows dealt round-robin to the threads: ``prange`` hands each thread one contiguous share
    of the loop, and the joint kernel's work per row varies with the windows offered (near depth
    edges 77 per pixel, elsewhere 7); on backgammon the top half of the rows held 67 % of it, so
    one of two threads ran 1.7x as long as the other (measured per thread: 89 vs 52 ticks; dealt
    round-robin 71 vs 71)."""
    T = max(numba.get_num_threads(), 1)
    return np.concatenate([np.arange(t, H, T) for t in range(T)]).astype(np.int64)
