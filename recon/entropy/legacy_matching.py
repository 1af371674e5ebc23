"""Retired compiled kernels of the line search, kept only because tests pin the current kernels
to them (``tests/test_twins_matching.py``): nothing in the estimator calls them.

- ``_joint_cost_pixelwise``: the pixel-by-pixel joint search kernel, the readable twin of
  :func:`recon.entropy.matching._joint_group_kernel` (the same maps bit for bit), over the penalty
  lists of ``_compact_penalty``;
- ``_compact_penalty`` and its readable twin ``_compact_penalty_reference``: each pixel's offered
  windows and penalties as flat lists.
"""

from __future__ import annotations

from recon.jit import numba
import numpy as np

from recon.entropy.cost import FIXED_INV


@numba.njit(cache=True, parallel=True)
def _joint_cost_pixelwise(integrals, pixel_set, rects, window_shape, counts, starts, ks, pens, scale,
                          order, out, best, best_k):
    # The readable twin of _joint_group_kernel (the same maps bit for bit; the search's kernel
    # before the window-major one): pixel by pixel, each pixel's allowed windows
    # ks[starts[p]:starts[p + 1]] with penalties pens[...] (:func:`_compact_penalty`) in ascending
    # order, the first least objective kept. out = this candidate's objective; best/best_k = the
    # least objective over the candidates so far and its window (the first candidate on ties, as
    # np.argmin over the curve picks). Rows in the given order (:func:`row_order`).
    H = out.shape[0]
    W = out.shape[1]
    for jr in numba.prange(H):
        y = order[jr]
        for x in range(W):
            p = y * W + x
            c_best = 1e300
            k_best = -1
            occluded_set = pixel_set[y, x]
            for j in range(starts[p], starts[p + 1]):
                k = ks[j]
                s = window_shape[k] if occluded_set else 0
                ya = max(y + rects[k, 0], 0)
                yb = min(y + rects[k, 1], H - 1) + 1
                xa = max(x + rects[k, 2], 0)
                xb = min(x + rects[k, 3], W - 1) + 1
                ii = integrals[s]
                total = (ii[yb, xb] - ii[ya, xb] - ii[yb, xa] + ii[ya, xa]) * FIXED_INV
                c = scale * total / ((yb - ya) * (xb - xa) * counts[s]) + pens[j]
                if c < c_best:
                    c_best = c
                    k_best = k
            c32 = np.float32(c_best)
            out[y, x] = c32
            if c32 < best[y, x]:
                best[y, x] = c32
                best_k[y, x] = k_best




@numba.njit(cache=True, parallel=True)
def _compact_penalty_kernel(penalty):
    # Two row-parallel passes: count each row's finite entries, then (rows offset by the counts
    # above) copy them out in row-major order, windows ascending: the same lists as one serial
    # pass. (The lists feed _joint_cost_pixelwise, the twin of the search's kernel.)
    H, W, K = penalty.shape
    row_n = np.zeros(H + 1, np.int64)
    for y in numba.prange(H):
        n = 0
        for x in range(W):
            for k in range(K):
                if np.isfinite(penalty[y, x, k]):
                    n += 1
        row_n[y + 1] = n
    for y in range(H):
        row_n[y + 1] += row_n[y]
    starts = np.empty(H * W + 1, np.int64)
    ks = np.empty(row_n[H], np.int32)
    pens = np.empty(row_n[H], np.float32)
    for y in numba.prange(H):
        n = row_n[y]
        for x in range(W):
            starts[y * W + x] = n
            for k in range(K):
                v = penalty[y, x, k]
                if np.isfinite(v):
                    ks[n] = k
                    pens[n] = v
                    n += 1
    starts[H * W] = row_n[H]
    return starts, ks, pens


def _compact_penalty_reference(penalty: np.ndarray):
    """Readable twin of :func:`_compact_penalty` (the same three arrays)."""
    H, W, K = penalty.shape
    flat = np.asarray(penalty, np.float32).reshape(H * W, K)
    finite = np.isfinite(flat)
    starts = np.concatenate([[0], np.cumsum(finite.sum(axis=1))]).astype(np.int64)
    p, k = np.nonzero(finite)  # row-major: pixels in order, windows ascending within a pixel
    return starts, k.astype(np.int32), flat[p, k]


def _compact_penalty(penalty: np.ndarray):
    """``(starts, ks, pens)``: the finite entries of ``(H, W, K)`` ``penalty`` per pixel, row-major
    (windows ascending); ``ks`` int32, ``pens`` float32 (the kernel adds them in float64, exactly).
    Pixel ``p = y * W + x`` has ``ks[starts[p]:starts[p + 1]]``."""
    return _compact_penalty_kernel(np.ascontiguousarray(penalty, dtype=np.float32))
