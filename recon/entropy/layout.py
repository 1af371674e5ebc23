"""What the joint line search reads fast: the runs of pixels that offer each window in its penalty
laid out window by window, the rows in the order the threads take them.

Twins follow the rule of :mod:`recon.entropy`: ``name`` compiled, ``name_reference`` readable.
"""

from __future__ import annotations

from recon.jit import numba
import numpy as np

#: Two runs of pixels that offer a window closer than this many columns are one run for the joint
#: kernel: the pixels between cost a vectorised evaluation each, a new run its set-up and a vector
#: loop's ends. Per candidate, one thread: slanted-v1 (offers scattered) 29.7 / 25.4 / 24.1 / 24.0
#: ms at 8 / 32 / 64 / 128, one span per row ~27.5; backgammon 23.0 / 22.2 / 21.8 / 21.6, ~22.2.
RUN_GAP = 64


@numba.njit(cache=True)
def _offer_runs(row, occluded, shaped, runs, n, lo, hi):
    # The runs of the pixels that offer one window in one row, both passes in one scan (see
    # _joint_row; row: (W,) penalty, inf = not offered; a pixel is in pass 1 if the window
    # is shaped and the pixel occluded, else in pass 0), gaps below RUN_GAP closed. n: (2,) each
    # pass's next run, advanced by the runs found, which are written to runs if it has rows;
    # lo, hi: (2,) scratch.
    lo[:] = -1
    hi[:] = -1
    for x in range(row.shape[0]):
        if row[x] == np.inf:
            continue
        p = 1 if shaped and occluded[x] else 0
        if lo[p] >= 0 and x - hi[p] >= RUN_GAP:
            _put_run(runs, n, p, lo[p], hi[p])
            lo[p] = -1
        if lo[p] < 0:
            lo[p] = x
        hi[p] = x + 1
    for p in range(2):
        if lo[p] >= 0:
            _put_run(runs, n, p, lo[p], hi[p])


@numba.njit(cache=True)
def _put_run(runs, n, p, lo, hi):
    if runs.shape[0] > 0:
        runs[n[p], 0] = lo
        runs[n[p], 1] = hi
    n[p] += 1


@numba.njit(cache=True, parallel=True)
def _offer_runs_kernel(penalty, pixel_set, window_shape):
    # Each window's runs of both passes in one scan of its row, counted; then laid out in the order
    # (row, window, pass) and written in a second scan.
    H, K, W = penalty.shape
    count = np.zeros(H * K * 2 + 1, np.int64)
    none = np.empty((0, 2), np.int32)
    for y in numba.prange(H):
        n = np.empty(2, np.int64)
        lo = np.empty(2, np.int64)
        hi = np.empty(2, np.int64)
        for k in range(K):
            n[:] = 0
            _offer_runs(penalty[y, k], pixel_set[y], window_shape[k] != 0, none, n, lo, hi)
            count[(y * K + k) * 2 + 1] = n[0]
            count[(y * K + k) * 2 + 2] = n[1]
    for i in range(H * K * 2):
        count[i + 1] += count[i]
    runs = np.empty((count[H * K * 2], 2), np.int32)
    for y in numba.prange(H):
        n = np.empty(2, np.int64)
        lo = np.empty(2, np.int64)
        hi = np.empty(2, np.int64)
        for k in range(K):
            n[0] = count[(y * K + k) * 2]
            n[1] = count[(y * K + k) * 2 + 1]
            _offer_runs(penalty[y, k], pixel_set[y], window_shape[k] != 0, runs, n, lo, hi)
    return count, runs


def offer_runs(penalty: np.ndarray, use_shape_set: np.ndarray, window_shape: np.ndarray):
    """The column runs of the pixels that offer each window in the joint search's penalty,
    ``(H, K, W)`` float32, each row's windows one after another, ``inf`` where a window is not
    offered (:meth:`recon.entropy.volume.SparseVolume.window_major`): per row ``y``, window ``k``
    and pass (0: pixels matched over all views, every pixel for a square window, shape 0; 1: shaped
    windows at ``use_shape_set`` pixels, matched over the window's visible set):
    ``runs[run_start[i]:run_start[i + 1]]`` with ``i = (y * K + k) * 2 + pass``, ``(n, 2)`` int32
    ``[lo, hi)`` ascending, each starting and ending at an offering pixel, runs closer than
    :data:`RUN_GAP` joined. Returns ``(run_start, runs)``."""
    return _offer_runs_kernel(np.ascontiguousarray(penalty, dtype=np.float32),
                              np.ascontiguousarray(use_shape_set, dtype=np.bool_),
                              np.ascontiguousarray(window_shape, dtype=np.int64))


def row_order(H: int) -> np.ndarray:
    """Rows dealt round-robin to the threads: ``prange`` hands each thread one contiguous share
    of the loop, and the joint kernel's work per row varies with the windows offered (near depth
    edges 77 per pixel, elsewhere 7); on backgammon the top half of the rows held 67 % of it, so
    one of two threads ran 1.7x as long as the other (measured per thread: 89 vs 52 ticks; dealt
    round-robin 71 vs 71)."""
    T = max(numba.get_num_threads(), 1)
    return np.concatenate([np.arange(t, H, T) for t in range(T)]).astype(np.int64)
