"""Median filter with ``mode="nearest"`` borders: a compiled, row-parallel twin of
``scipy.ndimage.median_filter(image, footprint=..., mode="nearest")`` (the reference,
:func:`median_filter_nearest_reference`) giving the very same map.

A median over an odd or even number of samples is one of the samples (scipy takes the one of rank
``n // 2``, counted from 0 in ascending order), so the twin only has to pick the same sample: it
sorts each pixel's samples and takes that rank. Two samples that compare equal but differ in bits
(``0.0`` and ``-0.0``) or NaN (no order) could make the two pick differently; images holding either
go to scipy.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import ndimage


def median_filter_nearest_reference(image: np.ndarray, *, footprint: np.ndarray) -> np.ndarray:
    """``scipy.ndimage.median_filter(image, footprint=footprint, mode="nearest")``."""
    return ndimage.median_filter(image, footprint=footprint, mode="nearest")


@numba.njit(cache=True, parallel=True)
def _median_kernel(image, dy, dx, rank, out):
    H, W = image.shape
    n = dy.shape[0]
    for y in numba.prange(H):
        buf = np.empty(n, image.dtype)
        for x in range(W):
            for i in range(n):
                yy = min(max(y + dy[i], 0), H - 1)
                xx = min(max(x + dx[i], 0), W - 1)
                buf[i] = image[yy, xx]
            # insertion sort: n is small (at most a few dozen samples)
            for i in range(1, n):
                v = buf[i]
                j = i - 1
                while j >= 0 and buf[j] > v:
                    buf[j + 1] = buf[j]
                    j -= 1
                buf[j + 1] = v
            out[y, x] = buf[rank]


def median_filter_nearest(image: np.ndarray, *, size: int | tuple[int, int] | None = None,
                          footprint: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` median of each pixel's ``size`` box (an int: square) or ``footprint`` (bool,
    centred at ``shape // 2`` like scipy's), borders continued by the nearest pixel; the dtype of
    ``image``. The same map as :func:`median_filter_nearest_reference` (see the module docstring)."""
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
    _median_kernel(np.ascontiguousarray(image), dy, dx, len(dy) // 2, out)
    return out
