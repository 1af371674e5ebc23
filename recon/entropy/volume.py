"""A per-pixel volume kept between steps in the room of its few meaningful entries.

The windows step scores every window at every pixel, ``(H, W, K)`` float32 with ``-inf`` for the
windows a pixel is not offered; most pixels are offered few of the ``K`` (7 of 77 away from depth
edges), and the line search reads the volume only a band of rows at a time and once more at each
pixel's chosen window. :class:`SparseVolume` holds the entries that are not the fill value, bit for
bit, with a bit mask per pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

from recon.jit import numba
import numpy as np

from recon.native import call, chosen, thread_count

#: Rows packed or unpacked at a time (keeps the ``(rows, W, K)`` temporaries small).
CHUNK_ROWS = 64


@dataclass(frozen=True)
class SparseVolume:
    """An ``(H, W, K)`` float32 volume: ``fill`` everywhere but at the entries of ``mask``.

    ``mask``: ``(H, W, ceil(K / 8))`` uint8, the entries that are not ``fill`` packed along ``K``
    (:func:`numpy.packbits`); ``start``: ``(H * W + 1,)`` int64, where each pixel's entries begin
    in ``values`` (pixels in row-major order, a pixel's entries by ascending ``k``)."""

    shape: tuple[int, int, int]
    fill: float
    mask: np.ndarray
    start: np.ndarray
    values: np.ndarray

    @classmethod
    def pack(cls, dense: np.ndarray, *, fill: float = -np.inf) -> SparseVolume:
        """The entries of ``dense`` ``(H, W, K)`` float32 that are not ``fill`` (NaN is kept)."""
        H, W, K = dense.shape
        masks, values, counts = [], [], []
        for y in range(0, H, CHUNK_ROWS):
            block = dense[y:y + CHUNK_ROWS]
            keep = ~(block == np.float32(fill))
            masks.append(np.packbits(keep, axis=2))
            counts.append(keep.sum(axis=2).ravel())
            values.append(block[keep])
        start = np.zeros(H * W + 1, np.int64)
        np.cumsum(np.concatenate(counts), out=start[1:])
        return cls((H, W, K), float(fill), np.concatenate(masks), start,
                   np.concatenate(values).astype(np.float32, copy=False))

    @property
    def nbytes(self) -> int:
        return self.mask.nbytes + self.start.nbytes + self.values.nbytes

    def rows(self, a: int, b: int) -> np.ndarray:
        """Rows ``[a, b)`` as a dense ``(b - a, W, K)`` float32 array."""
        H, W, K = self.shape
        a, b = max(a, 0), min(b, H)
        out = np.full((b - a, W, K), np.float32(self.fill), np.float32)
        keep = np.unpackbits(self.mask[a:b], axis=2, count=K).view(bool)
        out[keep] = self.values[self.start[a * W]:self.start[b * W]]
        return out

    def window_major(self, a: int, b: int, *, scale: float, kernel: str = "auto") -> np.ndarray:
        """Rows ``[a, b)`` laid out ``(b - a, K, W)`` float32, each row's windows one after another:
        ``float32(scale) * entry`` where that is finite, ``inf`` elsewhere (the fill and NaN
        included). The same values as ``np.multiply(self.rows(a, b), np.float32(scale),
        dtype=np.float32)`` with its non-finite entries set to ``inf``, moved to ``(b - a, K, W)``,
        in one pass without the dense volume (compiled: the C twin of the kernel,
        ``recon/native/volume.c``, where it loads, else numba's; ``kernel``: :func:`recon.native.chosen`)."""
        H, W, K = self.shape
        a, b = max(a, 0), min(b, H)
        out = np.empty((b - a, K, W), np.float32)
        if chosen("volume", kernel):
            self._check_packed()
            call("volume", "lfrig_window_major", self.mask, self.mask.shape[2], self.start, self.values, a, b - a, W,
                 K, float(np.float32(scale)), out, thread_count())
        else:
            _window_major_kernel(self.mask, self.start, self.values, a, W, np.float32(scale), out)
        return out

    def take(self, index: np.ndarray, *, kernel: str = "auto") -> np.ndarray:
        """``(H, W)`` float32: each pixel's entry at its ``index`` ``(H, W)`` in ``-K..K-1``
        (negative from the end), as ``np.take_along_axis(dense, index[..., None], 2)[..., 0]``
        (:meth:`take_reference`, the readable twin: the same entries). Compiled: the C twin of the
        kernel, ``recon/native/volume.c``, where it loads, else numba's (``kernel``:
        :func:`recon.native.chosen`)."""
        H, W, K = self._checked_index(index)
        out = np.empty((H, W), np.float32)
        index = np.ascontiguousarray(index, dtype=np.int64)
        if chosen("volume", kernel):
            self._check_packed()
            call("volume", "lfrig_take", self.mask, self.mask.shape[2], self.start, self.values, index, H, W, K,
                 float(np.float32(self.fill)), out, thread_count())
        else:
            _take_kernel(self.mask, self.start, self.values, index, K, np.float32(self.fill), out)
        return out

    def take_reference(self, index: np.ndarray) -> np.ndarray:
        """:meth:`take` in numpy, a chunk of rows at a time: each pixel's entry is the one whose
        rank among the pixel's kept entries is the count of kept entries up to its ``index``."""
        H, W, K = self._checked_index(index)
        index = np.where(index < 0, index + K, index)
        out = np.full((H, W), np.float32(self.fill), np.float32)
        if self.values.size == 0:
            return out
        for y in range(0, H, CHUNK_ROWS):
            keep = np.unpackbits(self.mask[y:y + CHUNK_ROWS], axis=2, count=K).view(bool)
            k = index[y:y + CHUNK_ROWS, :, None].astype(np.int64)
            before = np.cumsum(keep, axis=2, dtype=np.int32)  # entries up to and including k
            rank = np.take_along_axis(before, k, 2)[..., 0].astype(np.int64) - 1
            kept = np.take_along_axis(keep, k, 2)[..., 0]
            first = self.start[y * W:(y + keep.shape[0]) * W].reshape(keep.shape[:2])
            out[y:y + CHUNK_ROWS] = np.where(kept, self.values[np.where(kept, first + rank, 0)], np.float32(self.fill))
        return out

    def _check_packed(self) -> None:
        # What the C kernels read: the mask (H, W, ceil(K / 8)) uint8, the offsets (H * W + 1,)
        # int64 and the values float32, each C-contiguous (pack and select_windows make them so).
        H, W, K = self.shape
        for name, array, dtype, shape in (("mask", self.mask, np.uint8, (H, W, (K + 7) // 8)),
                                          ("start", self.start, np.int64, (H * W + 1,)),
                                          ("values", self.values, np.float32, (self.values.size,))):
            if array.dtype != dtype or array.shape != shape or not array.flags.c_contiguous:
                raise ValueError(f"the volume's {name} must be {shape} {np.dtype(dtype).name}, C-contiguous; "
                                 f"got {array.shape} {array.dtype}")

    def _checked_index(self, index: np.ndarray) -> tuple[int, int, int]:
        H, W, K = self.shape
        index = np.asarray(index)
        if index.shape != (H, W) or (index.size and (index.min() < -K or index.max() >= K)):
            raise ValueError(f"index must be ({H}, {W}) in {-K}..{K - 1}")
        return H, W, K


@numba.njit(cache=True, parallel=True, nogil=True)
def _take_kernel(mask, start, values, index, K, fill, out):
    # Twin of SparseVolume.take_reference, rows in parallel: a pixel's entry at k (index, -K..K-1)
    # is kept when bit k of its mask is set, and is then its entry after the kept ones below k.
    H, W = out.shape
    for y in numba.prange(H):
        for x in range(W):
            k = index[y, x]
            if k < 0:
                k += K
            bits = mask[y, x]
            if not bits[k >> 3] & (128 >> (k & 7)):
                out[y, x] = fill
                continue
            rank = 0
            for j in range(k):
                if bits[j >> 3] & (128 >> (j & 7)):
                    rank += 1
            out[y, x] = values[start[y * W + x] + rank]


@numba.njit(cache=True, parallel=True)
def _window_major_kernel(mask, start, values, a, W, scale, out):
    # Twin of SparseVolume.window_major's numpy statement: row by row, the row's (K, W) filled with
    # inf, then each pixel's entries (ascending k, as packed) scaled into it.
    n, K, _ = out.shape
    for r in numba.prange(n):
        dst = out[r]
        dst[:] = np.inf
        y = a + r
        for x in range(W):
            i = start[y * W + x]
            bits = mask[y, x]
            for k in range(K):
                if bits[k >> 3] & (128 >> (k & 7)):
                    v = values[i] * scale
                    i += 1
                    if np.isfinite(v):
                        dst[k, x] = v
