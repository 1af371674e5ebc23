"""Matching cost of Eq. 5 and the line search of Eqs. 6-7.

For a candidate disparity ``d`` (pixels per view step, lfrig's sign, ``docs/conventions.md``) the
centre-view pixel ``(y, x)`` is compared with view ``(u, v)`` at ``(y - du * d, x - dv * d)`` where
``du = u - u0``, ``dv = v - v0`` (bilinear interpolation, edge pixels repeated outside the image).

The absolute differences of every view are summed into nine *view blocks*: block
``3 * (sign(du) + 1) + (sign(dv) + 1)``. Every visible-viewpoint set of :mod:`recon.entropy.windows`
is a union of blocks, so the per-set difference image is a sum of at most nine block images, and the
window sum over a rectangular (side) window is an O(1) lookup in its integral image. With
``beta = 1 / #w`` (Eq. 5) and a further ``1 / #Phi`` the cost is the mean absolute difference over
window pixels and visible views, comparable between windows and sets.

Each kernel has a readable reference (``*_reference``) and a compiled twin (``*_fast``); the tests
check that they agree.
"""

from __future__ import annotations

import numba
import numpy as np

from recon.entropy.windows import SET_BLOCKS, window_rect

N_BLOCKS = 9


def view_offsets(grid_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(du, dv)``: ``(U, V)`` int arrays of ``u - u0`` and ``v - v0``."""
    U, V = grid_shape
    du, dv = np.meshgrid(np.arange(U) - U // 2, np.arange(V) - V // 2, indexing="ij")
    return du, dv


def view_blocks(grid_shape: tuple[int, int]) -> np.ndarray:
    """``(U, V)`` block index ``3 * (sign(du) + 1) + (sign(dv) + 1)`` in ``0..8``."""
    du, dv = view_offsets(grid_shape)
    return (3 * (np.sign(du) + 1) + (np.sign(dv) + 1)).astype(np.int64)


def _bilinear(image: np.ndarray, y: float, x: float) -> float:
    H, W = image.shape
    y = min(max(y, 0.0), H - 1.0)
    x = min(max(x, 0.0), W - 1.0)
    y0 = min(int(np.floor(y)), H - 2) if H > 1 else 0
    x0 = min(int(np.floor(x)), W - 2) if W > 1 else 0
    fy, fx = y - y0, x - x0
    y1, x1 = min(y0 + 1, H - 1), min(x0 + 1, W - 1)
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x1])
            + fy * ((1 - fx) * image[y1, x0] + fx * image[y1, x1]))


def block_abs_diff_reference(gray: np.ndarray, disparity: float, *,
                             view_mask: np.ndarray | None = None) -> np.ndarray:
    """Per-block sums of ``|L_c(y, x) - L_uv(y - du d, x - dv d)|`` (readable reference).

    Parameters
    ----------
    gray
        ``(U, V, H, W)`` float32 light field.
    disparity
        Candidate disparity ``d`` in pixels per view step.
    view_mask
        ``(U, V)`` bool, views to include (default all).

    Returns
    -------
    ``(9, H, W)`` float32: sum over the included views of each block.
    """
    U, V, H, W = gray.shape
    du, dv = view_offsets((U, V))
    blocks = view_blocks((U, V))
    centre = gray[U // 2, V // 2]
    out = np.zeros((N_BLOCKS, H, W), np.float64)
    for u in range(U):
        for v in range(V):
            if view_mask is not None and not view_mask[u, v]:
                continue
            for y in range(H):
                for x in range(W):
                    s = _bilinear(gray[u, v], y - du[u, v] * disparity, x - dv[u, v] * disparity)
                    out[blocks[u, v], y, x] += abs(centre[y, x] - s)
    return out.astype(np.float32)


@numba.njit(cache=True, parallel=True, fastmath={"nnan", "ninf", "nsz"})  # IEEE rounding: see recon/costvolume.py
def _block_abs_diff_kernel(gray, vu, vv, vdu, vdv, vblock, disparity, out):
    # One output row at a time: every view's row is interpolated (bilinear is separable: first
    # between the two source rows, then along x with one fraction for the whole row, since the
    # shift is the same for every x) and its absolute difference added to a row accumulator per
    # block, which is written once. Clamping at the image edges as in the reference. float32
    # arithmetic throughout (8 SIMD lanes; a float64 weight made the rows float64: 29 -> 22 ms per
    # candidate on 81 views of 512x512); the weights depend only on the shift, not on where the
    # image starts, so a tile computes the same values.
    H = gray.shape[2]
    W = gray.shape[3]
    u0 = gray.shape[0] // 2
    v0 = gray.shape[1] // 2
    n_blocks = out.shape[0]
    for y in numba.prange(H):
        acc = np.zeros((n_blocks, W), np.float32)
        rv = np.empty(W, np.float32)
        centre = gray[u0, v0, y]
        for k in range(vu.shape[0]):
            img = gray[vu[k], vv[k]]
            b = vblock[k]
            sy = y - vdu[k] * disparity
            if sy < 0.0:
                sy = 0.0
            elif sy > H - 1.0:
                sy = H - 1.0
            y0 = int(np.floor(sy))
            if y0 > H - 2:
                y0 = H - 2
            if y0 < 0:
                y0 = 0
            fy = np.float32(sy - y0)  # exact in float64 (whatever the image origin), then rounded
            gy = np.float32(1.0) - fy
            y1 = min(y0 + 1, H - 1)
            for x in range(W):
                rv[x] = gy * img[y0, x] + fy * img[y1, x]
            base = -vdv[k] * disparity
            fl = np.floor(base)
            fx = base - fl
            gx = np.float32(1.0) - fx
            o = int(fl)
            row = acc[b]
            # x + o < 0: the first sample; x + o >= W - 1: the last; between, interpolated. The
            # middle run indexes slices from 0 (numba's negative-index wrap of rv[x + o] made every
            # load a gather and kept the loop scalar).
            lo = min(max(-o, 0), W)
            hi = min(max(W - 1 - o, lo), W)
            for x in range(lo):
                row[x] += abs(centre[x] - rv[0])
            n = hi - lo
            if n > 0:
                r0 = rv[lo + o:hi + o]
                r1 = rv[lo + o + 1:hi + o + 1]
                c = centre[lo:hi]
                a = row[lo:hi]
                for i in range(n):
                    a[i] += abs(c[i] - (gx * r0[i] + fx * r1[i]))
            for x in range(hi, W):
                row[x] += abs(centre[x] - rv[W - 1])
        for bb in range(n_blocks):
            for x in range(W):
                out[bb, y, x] = acc[bb, x]


def _view_lists(grid_shape, view_mask):
    du, dv = view_offsets(grid_shape)
    blocks = view_blocks(grid_shape)
    mask = np.ones(grid_shape, bool) if view_mask is None else np.asarray(view_mask, bool)
    uu, vv = np.nonzero(mask)
    return (uu.astype(np.int64), vv.astype(np.int64), du[uu, vv].astype(np.float32),
            dv[uu, vv].astype(np.float32), blocks[uu, vv])


def block_abs_diff_fast(gray: np.ndarray, disparity: float, *,
                        view_mask: np.ndarray | None = None,
                        out: np.ndarray | None = None) -> np.ndarray:
    """Compiled twin of :func:`block_abs_diff_reference` (same arguments and result)."""
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    U, V, H, W = gray.shape
    if out is None:
        out = np.empty((N_BLOCKS, H, W), np.float32)
    _block_abs_diff_kernel(gray, *_view_lists((U, V), view_mask), np.float32(disparity), out)
    return out


def set_view_counts(grid_shape: tuple[int, int], view_mask: np.ndarray | None = None) -> np.ndarray:
    """``(9,)`` number of (included) views in each visible-viewpoint set."""
    blocks = view_blocks(grid_shape)
    mask = np.ones(grid_shape, bool) if view_mask is None else np.asarray(view_mask, bool)
    per_block = np.bincount(blocks[mask], minlength=N_BLOCKS)
    return (SET_BLOCKS.astype(np.int64) @ per_block).astype(np.int64)  # (N_SHAPES,)


def integral_image(image: np.ndarray) -> np.ndarray:
    """``(H + 1, W + 1)`` float64 summed-area table with a zero first row and column."""
    out = np.zeros((image.shape[0] + 1, image.shape[1] + 1), np.float64)
    np.cumsum(np.cumsum(image, axis=0, dtype=np.float64), axis=1, out=out[1:, 1:])
    return out


def window_cost_reference(blocks_ad: np.ndarray, shape_map: np.ndarray, size_map: np.ndarray,
                          set_map: np.ndarray, set_counts: np.ndarray) -> np.ndarray:
    """Cost of Eq. 5 for one disparity with each pixel's own window and view set (reference).

    Parameters
    ----------
    blocks_ad
        ``(9, H, W)`` per-block absolute differences (:func:`block_abs_diff_reference`).
    shape_map, size_map, set_map
        ``(H, W)`` int: window shape (0 = full square, 1..8 = W1..W8), window size (odd, side of
        the square) and visible-viewpoint set (0 = all views, 1..8 = the set of W1..W8).
    set_counts
        ``(9,)`` number of views in each set (:func:`set_view_counts`).

    Returns
    -------
    ``(H, W)`` float32 mean absolute difference over the window (clipped to the image) and the set.
    """
    _, H, W = blocks_ad.shape
    out = np.zeros((H, W), np.float32)
    for y in range(H):
        for x in range(W):
            s = set_map[y, x]
            img = np.tensordot(SET_BLOCKS[s].astype(np.float32), blocks_ad, axes=1)
            y0, y1, x0, x1 = window_rect(shape_map[y, x], size_map[y, x])
            ya, yb = max(y + y0, 0), min(y + y1, H - 1)
            xa, xb = max(x + x0, 0), min(x + x1, W - 1)
            patch = img[ya:yb + 1, xa:xb + 1]
            out[y, x] = patch.sum() / (patch.size * max(set_counts[s], 1))
    return out


@numba.njit(cache=True, parallel=True)
def _window_cost_kernel(integrals, set_index, rects, set_counts, out):
    H = out.shape[0]
    W = out.shape[1]
    for y in numba.prange(H):
        for x in range(W):
            k = set_index[y, x]
            ya = max(y + rects[y, x, 0], 0)
            yb = min(y + rects[y, x, 1], H - 1) + 1
            xa = max(x + rects[y, x, 2], 0)
            xb = min(x + rects[y, x, 3], W - 1) + 1
            ii = integrals[k]
            total = (ii[yb, xb] - ii[ya, xb] - ii[yb, xa] + ii[ya, xa]) * FIXED_INV
            out[y, x] = total / ((yb - ya) * (xb - xa) * set_counts[y, x])


#: Window sums are exact integer sums: each pixel's set value is rounded to a multiple of
#: ``1 / FIXED_POINT`` (3.7e-9 grey levels of ``[0, 1]``) and the summed-area tables are int64, so a
#: window's sum does not depend on where the table starts (a float table's rounding does: a tile
#: would round differently from the whole image and flip near-ties of the line search). Holds
#: without overflow up to 2^63 / 2^28 / 256 views = 2^27 pixels (134 Mpx) per image or tile.
FIXED_POINT = float(2 ** 28)
FIXED_INV = 1.0 / FIXED_POINT


@numba.njit(cache=True, parallel=True)
def _set_integrals_kernel(blocks_ad, set_blocks, n_bands, out):
    # out[s] = summed-area table of round(FIXED_POINT * sum of blocks_ad over the blocks of set s),
    # int64, zero first row/column; set_blocks[s] lists those blocks ascending (-1 padded) and
    # they are added in that order (float64, from 0.0). The rows are cut into n_bands bands (one
    # per thread); within a band, row by row and set by set, the set's row is added up along x
    # (vectorisable), rounded, summed along x and onto the row above while it is in cache; then the
    # bands below the first get the total of the bands above them added (integers: the same table
    # whatever the banding).
    S = set_blocks.shape[0]
    B, H, W = blocks_ad.shape
    for s in range(S):
        for x in range(W + 1):
            out[s, 0, x] = 0
    for band in numba.prange(n_bands):
        y0 = band * H // n_bands
        y1 = (band + 1) * H // n_bands
        v = np.empty(W, np.float64)
        fixed = np.empty(W, np.int64)
        for y in range(y0, y1):
            for s in range(S):
                for x in range(W):
                    v[x] = 0.0
                for t in range(set_blocks.shape[1]):
                    b = set_blocks[s, t]
                    if b < 0:
                        break
                    row_b = blocks_ad[b, y]
                    for x in range(W):
                        v[x] += row_b[x]
                for x in range(W):  # rounded apart from the running sum: this loop vectorises
                    fixed[x] = np.int64(np.floor(v[x] * FIXED_POINT + 0.5))
                cur = out[s, y + 1]
                cur[0] = 0
                acc = np.int64(0)
                if y > y0:
                    prev = out[s, y]
                    for x in range(W):
                        acc += fixed[x]
                        cur[x + 1] = acc + prev[x + 1]
                else:
                    for x in range(W):
                        acc += fixed[x]
                        cur[x + 1] = acc
    if n_bands > 1:
        carry = np.zeros((n_bands, S, W + 1), np.int64)  # total of the bands above each band
        for band in range(1, n_bands):
            last = band * H // n_bands  # table row of the last image row of the band above
            for s in range(S):
                for x in range(W + 1):
                    carry[band, s, x] = carry[band - 1, s, x] + out[s, last, x]
        for band in numba.prange(1, n_bands):
            y0 = band * H // n_bands
            y1 = (band + 1) * H // n_bands
            for s in range(S):
                c = carry[band, s]
                for y in range(y0 + 1, y1 + 1):
                    row = out[s, y]
                    for x in range(W + 1):
                        row[x] += c[x]


def _set_block_lists(sets: np.ndarray) -> np.ndarray:
    """``(len(sets), 9)`` int64: the blocks of each set ascending, padded with -1."""
    table = np.full((len(sets), N_BLOCKS), -1, np.int64)
    for i, s in enumerate(sets):
        members = np.nonzero(SET_BLOCKS[s])[0]
        table[i, :len(members)] = members
    return table


def set_integrals_reference(blocks_ad: np.ndarray, sets: np.ndarray) -> np.ndarray:
    """Reference of :func:`set_integrals`: each set's image (its blocks added in ascending order,
    float64), rounded to ``1 / FIXED_POINT`` and summed into an int64 table."""
    _, H, W = blocks_ad.shape
    out = np.zeros((len(sets), H + 1, W + 1), np.int64)
    for i, members in enumerate(_set_block_lists(np.asarray(sets))):
        v = np.zeros((H, W), np.float64)
        for b in members[members >= 0]:
            v += blocks_ad[b]
        fixed = np.floor(v * FIXED_POINT + 0.5).astype(np.int64)
        out[i, 1:, 1:] = np.cumsum(np.cumsum(fixed, axis=0), axis=1)
    return out


def set_integrals(blocks_ad: np.ndarray, sets: np.ndarray,
                  out: np.ndarray | None = None) -> np.ndarray:
    """``(S, H + 1, W + 1)`` int64 summed-area tables of the view-set images ``sets`` (0..8), in
    units of ``1 / FIXED_POINT`` (see :data:`FIXED_POINT`)."""
    _, H, W = blocks_ad.shape
    if out is None:
        out = np.empty((len(sets), H + 1, W + 1), np.int64)
    n_bands = max(1, min(numba.get_num_threads(), H))
    _set_integrals_kernel(blocks_ad, _set_block_lists(np.asarray(sets)), n_bands, out)
    return out


class WindowCost:
    """Fast evaluation of Eq. 5 for per-pixel windows and view sets, one disparity at a time.

    Build once per window assignment, then call with each ``(9, H, W)`` block image.
    """

    def __init__(self, shape_map: np.ndarray, size_map: np.ndarray, set_map: np.ndarray,
                 set_counts: np.ndarray) -> None:
        H, W = shape_map.shape
        rects = np.empty((H, W, 4), np.int64)
        for shape in np.unique(shape_map):
            for size in np.unique(size_map[shape_map == shape]):
                sel = (shape_map == shape) & (size_map == size)
                rects[sel] = window_rect(int(shape), int(size))
        self.rects = rects
        self.sets = np.unique(set_map)
        lookup = np.full(SET_BLOCKS.shape[0], -1, np.int64)
        lookup[self.sets] = np.arange(len(self.sets))
        self.set_index = lookup[set_map]
        self.pixel_counts = set_counts[set_map].astype(np.float64)
        self._integrals = None

    def __call__(self, blocks_ad: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        _, H, W = blocks_ad.shape
        self._integrals = set_integrals(blocks_ad, self.sets, out=self._integrals)
        if out is None:
            out = np.empty((H, W), np.float32)
        _window_cost_kernel(self._integrals, self.set_index, self.rects, self.pixel_counts, out)
        return out


def min_window_cost_reference(integrals: np.ndarray, window_set: np.ndarray, rects: np.ndarray,
                              counts: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32: each pixel's least mean absolute difference over its allowed windows
    (reference of the kernel behind :func:`min_window_line_search`).

    ``integrals`` ``(S, H + 1, W + 1)`` int64 from :func:`set_integrals`; window ``k`` is the
    rectangle ``rects[k]`` (``y0, y1, x0, x1`` offsets, clipped to the image) matched over table
    ``window_set[k]`` with ``counts[k]`` views; ``allowed`` ``(H, W, K)`` or ``(1, 1, K)`` bool.
    A NaN cost never wins; a pixel with no finite cost gets 1e300 (inf in float32)."""
    S, H1, W1 = integrals.shape
    H, W = H1 - 1, W1 - 1
    y, x = np.arange(H)[:, None], np.arange(W)[None, :]
    best = np.full((H, W), 1e300)
    for k in range(len(rects)):
        ya = np.maximum(y + rects[k, 0], 0)
        yb = np.minimum(y + rects[k, 1], H - 1) + 1
        xa = np.maximum(x + rects[k, 2], 0)
        xb = np.minimum(x + rects[k, 3], W - 1) + 1
        ii = integrals[window_set[k]]
        total = (ii[yb, xb] - ii[ya, xb] - ii[yb, xa] + ii[ya, xa]) * FIXED_INV
        c = total / ((yb - ya) * (xb - xa) * counts[k])
        ok = np.broadcast_to(allowed[..., k], (H, W))
        best = np.where(ok & (c < best), c, best)
    return best.astype(np.float32)


@numba.njit(cache=True, parallel=True)
def _min_window_cost_kernel(integrals, window_set, rects, counts, allowed, out):
    # allowed: (H, W, K) bool, or (1, 1, K) for every pixel alike. Each pixel's least cost over its
    # allowed windows (NaN costs never win; 1e300 if none is finite). Within a row, window by
    # window along x, so that each summed-area table is read along its rows (not all K tables at
    # every pixel); the least of the same values, so the same map in any order.
    H = out.shape[0]
    W = out.shape[1]
    per_pixel = allowed.shape[0] > 1
    for y in numba.prange(H):
        best = np.full(W, 1e300)
        for k in range(rects.shape[0]):
            ya = max(y + rects[k, 0], 0)
            yb = min(y + rects[k, 1], H - 1) + 1
            ii = integrals[window_set[k]]
            top = ii[ya]
            bottom = ii[yb]
            ck = counts[k]
            if not per_pixel and not allowed[0, 0, k]:
                continue
            ra = rects[k, 2]
            rb = rects[k, 3]
            # [lo, hi): the window's columns inside the image; there the loop indexes slices from
            # 0 and vectorises (numba's negative-index wrap of top[x + ra] made loads gathers)
            lo = min(max(-ra, 0), W)
            hi = min(max(W - 1 - rb, lo), W)
            for x in range(W):
                if lo <= x < hi:
                    continue
                if per_pixel and not allowed[y, x, k]:
                    continue
                xa = max(x + ra, 0)
                xb = min(x + rb, W - 1) + 1
                total = (bottom[xb] - top[xb] - bottom[xa] + top[xa]) * FIXED_INV
                c = total / ((yb - ya) * (xb - xa) * ck)
                if c < best[x]:
                    best[x] = c
            n = hi - lo
            if n > 0:
                b1 = bottom[lo + rb + 1:hi + rb + 1]
                t1 = top[lo + rb + 1:hi + rb + 1]
                b0 = bottom[lo + ra:hi + ra]
                t0 = top[lo + ra:hi + ra]
                bs = best[lo:hi]
                denom = (yb - ya) * (rb - ra + 1) * ck
                if per_pixel:
                    al = allowed[y, lo:hi, k]
                    for i in range(n):
                        c = (b1[i] - t1[i] - b0[i] + t0[i]) * FIXED_INV / denom
                        bs[i] = c if al[i] and c < bs[i] else bs[i]
                else:
                    for i in range(n):
                        c = (b1[i] - t1[i] - b0[i] + t0[i]) * FIXED_INV / denom
                        bs[i] = c if c < bs[i] else bs[i]
        for x in range(W):
            out[y, x] = best[x]


def cost_ambiguity_reference(costs: np.ndarray, delta: float) -> np.ndarray:
    """``(H, W)`` int32: how many of the ``D`` candidates of a ``(D, H, W)`` cost volume come
    within ``delta`` of the pixel's least cost. A few (a narrow valley) where the matching tells
    disparities apart; many (a plateau) where it has no information, e.g. inside a textureless
    patch, where the window matches itself at every small shift. Reference of :func:`cost_ambiguity`."""
    D, H = costs.shape[:2]
    out = np.empty(costs.shape[1:], np.int32)
    for y in range(0, H, 32):  # a few rows at a time: no (D, H, W) boolean temporary
        c = costs[:, y:y + 32]
        best = c.min(axis=0)
        out[y:y + 32] = np.count_nonzero(c <= best[None] + np.float32(delta), axis=0)
    return out


@numba.njit(cache=True, parallel=True)
def _cost_ambiguity_kernel(costs, delta, out):
    # Twin of cost_ambiguity_reference: the float32 least cost of each pixel (NaN if any cost is
    # NaN, as ndarray.min), then how many costs are <= least + delta (float32 sum).
    D, H, W = costs.shape
    for y in numba.prange(H):
        best = np.empty(W, np.float32)
        for x in range(W):
            best[x] = costs[0, y, x]
        for d in range(1, D):
            for x in range(W):
                c = costs[d, y, x]
                if c != c or c < best[x]:
                    if best[x] == best[x]:
                        best[x] = c
        for x in range(W):
            best[x] = best[x] + delta
            out[y, x] = 0
        for d in range(D):
            for x in range(W):
                if costs[d, y, x] <= best[x]:
                    out[y, x] += 1


def cost_ambiguity(costs: np.ndarray, delta: float) -> np.ndarray:
    """``(H, W)`` int32: how many of the ``D`` candidates of a ``(D, H, W)`` cost volume come
    within ``delta`` of the pixel's least cost. A few (a narrow valley) where the matching tells
    disparities apart; many (a plateau) where it has no information, e.g. inside a textureless
    patch, where the window matches itself at every small shift. Compiled twin of
    :func:`cost_ambiguity_reference` (same map)."""
    if costs.dtype != np.float32 or not costs.flags.c_contiguous or costs.ndim != 3:
        return cost_ambiguity_reference(costs, delta)
    out = np.empty(costs.shape[1:], np.int32)
    _cost_ambiguity_kernel(costs, np.float32(delta), out)
    return out


def min_window_line_search(gray: np.ndarray, candidates: np.ndarray, *,
                           windows: list[tuple[int, int, int]],
                           view_mask: np.ndarray | None = None,
                           ambiguity_delta: float | None = None, progress=None,
                           allowed: np.ndarray | None = None):
    """Line search whose cost at each candidate is the least over several windows.

    ``windows`` lists ``(shape, size, view_set)``; at every candidate disparity each pixel takes the
    smallest mean absolute difference over them (a "shiftable window": near an edge one of the side
    windows with its visible views lies on the pixel's own surface); with ``allowed`` (``(H, W, K)``
    bool, every pixel allowed at least one window) over the windows allowed at the pixel only. Returns ``(disparity, cost)``,
    ``(H, W)`` float32, with the parabolic sub-step refinement of :func:`subpixel_argmin`, and
    with ``ambiguity_delta`` also :func:`cost_ambiguity` of the cost curves. ``progress(fraction)``
    is called after each candidate.
    """
    U, V, H, W = gray.shape
    counts = set_view_counts((U, V), view_mask)
    sets = np.unique([w[2] for w in windows])
    lookup = {int(s): i for i, s in enumerate(sets)}
    window_set = np.array([lookup[w[2]] for w in windows], np.int64)
    rects = np.array([window_rect(w[0], w[1]) for w in windows], np.int64)
    wcounts = np.array([counts[w[2]] for w in windows], np.float64)
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    buf = np.empty((N_BLOCKS, H, W), np.float32)
    integrals = None
    if allowed is None:
        allowed = np.ones((1, 1, len(windows)), np.bool_)
    elif allowed.shape != (H, W, len(windows)) or not allowed.any(axis=2).all():
        raise ValueError(f"allowed must be ({H}, {W}, {len(windows)}) bool with a window at every pixel")
    allowed = np.ascontiguousarray(allowed, dtype=np.bool_)
    costs = np.empty((len(candidates), H, W), np.float32)
    for i, d in enumerate(candidates):
        block_abs_diff_fast(gray, float(d), view_mask=view_mask, out=buf)
        integrals = set_integrals(buf, sets, out=integrals)
        _min_window_cost_kernel(integrals, window_set, rects, wcounts, allowed, costs[i])
        if progress is not None:
            progress((i + 1) / len(candidates))
    disparity, best = subpixel_argmin(costs, candidates)
    if ambiguity_delta is not None:
        return disparity, best, cost_ambiguity(costs, ambiguity_delta)
    return disparity, best


@numba.njit(cache=True, parallel=True)
def _joint_cost_pixelwise(integrals, pixel_set, rects, window_shape, counts, starts, ks, pens, scale,
                          order, out, best, best_k):
    # The readable twin of _joint_cost_kernel (the same maps bit for bit; the search used it until
    # issue #14's fourth session): pixel by pixel, each pixel's allowed windows
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


@numba.njit(cache=True, inline="always")
def _joint_edge_pixel(x, k, ya, yb, ra, rb, W, iya, iyb, cnt, scale, pen, every, want, occluded,
                      c_best, k_best):
    # _joint_cost_kernel at a pixel whose window the image's left or right edge clips.
    xa = max(x + ra, 0)
    xb = min(x + rb, W - 1) + 1
    total = (iyb[xb] - iya[xb] - iyb[xa] + iya[xa]) * FIXED_INV
    c = scale * total / ((yb - ya) * (xb - xa) * cnt) + pen[x]
    if (every or occluded[x] == want) and c < c_best[x]:
        c_best[x] = c
        k_best[x] = k


@numba.njit(cache=True, parallel=True)
def _joint_cost_kernel(integrals, pixel_set, rects, window_shape, counts, penalty, run_start,
                       runs, scale, order, out, best, best_k):
    # Window-major twin of _joint_cost_pixelwise (the same float64 arithmetic for every pixel and
    # window, windows in ascending order, strict <: the same maps bit for bit). For one row and
    # one window the four corners of every pixel's window lie on two rows of one integral table,
    # contiguous in x: away from the image's left and right edges the loop over x vectorises (the
    # slices index from 0, so that numba's negative-index wrap does not turn loads into gathers).
    # penalty (K, H, W): inf where the window is not offered; runs[run_start[i]:run_start[i + 1]]
    # with i = (k * H + y) * 2 + pass: column runs [lo, hi) covering the pixels of row y that offer
    # window k, matched over all views (pass 0; every pixel for a square) or over the window's
    # visible set (pass 1: occluded pixels, shaped windows). See window_major_penalty.
    K, H, W = penalty.shape
    for jr in numba.prange(H):
        y = order[jr]
        c_best = np.full(W, 1e300)
        k_best = np.full(W, -1, np.int64)
        occluded = pixel_set[y]
        for k in range(K):
            ya = max(y + rects[k, 0], 0)
            yb = min(y + rects[k, 1], H - 1) + 1
            ra = rects[k, 2]
            rb = rects[k, 3]
            pen = penalty[k, y]
            for r in range(run_start[(k * H + y) * 2], run_start[(k * H + y) * 2 + 2]):
                x0 = runs[r, 0]
                x1 = runs[r, 1]
                pas = 1 if r >= run_start[(k * H + y) * 2 + 1] else 0
                s = window_shape[k] if pas == 1 else 0
                every = window_shape[k] == 0  # a square: the same set for every pixel
                want = pas == 1  # otherwise only pixels whose pixel_set is this pass's
                ii = integrals[s]
                iya = ii[ya]
                iyb = ii[yb]
                cnt = counts[s]
                lo = min(max(x0, -ra), x1)  # [lo, hi): the window's columns inside the image
                hi = max(min(x1, W - 1 - rb), lo)
                for x in range(x0, lo):  # left edge: the window clipped
                    _joint_edge_pixel(x, k, ya, yb, ra, rb, W, iya, iyb, cnt, scale, pen, every,
                                      want, occluded, c_best, k_best)
                if hi > lo:
                    n = hi - lo
                    b1 = iyb[lo + rb + 1:hi + rb + 1]
                    a1 = iya[lo + rb + 1:hi + rb + 1]
                    b0 = iyb[lo + ra:hi + ra]
                    a0 = iya[lo + ra:hi + ra]
                    pn = pen[lo:hi]
                    oc = occluded[lo:hi]
                    cb = c_best[lo:hi]
                    kb = k_best[lo:hi]
                    denom = (yb - ya) * (rb - ra + 1) * cnt
                    for i in range(n):
                        total = (b1[i] - a1[i] - b0[i] + a0[i]) * FIXED_INV
                        c = scale * total / denom + pn[i]
                        better = (every | (oc[i] == want)) & (c < cb[i])
                        cb[i] = c if better else cb[i]
                        kb[i] = k if better else kb[i]
                for x in range(hi, x1):  # right edge
                    _joint_edge_pixel(x, k, ya, yb, ra, rb, W, iya, iyb, cnt, scale, pen, every,
                                      want, occluded, c_best, k_best)
        for x in range(W):
            c32 = np.float32(c_best[x])
            out[y, x] = c32
            if c32 < best[y, x]:
                best[y, x] = c32
                best_k[y, x] = k_best[x]


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


def joint_line_search_reference(gray: np.ndarray, candidates: np.ndarray, *,
                                windows: list[tuple[int, int]], penalty: np.ndarray,
                                use_shape_set: np.ndarray, intensity_scale: float):
    """Readable reference of :func:`joint_line_search` (same arguments; no sub-step refinement):
    ``(candidate index, objective, window index)`` per pixel, ``(H, W)`` each."""
    U, V, H, W = gray.shape
    counts = set_view_counts((U, V))
    best = np.full((H, W), np.inf)
    best_i = np.zeros((H, W), np.int64)
    best_k = np.full((H, W), -1, np.int64)
    for i, d in enumerate(candidates):
        blocks = block_abs_diff_reference(gray, float(d))
        for y in range(H):
            for x in range(W):
                for k, (shape, size) in enumerate(windows):
                    if not np.isfinite(penalty[y, x, k]):
                        continue
                    s = shape if use_shape_set[y, x] else 0
                    img = np.tensordot(SET_BLOCKS[s].astype(np.float64), blocks, axes=1)
                    y0, y1, x0, x1 = window_rect(shape, size)
                    patch = img[max(y + y0, 0):min(y + y1, H - 1) + 1,
                                max(x + x0, 0):min(x + x1, W - 1) + 1]
                    c = intensity_scale * patch.sum() / (patch.size * counts[s]) + penalty[y, x, k]
                    if c < best[y, x]:
                        best[y, x], best_i[y, x], best_k[y, x] = c, i, k
    return best_i, best.astype(np.float32), best_k


def joint_line_search(gray: np.ndarray, candidates: np.ndarray, *,
                      windows: list[tuple[int, int]], penalty: np.ndarray,
                      use_shape_set: np.ndarray, intensity_scale: float,
                      view_mask: np.ndarray | None = None, ambiguity_delta: float = 0.0,
                      progress=None):
    """Joint minimisation of Eq. 7 over disparity and window.

    For every pixel and candidate ``d`` the objective is
    ``min_w  intensity_scale * cost(d, w, Phi_w) + penalty[w]`` with ``penalty = -lambda * E(w)``
    (``inf`` for windows not allowed); the disparity is the arg-min over ``d`` (parabola-refined on
    that lower envelope) and the window the minimiser at that ``d``.

    Parameters
    ----------
    windows
        ``K`` pairs ``(shape, size)``.
    penalty
        ``(H, W, K)`` float32 (laid out window by window first, :func:`window_major_penalty`; pass
        a temporary to let the volume go before the search).
    use_shape_set
        ``(H, W)`` bool: match over the window shape's visible set (occluded pixels) instead of all
        views.
    intensity_scale
        Factor on the mean absolute difference of ``[0, 1]`` grey values (255: 8-bit levels).
    ambiguity_delta
        Tolerance of :func:`cost_ambiguity` (objective units).
    progress
        Called as ``progress(fraction)`` after each candidate.

    Returns
    -------
    ``(disparity, objective, window_index, ambiguity)``: ``(H, W)`` float32, float32, int64 and
    int32 :func:`cost_ambiguity` of the objective's curve over the candidates.
    """
    U, V, H, W = gray.shape
    counts = set_view_counts((U, V), view_mask).astype(np.float64)
    rects = np.array([window_rect(s, z) for s, z in windows], np.int64)
    shapes = np.array([s for s, _ in windows], np.int64)
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    pixel_set = np.ascontiguousarray(use_shape_set, dtype=np.bool_)
    penalty, run_start, runs = window_major_penalty(penalty, pixel_set, shapes)  # the caller's (H, W, K)
    # volume is freed here when it passed a temporary
    buf = np.empty((N_BLOCKS, H, W), np.float32)
    integrals = None
    all_sets = np.arange(SET_BLOCKS.shape[0])
    costs = np.empty((len(candidates), H, W), np.float32)
    least = np.full((H, W), np.inf, np.float32)
    order = row_order(H)
    window_index = np.full((H, W), -1, np.int64)
    for i, d in enumerate(candidates):
        block_abs_diff_fast(gray, float(d), view_mask=view_mask, out=buf)
        integrals = set_integrals(buf, all_sets, out=integrals)
        _joint_cost_kernel(integrals, pixel_set, rects, shapes, counts, penalty, run_start, runs,
                           float(intensity_scale), order, costs[i], least, window_index)
        if progress is not None:
            progress((i + 1) / len(candidates))
    disparity, best = subpixel_argmin(costs, candidates)
    return disparity, best, window_index, cost_ambiguity(costs, ambiguity_delta)


def disparity_candidates(d_min: float, d_max: float, step: float) -> np.ndarray:
    """Evenly spaced candidates from ``d_min`` to at least ``d_max`` (float64)."""
    n = int(np.ceil((d_max - d_min) / step - 1e-9)) + 1
    return d_min + step * np.arange(n)


def line_search(gray: np.ndarray, candidates: np.ndarray, *, shape_map: np.ndarray,
                size_map: np.ndarray, set_map: np.ndarray, view_mask: np.ndarray | None = None,
                return_costs: bool = False, progress=None):
    """Minimise Eq. 5 over the candidates per pixel, with parabolic sub-step refinement.

    Returns ``(disparity, min_cost)`` as ``(H, W)`` float32 (and the ``(D, H, W)`` cost volume when
    ``return_costs``); ``progress(fraction)`` is called after each candidate. The parabola through the minimum and its two neighbours moves the estimate by
    at most half a step; minima at either end of the range are not refined.
    """
    U, V, H, W = gray.shape
    counts = set_view_counts((U, V), view_mask)
    cost_of = WindowCost(shape_map, size_map, set_map, counts)
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    buf = np.empty((N_BLOCKS, H, W), np.float32)
    costs = np.empty((len(candidates), H, W), np.float32)
    for i, d in enumerate(candidates):
        block_abs_diff_fast(gray, float(d), view_mask=view_mask, out=buf)
        cost_of(buf, out=costs[i])
        if progress is not None:
            progress((i + 1) / len(candidates))
    disparity, best = subpixel_argmin(costs, candidates)
    if return_costs:
        return disparity, best, costs
    return disparity, best


def subpixel_argmin_reference(costs: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel arg-min of a ``(D, H, W)`` cost volume refined by a parabola; ``(H, W)`` float32
    (reference of :func:`subpixel_argmin`)."""
    D = costs.shape[0]
    k = np.argmin(costs, axis=0)
    c0 = np.take_along_axis(costs, k[None], 0)[0].astype(np.float64)
    km, kp = np.clip(k - 1, 0, D - 1), np.clip(k + 1, 0, D - 1)
    cm = np.take_along_axis(costs, km[None], 0)[0].astype(np.float64)
    cp = np.take_along_axis(costs, kp[None], 0)[0].astype(np.float64)
    denom = cm - 2 * c0 + cp
    inner = (k > 0) & (k < D - 1) & (denom > 0)
    offset = np.where(inner, 0.5 * (cm - cp) / np.where(denom > 0, denom, 1.0), 0.0)
    offset = np.clip(offset, -0.5, 0.5)
    step = candidates[1] - candidates[0] if D > 1 else 0.0
    disparity = candidates[k] + offset * step
    return disparity.astype(np.float32), c0.astype(np.float32)


@numba.njit(cache=True, parallel=True)
def _subpixel_argmin_kernel(costs, candidates, step, disparity, best_out):
    # Twin of subpixel_argmin_reference, rows in parallel, candidates outer within a row so the
    # volume is read contiguously. Arg-min as np.argmin: the first minimum, the first NaN if any.
    D, H, W = costs.shape
    for y in numba.prange(H):
        kk = np.zeros(W, np.int64)
        best = np.empty(W, np.float32)
        nan = np.zeros(W, np.bool_)
        for x in range(W):
            best[x] = costs[0, y, x]
            nan[x] = costs[0, y, x] != costs[0, y, x]
        for d in range(1, D):
            for x in range(W):
                c = costs[d, y, x]
                if nan[x]:
                    continue
                if c != c:
                    nan[x] = True
                    kk[x] = d
                    best[x] = c
                elif c < best[x]:
                    best[x] = c
                    kk[x] = d
        for x in range(W):
            k = kk[x]
            c0 = np.float64(costs[k, y, x])
            cm = np.float64(costs[max(k - 1, 0), y, x])
            cp = np.float64(costs[min(k + 1, D - 1), y, x])
            denom = cm - 2 * c0 + cp
            offset = 0.0
            if k > 0 and k < D - 1 and denom > 0:
                offset = 0.5 * (cm - cp) / denom
            if offset < -0.5:
                offset = -0.5
            elif offset > 0.5:
                offset = 0.5
            disparity[y, x] = np.float32(np.float64(candidates[k]) + offset * step)
            best_out[y, x] = np.float32(c0)


def subpixel_argmin(costs: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel arg-min of a ``(D, H, W)`` cost volume refined by a parabola: ``(disparity, cost
    at the arg-min)``, ``(H, W)`` float32 each. The arg-min is the first least candidate (the first
    NaN if any, as ``np.argmin``); the parabola through it and its two neighbours moves it by at
    most half a step (not at the ends of the range, nor where the curve is not convex there).
    Compiled twin of :func:`subpixel_argmin_reference` (the same float64 arithmetic, same maps)."""
    costs = np.asarray(costs)
    if costs.dtype != np.float32 or not costs.flags.c_contiguous or costs.ndim != 3:
        return subpixel_argmin_reference(costs, candidates)
    D, H, W = costs.shape
    candidates = np.asarray(candidates)
    step = float(candidates[1] - candidates[0]) if D > 1 else 0.0
    disparity = np.empty((H, W), np.float32)
    best = np.empty((H, W), np.float32)
    _subpixel_argmin_kernel(costs, np.ascontiguousarray(candidates, np.float64), step, disparity, best)
    return disparity, best
