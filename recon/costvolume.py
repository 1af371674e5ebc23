"""Plane-sweep matching costs: every view shifted by a candidate disparity, compared with the centre.

For a candidate disparity ``d`` the view ``(u, v)`` is sampled at ``(y - (u-u0) d, x - (v-v0) d)``
(``docs/conventions.md``), so that a scene point at disparity ``d`` lands on the centre view's pixel.
The per-pixel cost is the mean absolute difference over the chosen views; windows are applied
afterwards with box filters.

Sampling is bilinear with edge replication (coordinates are clamped into the image). Two
implementations compute the same numbers: :func:`pixel_cost_reference` is plain numpy and easy to
read; :func:`pixel_cost` is a numba kernel, parallel over rows, that the estimators use.
"""

from __future__ import annotations

import numba
import numpy as np


def view_offsets(grid_shape: tuple[int, int], views: np.ndarray | None = None) -> np.ndarray:
    """``(N, 2)`` float64 ``(u - u0, v - v0)`` of the views to match (all but the centre by default).

    ``views`` is an optional ``(N, 2)`` integer array of ``(u, v)`` grid positions to use instead.
    """
    rows, cols = grid_shape
    u0, v0 = rows // 2, cols // 2
    if views is None:
        views = np.array([(u, v) for u in range(rows) for v in range(cols) if (u, v) != (u0, v0)])
    views = np.asarray(views, dtype=np.int64).reshape(-1, 2)
    return (views - np.array([u0, v0])).astype(np.float64)


def sample_shifted(image: np.ndarray, dy: float, dx: float) -> np.ndarray:
    """``image`` sampled at ``(y + dy, x + dx)``, bilinear, edges replicated. ``(H, W)`` float32."""
    h, w = image.shape
    ys = np.clip(np.arange(h) + dy, 0, h - 1)
    xs = np.clip(np.arange(w) + dx, 0, w - 1)
    y0 = np.minimum(np.floor(ys).astype(np.int64), h - 2) if h > 1 else np.zeros(h, np.int64)
    x0 = np.minimum(np.floor(xs).astype(np.int64), w - 2) if w > 1 else np.zeros(w, np.int64)
    fy = (ys - y0)[:, None]
    fx = (xs - x0)[None, :]
    y1 = np.minimum(y0 + 1, h - 1)
    x1 = np.minimum(x0 + 1, w - 1)
    top = image[y0][:, x0] * (1 - fx) + image[y0][:, x1] * fx
    bottom = image[y1][:, x0] * (1 - fx) + image[y1][:, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def pixel_cost_reference(
    gray: np.ndarray, disparity: float, *, offsets: np.ndarray, indices: np.ndarray
) -> np.ndarray:
    """Mean absolute difference between the centre view and the shifted views, per pixel.

    Parameters
    ----------
    gray
        ``(U, V, H, W)`` float32 views.
    disparity
        Candidate disparity in pixels per view step.
    offsets
        ``(N, 2)`` ``(u - u0, v - v0)`` of the views to compare (:func:`view_offsets`).
    indices
        ``(N, 2)`` integer ``(u, v)`` of the same views.

    Returns
    -------
    ``(H, W)`` float32 cost.
    """
    rows, cols = gray.shape[:2]
    centre = gray[rows // 2, cols // 2]
    total = np.zeros(centre.shape, dtype=np.float64)
    for (du, dv), (u, v) in zip(offsets, indices):
        total += np.abs(centre - sample_shifted(gray[u, v], -du * disparity, -dv * disparity))
    return (total / len(offsets)).astype(np.float32)


# Only the fast-math flags that cannot change a finite result (no NaN/inf, sign of zero): with
# reassociation or FMA contraction, a freshly compiled kernel and its cached twin in another process
# rounded differently, and a batch worker disagreed with `lfrig reconstruct` in the last bits.
@numba.njit(parallel=True, fastmath={"nnan", "ninf", "nsz"}, cache=True)
def _pixel_cost_kernel(gray, disparity, offsets, indices, out):
    n_views = offsets.shape[0]
    h, w = gray.shape[2], gray.shape[3]
    centre = gray[gray.shape[0] // 2, gray.shape[1] // 2]
    inv = np.float32(1.0 / n_views)
    for y in numba.prange(h):
        acc = np.zeros(w, dtype=np.float32)
        for k in range(n_views):
            view = gray[indices[k, 0], indices[k, 1]]
            sy = y - offsets[k, 0] * disparity
            sy = min(max(sy, 0.0), h - 1.0)
            y0 = min(int(np.floor(sy)), h - 2) if h > 1 else 0
            fy = np.float32(sy - y0)
            y1 = min(y0 + 1, h - 1)
            shift_x = -offsets[k, 1] * disparity
            for x in range(w):
                sx = min(max(x + shift_x, 0.0), w - 1.0)
                x0 = min(int(np.floor(sx)), w - 2) if w > 1 else 0
                fx = np.float32(sx - x0)
                x1 = min(x0 + 1, w - 1)
                top = view[y0, x0] + (view[y0, x1] - view[y0, x0]) * fx
                bottom = view[y1, x0] + (view[y1, x1] - view[y1, x0]) * fx
                acc[x] += abs(centre[y, x] - (top + (bottom - top) * fy))
        for x in range(w):
            out[y, x] = acc[x] * inv


def pixel_cost(gray: np.ndarray, disparity: float, *, offsets: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fast twin of :func:`pixel_cost_reference` (same arguments, same result to float32 rounding)."""
    out = np.empty(gray.shape[2:], dtype=np.float32)
    _pixel_cost_kernel(
        np.ascontiguousarray(gray, dtype=np.float32),
        float(disparity),
        np.ascontiguousarray(offsets, dtype=np.float64),
        np.ascontiguousarray(indices, dtype=np.int64),
        out,
    )
    return out


def box_mean_reference(image: np.ndarray, window: int) -> np.ndarray:
    """Mean over a ``window x window`` square around each pixel, borders mirrored (``fedcba|abcdef``,
    OpenCV's ``BORDER_REFLECT``). ``(H, W)`` float32; plain numpy."""
    r = window // 2
    padded = np.pad(image.astype(np.float64), r, mode="symmetric")
    rows = np.lib.stride_tricks.sliding_window_view(padded, window, axis=1).sum(axis=-1)
    both = np.lib.stride_tricks.sliding_window_view(rows, window, axis=0).sum(axis=-1)
    return (both / (window * window)).astype(np.float32)


@numba.njit(cache=True)
def _reflect(i, n):
    # BORDER_REFLECT for offsets of less than one image size.
    if i < 0:
        return -i - 1
    if i >= n:
        return 2 * n - i - 1
    return i


@numba.njit(parallel=True, cache=True)
def _box_mean_kernel(image, window, out):
    h, w = image.shape
    r = window // 2
    rows = np.empty((h, w), dtype=np.float64)
    for y in numba.prange(h):
        for x in range(w):
            acc = 0.0
            for k in range(-r, r + 1):
                acc += image[y, _reflect(x + k, w)]
            rows[y, x] = acc
    scale = 1.0 / (window * window)
    for y in numba.prange(h):
        for x in range(w):
            acc = 0.0
            for k in range(-r, r + 1):
                acc += rows[_reflect(y + k, h), x]
            out[y, x] = acc * scale


def box_mean(image: np.ndarray, window: int) -> np.ndarray:
    """Fast twin of :func:`box_mean_reference`.

    Every output pixel is a direct sum over its own window in a fixed order (no running sums), so a
    pixel's value does not depend on the image size, the thread count or where a tile starts: a tile
    with a wide enough halo reproduces the whole image's result bit for bit.
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be an odd number of pixels >= 1; got {window}")
    if window // 2 >= min(image.shape):
        raise ValueError(f"window {window} is too large for a {image.shape[1]}x{image.shape[0]} image")
    out = np.empty(image.shape, dtype=np.float32)
    _box_mean_kernel(np.ascontiguousarray(image, dtype=np.float32), int(window), out)
    return out
