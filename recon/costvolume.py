"""Plane-sweep matching costs: every view shifted by a candidate disparity, compared with the centre.

For a candidate disparity ``d`` the view ``(u, v)`` is sampled at ``(y - (u-u0) d, x - (v-v0) d)``
(``docs/conventions.md``), so that a scene point at disparity ``d`` lands on the centre view's pixel.
The per-pixel cost is the mean absolute difference over the chosen views; windows are applied
afterwards with box filters.

Sampling is bilinear with edge replication (coordinates are clamped into the image). Two
implementations compute the same numbers: :func:`pixel_cost_reference` is plain numpy and easy to
read; :func:`pixel_cost` is a numba kernel, parallel over rows, that the estimators use. The
baseline's plane sweep (:func:`recon.sweep.sweep_least_cost`) runs :func:`_sweep_kernel` from here,
or its C twin (``recon/native/sweep.c``), which mirrors it and the row helpers it calls line for line.
"""

from __future__ import annotations

from recon.jit import numba
import numpy as np

from recon.shifts import split_shift, view_offsets  # noqa: F401  view_offsets: the views to match


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
FAST = {"nnan", "ninf", "nsz"}


@numba.njit(fastmath=FAST, cache=True)
def _view_row(img, y, oy, fy, rv):
    # The row of one view (img, (H, W)) at y + oy + fy, blended from its two source rows with one
    # fraction fy for the whole row (into rv, a float32 row to work in, or the source row itself
    # where no blend is needed). Bilinear sampling is separable: the caller samples this row along x
    # with one fraction fx for the whole row, since the shift is the same for every pixel. The
    # integer part oy and the fraction depend only on the shift, not on where the image starts.
    H, W = img.shape
    y0 = y + oy
    if y0 < 0:  # above the image: its first row (edges replicated)
        return img[0]
    if y0 >= H - 1:  # below: its last row
        return img[H - 1]
    if fy == 0.0:  # on a row: 1 * a + 0 * b is a
        return img[y0]
    a = img[y0]
    b = img[y0 + 1]
    g = np.float32(1.0) - fy
    for x in range(W):
        rv[x] = g * a[x] + fy * b[x]
    return rv


@numba.njit(fastmath=FAST, cache=True)
def _add_view_row(img, c_row, y, oy, fy, ox, fx, acc, rv):
    # Adds to acc (float32, W) the absolute differences between the centre view's row y (c_row)
    # and one view (img, (H, W)) sampled at (y + oy + fy, x + ox + fx) (_view_row, then
    # add_shifted_row_diff).
    add_shifted_row_diff(acc, c_row, _view_row(img, y, oy, fy, rv), ox, fx)


@numba.njit(fastmath=FAST, cache=True)
def add_shifted_row_diff(acc, c_row, row, ox, fx):
    # Adds to acc (float32, W) |c_row[x] - row sampled at x + ox + fx| (linear between two samples,
    # fx in [0, 1) the same for the whole row; the first or last sample beyond the row's ends). The
    # middle run indexes slices from 0 so that numba vectorises it (numba's negative-index wrap of
    # row[x + ox] made every load a gather and kept the loop scalar); float32, 8 SIMD lanes.
    W = acc.shape[0]
    g = np.float32(1.0) - fx
    lo = min(max(-ox, 0), W)
    hi = min(max(W - 1 - ox, lo), W)
    for x in range(lo):
        acc[x] += abs(c_row[x] - row[0])
    n = hi - lo
    if n > 0:
        r0 = row[lo + ox:hi + ox]
        r1 = row[lo + ox + 1:hi + ox + 1]
        c = c_row[lo:hi]
        s = acc[lo:hi]
        for i in range(n):
            s[i] += abs(c[i] - (g * r0[i] + fx * r1[i]))
    for x in range(hi, W):
        acc[x] += abs(c_row[x] - row[W - 1])


@numba.njit(fastmath=FAST, cache=True)
def _cost_row(gray, vu, vv, oy, fy, ox, fx, y, acc, rv):
    # The summed absolute differences of the centre view's row y into acc (float32, W): the
    # views k = 0, 1, ... added in that order (_add_view_row).
    c_row = gray[gray.shape[0] // 2, gray.shape[1] // 2, y]
    acc[:] = 0.0
    for k in range(vu.shape[0]):
        _add_view_row(gray[vu[k], vv[k]], c_row, y, oy[k], fy[k], ox[k], fx[k], acc, rv)


@numba.njit(fastmath=FAST, cache=True)
def _sample(row, x, ox, fx):
    # row sampled at x + ox + fx as add_shifted_row_diff samples it: linear between two samples,
    # the first or last sample beyond the row's ends.
    i = x + ox
    if i < 0:
        return row[0]
    if i >= row.shape[0] - 1:
        return row[row.shape[0] - 1]
    return (np.float32(1.0) - fx) * row[i] + fx * row[i + 1]


@numba.njit(fastmath=FAST, cache=True)
def add_two_shifted_row_diffs(acc, c_row, p, ox_p, fx_p, q, ox_q, fx_q):
    # add_shifted_row_diff(acc, c_row, p, ox_p, fx_p), then the same with q, ox_q, fx_q, in one
    # pass: each acc[x] gets p's difference added, then q's, as the two calls would add them (the
    # same bits), but acc and c_row are read and acc written once for the two views. The middle
    # run, where both samples lie inside their rows, is vectorised as in add_shifted_row_diff.
    W = acc.shape[0]
    gp = np.float32(1.0) - fx_p
    gq = np.float32(1.0) - fx_q
    lo = min(max(-ox_p, -ox_q, 0), W)
    hi = min(max(min(W - 1 - ox_p, W - 1 - ox_q), lo), W)
    for x in range(lo):
        acc[x] = (acc[x] + abs(c_row[x] - _sample(p, x, ox_p, fx_p))) + abs(c_row[x] - _sample(q, x, ox_q, fx_q))
    n = hi - lo
    if n > 0:
        p0 = p[lo + ox_p:hi + ox_p]
        p1 = p[lo + ox_p + 1:hi + ox_p + 1]
        q0 = q[lo + ox_q:hi + ox_q]
        q1 = q[lo + ox_q + 1:hi + ox_q + 1]
        c = c_row[lo:hi]
        s = acc[lo:hi]
        for i in range(n):
            s[i] = (s[i] + abs(c[i] - (gp * p0[i] + fx_p * p1[i]))) + abs(c[i] - (gq * q0[i] + fx_q * q1[i]))
    for x in range(hi, W):
        acc[x] = (acc[x] + abs(c_row[x] - _sample(p, x, ox_p, fx_p))) + abs(c_row[x] - _sample(q, x, ox_q, fx_q))


@numba.njit(fastmath=FAST, cache=True)
def _cost_rows(gray, vu, vv, oy, fy, ox, fx, y, accs, rv):
    # _cost_row for D candidates at once (oy, fy, ox, fx: (D, N); accs: (D, W) float32; rv: (2, W)
    # float32 rows to work in): each candidate's sum adds the views in the same order, but two
    # views are taken for every candidate before the next two, so their few source rows are read
    # from memory once, not D times, and each candidate's sum is read and written once per two
    # views (add_two_shifted_row_diffs; 0.94 -> 0.82 s CPU on backgammon).
    c_row = gray[gray.shape[0] // 2, gray.shape[1] // 2, y]
    accs[:] = 0.0
    n = vu.shape[0]
    for k in range(0, n - 1, 2):
        p_img = gray[vu[k], vv[k]]
        q_img = gray[vu[k + 1], vv[k + 1]]
        for j in range(oy.shape[0]):
            p = _view_row(p_img, y, oy[j, k], fy[j, k], rv[0])
            q = _view_row(q_img, y, oy[j, k + 1], fy[j, k + 1], rv[1])
            add_two_shifted_row_diffs(accs[j], c_row, p, ox[j, k], fx[j, k], q, ox[j, k + 1], fx[j, k + 1])
    if n % 2:  # the last view of an odd number
        img = gray[vu[n - 1], vv[n - 1]]
        for j in range(oy.shape[0]):
            _add_view_row(img, c_row, y, oy[j, n - 1], fy[j, n - 1], ox[j, n - 1], fx[j, n - 1], accs[j], rv[0])


@numba.njit(parallel=True, fastmath=FAST, cache=True)
def _pixel_cost_kernel(gray, vu, vv, oy, fy, ox, fx, out):
    W = gray.shape[3]
    inv = np.float32(1.0 / vu.shape[0])
    for y in numba.prange(gray.shape[2]):
        acc = np.empty(W, dtype=np.float32)
        rv = np.empty(W, dtype=np.float32)
        _cost_row(gray, vu, vv, oy, fy, ox, fx, y, acc, rv)
        for x in range(W):
            out[y, x] = acc[x] * inv


def pixel_cost(gray: np.ndarray, disparity: float, *, offsets: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fast twin of :func:`pixel_cost_reference` (same arguments, same result to float32 rounding).

    Each view's sampling offset ``-(u - u0) d``, ``-(v - v0) d`` is split once into its integer part
    and fraction, so a pixel's cost does not depend on where the image starts: a tile with a wide
    enough halo gives the whole image's values.
    """
    offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
    indices = np.ascontiguousarray(indices, dtype=np.int64).reshape(-1, 2)
    oy, fy = split_shift(-offsets[:, 0] * float(disparity))
    ox, fx = split_shift(-offsets[:, 1] * float(disparity))
    out = np.empty(gray.shape[2:], dtype=np.float32)
    _pixel_cost_kernel(np.ascontiguousarray(gray, dtype=np.float32), indices[:, 0].copy(), indices[:, 1].copy(),
                       oy, fy, ox, fx, out)
    return out


def start_numba() -> None:
    """numba's start-up in this process (its typing and target registries, which the first cached
    kernel of a process loads, whichever it is: ~0.3-0.5 s), done by loading the smallest one."""
    _reflect(0, 1)


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


@numba.njit(cache=True)
def _row_sums(src, r, acc):
    # acc[x] = sum of src[reflect(x + k)] for k = -r..r, added in that order from 0.0 (float64); the
    # loops are swapped (window offset outer, pixels inner) so that the pixels away from the left
    # and right borders, where the mirror is the identity, are whole vectorised rows.
    w = src.shape[0]
    acc[:] = 0.0
    for k in range(-r, r + 1):
        lo = min(max(-k, 0), w)  # x + k inside the row for lo <= x < hi
        hi = max(min(w - k, w), lo)
        for x in range(lo):
            acc[x] += src[_reflect(x + k, w)]
        a = acc[lo:hi]
        b = src[lo + k:hi + k]
        for i in range(hi - lo):
            a[i] += b[i]
        for x in range(hi, w):
            acc[x] += src[_reflect(x + k, w)]


@numba.njit(cache=True)
def _column_sums(rows, y, r, h, first, col):
    # col[x] = sum of rows[reflect(y + k, h) - first, x] for k = -r..r, in that order from 0.0.
    col[:] = 0.0
    for k in range(-r, r + 1):
        src = rows[_reflect(y + k, h) - first]
        for x in range(col.shape[0]):
            col[x] += src[x]


@numba.njit(parallel=True, cache=True)
def _box_mean_kernel(image, window, out):
    h, w = image.shape
    r = window // 2
    rows = np.empty((h, w), dtype=np.float64)
    for y in numba.prange(h):
        _row_sums(image[y], r, rows[y])
    scale = 1.0 / (window * window)
    for y in numba.prange(h):
        col = np.empty(w, dtype=np.float64)
        _column_sums(rows, y, r, h, 0, col)
        dst = out[y]
        for x in range(w):
            dst[x] = col[x] * scale


@numba.njit(parallel=True, cache=True)  # no fast math here: the NaN test must stay
def _sweep_kernel(gray, vu, vv, oy, fy, ox, fx, first, window, edges, previous, best, best_index,
                  c_minus, c_plus):
    # Candidates first .. first + D - 1 of the plane sweep (oy, fy, ox, fx: (D, N), one row per
    # candidate) in bands of rows (edges), one per thread, with no barrier between candidates: a
    # band computes the pixel costs of its rows and of the window's radius around them (the same
    # values pixel_cost gives), their box mean (box_mean's sums, in its order) and keeps, per
    # pixel, the least mean, its index and its neighbours' means, as np.argmin over the volume
    # would (the first least, or the first NaN). previous: the last candidate's means.
    # Row by row, all D candidates of a row before the next row: the views' rows that a row's
    # candidates sample are nearly the same ones, so they are read from memory once per call
    # rather than once per candidate. Each candidate keeps the row sums of the window's last
    # 2r + 1 rows in a ring; an output row is summed as soon as its window's last row is in.
    H, W = gray.shape[2], gray.shape[3]
    D = oy.shape[0]
    r = window // 2
    n = 2 * r + 1
    inv = np.float32(1.0 / vu.shape[0])
    scale = 1.0 / (window * window)
    for b in numba.prange(edges.shape[0] - 1):
        lo, hi = edges[b], edges[b + 1]
        a = max(lo - r, 0)
        z = min(hi + r, H)
        cost = np.empty(W, np.float32)
        ring = np.empty((D, n, W), np.float64)
        accs = np.empty((D, W), np.float32)
        rv = np.empty((2, W), np.float32)
        col = np.empty(W, np.float64)
        for y in range(a, z):
            _cost_rows(gray, vu, vv, oy, fy, ox, fx, y, accs, rv)
            for j in range(D):
                acc = accs[j]
                for x in range(W):
                    cost[x] = acc[x] * inv
                _row_sums(cost, r, ring[j, y % n])
            # the output rows whose window ends at row y (at the last row, the last r + 1 rows)
            out_lo = max(y - r, lo)
            out_hi = min(y + 1 if y == H - 1 else y - r + 1, hi)
            for yo in range(out_lo, out_hi):
                for j in range(D):
                    index = first + j
                    col[:] = 0.0
                    for k in range(-r, r + 1):
                        src = ring[j, _reflect(yo + k, H) % n]
                        for x in range(W):
                            col[x] += src[x]
                    for x in range(W):
                        c = np.float32(col[x] * scale)
                        if best_index[yo, x] == index - 1:
                            c_plus[yo, x] = c
                        m = best[yo, x]
                        if index == 0 or c < m or (c != c and m == m):
                            best[yo, x] = c
                            best_index[yo, x] = index
                            c_minus[yo, x] = previous[yo, x]
                        previous[yo, x] = c


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
