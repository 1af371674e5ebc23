"""Median filter with ``mode="nearest"`` borders: a compiled, row-parallel twin of
``scipy.ndimage.median_filter(image, footprint=..., mode="nearest")`` (the reference,
:func:`median_filter_nearest_reference`) giving the very same map.

A median over an odd or even number of samples is one of the samples (scipy takes the one of rank
``n // 2``, counted from 0 in ascending order), so the twin only has to pick the same sample. It
runs a selection network: Batcher's odd-even merge sort of the ``n`` samples
(:func:`sorting_network`), cut to the compare-exchanges that the output of rank ``n // 2`` depends on
(:func:`selection_network`; 113 of them for a 5x5 box), each a minimum and a maximum of two rows of
samples along x, branch-free, so many pixels go through it at once. Two samples that compare equal
but differ in bits (``0.0`` and ``-0.0``) or NaN (no order) could make the two pick differently;
images holding either go to scipy.
"""

from __future__ import annotations

from functools import lru_cache

from recon.jit import numba
import numpy as np

from recon.native import call, chosen, thread_count


def median_filter_nearest_reference(image: np.ndarray, *, footprint: np.ndarray) -> np.ndarray:
    """``scipy.ndimage.median_filter(image, footprint=footprint, mode="nearest")``."""
    from scipy import ndimage

    return ndimage.median_filter(image, footprint=footprint, mode="nearest")


def sorting_network(n: int) -> list[tuple[int, int]]:
    """Batcher's odd-even merge sort of ``n`` values as compare-exchanges ``(i, j)``, ``i < j``:
    put the smaller of positions ``i`` and ``j`` at ``i`` and the larger at ``j``, in list order.
    Sorts any ``n`` (the network of the next power of two without the exchanges beyond ``n``: the
    missing values act as ``+inf``, which no exchange moves down)."""
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return pairs


@lru_cache(maxsize=32)
def selection_network(n: int, rank: int) -> np.ndarray:
    """``(M, 2)`` int64: the compare-exchanges of :func:`sorting_network` ``(n)`` that the value
    at position ``rank`` depends on, in order; after them that position holds the value of that
    rank (counted from 0 in ascending order)."""
    needed = {rank}
    kept = []
    for i, j in reversed(sorting_network(n)):
        if i in needed or j in needed:
            kept.append((i, j))
            needed |= {i, j}
    return np.array(kept[::-1], np.int64).reshape(-1, 2)


#: Columns of a row that go through the selection network together: their samples stay in the
#: first-level cache (25 samples x 128 px x 8 bytes).
MEDIAN_COLUMNS = 128


@numba.njit(cache=True, parallel=True)
def _median_kernel(image, dy, dx, pairs, rank, out):
    # Row by row, MEDIAN_COLUMNS columns at a time: the n samples of every column gathered into
    # rows of buf (borders continued by the nearest pixel), the selection network's
    # compare-exchanges run along those rows, the sample of rank `rank` written out.
    H, W = image.shape
    n = dy.shape[0]
    block = MEDIAN_COLUMNS
    for y in numba.prange(H):
        buf = np.empty((n, block), image.dtype)
        for x0 in range(0, W, block):
            m = min(block, W - x0)
            for i in range(n):
                src = image[min(max(y + dy[i], 0), H - 1)]
                row = buf[i]
                d = dx[i]
                lo = min(max(-d - x0, 0), m)  # [lo, hi): x0 + x + d inside the image
                hi = min(max(W - d - x0, lo), m)
                for x in range(lo):
                    row[x] = src[0]
                inner = src[x0 + lo + d:x0 + hi + d]
                for x in range(hi - lo):
                    row[lo + x] = inner[x]
                for x in range(hi, m):
                    row[x] = src[W - 1]
            for p in range(pairs.shape[0]):
                a = buf[pairs[p, 0]]
                b = buf[pairs[p, 1]]
                for x in range(m):
                    u = a[x]
                    v = b[x]
                    a[x] = u if u < v else v
                    b[x] = v if u < v else u
            result = buf[rank]
            for x in range(m):
                out[y, x0 + x] = result[x]


def median_filter_nearest(image: np.ndarray, *, size: int | tuple[int, int] | None = None,
                          footprint: np.ndarray | None = None, kernel: str = "auto") -> np.ndarray:
    """``(H, W)`` median of each pixel's ``size`` box (an int: square) or ``footprint`` (bool,
    centred at ``shape // 2`` like scipy's), borders continued by the nearest pixel; the dtype of
    ``image``. The same map as :func:`median_filter_nearest_reference` (see the module docstring).
    Compiled: the C twin of the kernel, ``recon/native/median.c``, where it loads, else numba's
    (``kernel``: :func:`recon.native.chosen`, asked first: a wrong name is refused also where scipy's
    filter takes the image)."""
    native = chosen("median", kernel)
    if footprint is None:
        if size is None:
            raise ValueError("median_filter_nearest needs size or footprint, got neither")
        shape = (size, size) if np.isscalar(size) else tuple(size)
        footprint = np.ones(shape, bool)
    footprint = np.asarray(footprint, bool)
    image = np.asarray(image)
    if (image.ndim != 2 or footprint.ndim != 2 or image.dtype not in (np.float32, np.float64)
            or not footprint.any() or image.size == 0):
        return median_filter_nearest_reference(image, footprint=footprint)
    if np.isnan(image).any() or (np.signbit(image) & (image == 0)).any():
        return median_filter_nearest_reference(image, footprint=footprint)
    fy, fx = np.nonzero(footprint)
    dy = (fy - footprint.shape[0] // 2).astype(np.int64)
    dx = (fx - footprint.shape[1] // 2).astype(np.int64)
    out = np.empty(image.shape, image.dtype)
    rank = len(dy) // 2
    image = np.ascontiguousarray(image)
    pairs = selection_network(len(dy), rank)
    if native:  # image float32 or float64 (above), out of its dtype, pairs (M, 2) in 0..n-1
        call("median", "lfrig_median", image, int(image.dtype == np.float64), *image.shape, dy, dx, len(dy), pairs,
             len(pairs), rank, out, thread_count())
    else:
        _median_kernel(image, dy, dx, pairs, rank, out)
    return out
