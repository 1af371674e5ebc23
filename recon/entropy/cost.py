"""The matching cost of Eq. 5 at one candidate disparity, and what a curve of such costs says.

For a candidate disparity ``d`` (pixels per view step, lfrig's sign, ``docs/conventions.md``) the
centre-view pixel ``(y, x)`` is compared with view ``(u, v)`` at ``(y - du * d, x - dv * d)`` where
``du = u - u0``, ``dv = v - v0`` (bilinear interpolation, edge pixels repeated outside the image).

The absolute differences of every view are summed into nine *view blocks*: block
``3 * (sign(du) + 1) + (sign(dv) + 1)``. Every visible-viewpoint set of :mod:`recon.entropy.windows`
is a union of blocks, so the per-set difference image is a sum of at most nine block images, and the
window sum over a rectangular (side) window is an O(1) lookup in its integral image. With
``beta = 1 / #w`` (Eq. 5) and a further ``1 / #Phi`` the cost is the mean absolute difference over
window pixels and visible views, comparable between windows and sets.

Twins follow the rule of :mod:`recon.entropy`: ``name`` compiled, ``name_reference`` readable.
"""

from __future__ import annotations

from functools import lru_cache

from recon.jit import numba
import numpy as np

from recon.costvolume import add_shifted_row_diff, add_two_shifted_row_diffs
from recon.entropy.windows import SET_BLOCKS, window_rect
from recon.native import call, chosen, thread_count

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


@numba.njit(cache=True, fastmath={"nnan", "ninf", "nsz"})  # IEEE rounding: see recon/costvolume.py
def _view_row(img, sy, rv):
    # The row of one view (img, (H, W)) at sy (float64), blended from its two source rows with one
    # fraction for the whole row into rv ((W,) float32; bilinear is separable: the caller samples
    # this row along x with one fraction, since the shift is the same for every x). Clamping at
    # the image edges as in the reference. float32 arithmetic (8 SIMD lanes; a float64 weight made
    # the rows float64: 29 -> 22 ms per candidate on 81 views of 512x512); the weights depend only
    # on the shift, not on where the image starts, so a tile computes the same values.
    H, W = img.shape
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
    return rv


@numba.njit(cache=True, fastmath={"nnan", "ninf", "nsz"})
def _block_view_rows(gray, vu, vv, vdu, vdv, vblock, disparity, y, acc, rv, k):
    # Rows y, y + 1, ... of view k's block, added into acc (rows, n_blocks, W) float32: the view's
    # row (_view_row) sampled along x and its absolute difference added to the row of its block,
    # with view k + 1 in the same pass where it is in the same block (add_two_shifted_row_diffs:
    # each block's sum adds its views in their order, the same bits as one at a time; view_lists
    # puts each block's views together). A view gives all the rows before the next view: its
    # source rows are read in one run. rv: (2, W) float32 scratch. Returns the next view's index.
    U, V = gray.shape[0], gray.shape[1]
    n = vu.shape[0]
    base_p = -vdv[k] * disparity
    fl_p = np.floor(base_p)
    two = k + 1 < n and vblock[k + 1] == vblock[k]
    m = k + 1 if two else k
    base_q = -vdv[m] * disparity
    fl_q = np.floor(base_q)
    for j in range(acc.shape[0]):
        centre = gray[U // 2, V // 2, y + j]
        p = _view_row(gray[vu[k], vv[k]], (y + j) - vdu[k] * disparity, rv[0])
        if two:
            q = _view_row(gray[vu[m], vv[m]], (y + j) - vdu[m] * disparity, rv[1])
            add_two_shifted_row_diffs(acc[j, vblock[k]], centre, p, int(fl_p), base_p - fl_p,
                                      q, int(fl_q), base_q - fl_q)
        else:
            add_shifted_row_diff(acc[j, vblock[k]], centre, p, int(fl_p), base_p - fl_p)
    return m + 1


@numba.njit(cache=True)
def _block_rows(gray, vu, vv, vdu, vdv, vblock, disparity, y, acc, rv):
    # Rows y, y + 1, ... of every block image, added into acc (rows, n_blocks, W) float32 (zeroed
    # by the caller), view by view (_block_view_rows). rv: (2, W) float32 scratch.
    k = 0
    while k < vu.shape[0]:
        k = _block_view_rows(gray, vu, vv, vdu, vdv, vblock, disparity, y, acc, rv, k)


@numba.njit(cache=True, parallel=True)
def _block_abs_diff_kernel(gray, vu, vv, vdu, vdv, vblock, disparity, out):
    # One output row at a time (_block_rows), written once.
    H = gray.shape[2]
    W = gray.shape[3]
    n_blocks = out.shape[0]
    for y in numba.prange(H):
        acc = np.zeros((1, n_blocks, W), np.float32)
        rv = np.empty((2, W), np.float32)
        _block_rows(gray, vu, vv, vdu, vdv, vblock, disparity, y, acc, rv)
        for bb in range(n_blocks):
            for x in range(W):
                out[bb, y, x] = acc[0, bb, x]


def view_lists(grid_shape, view_mask):
    # (u, v, du, dv, block) of the included views, block by block, each block's views in grid order
    # (the order its sum adds them in; _block_rows takes a block's views two at a time).
    du, dv = view_offsets(grid_shape)
    blocks = view_blocks(grid_shape)
    mask = np.ones(grid_shape, bool) if view_mask is None else np.asarray(view_mask, bool)
    uu, vv = np.nonzero(mask)
    by_block = np.argsort(blocks[uu, vv], kind="stable")
    uu, vv = uu[by_block], vv[by_block]
    return (uu.astype(np.int64), vv.astype(np.int64), du[uu, vv].astype(np.float32),
            dv[uu, vv].astype(np.float32), blocks[uu, vv])


def block_abs_diff(gray: np.ndarray, disparity: float, *,
                        view_mask: np.ndarray | None = None,
                        out: np.ndarray | None = None) -> np.ndarray:
    """Compiled twin of :func:`block_abs_diff_reference` (same arguments and result)."""
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    U, V, H, W = gray.shape
    if out is None:
        out = np.empty((N_BLOCKS, H, W), np.float32)
    _block_abs_diff_kernel(gray, *view_lists((U, V), view_mask), np.float32(disparity), out)
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

#: Exact ``float64 <-> int64`` conversions that vectorise (AVX2 has no vector instruction for
#: them): for an integer ``t`` with ``|t| < 2^51``, the bits of ``MAGIC_FLOAT + t`` (1.5 * 2^52,
#: whose ulp is 1) are ``MAGIC_BITS + t``.
MAGIC_FLOAT = 6755399441055744.0
MAGIC_BITS = np.int64(0x4338000000000000)
MAGIC_LIMIT = 2 ** 51
#: Set values (``[0, 1]`` grey units summed over views) whose fixed-point value is below ``MAGIC_LIMIT``.
FIXED_LIMIT = float(MAGIC_LIMIT // 2 ** 28 - 1)


@numba.njit(cache=True)
def _set_sum(rows, set_blocks, set_from, s, sums):
    # sums[s] = set s's row from the block rows rows (9, W): its blocks added in ascending order
    # (float64, from 0.0; set_blocks[s] lists them, -1 padded), continuing the sum of set_from[s]
    # (>= 0: the set whose blocks begin s's, whose sum is in sums already): the same additions in
    # the same order. Returns sums[s].
    W = rows.shape[1]
    v = sums[s]
    t = 0
    p = set_from[s]
    if p >= 0:
        before = sums[p]
        while t < set_blocks.shape[1] and set_blocks[p, t] >= 0:
            t += 1
        row_b = rows[set_blocks[s, t]]
        for x in range(W):
            v[x] = before[x] + row_b[x]
    else:
        row_b = rows[set_blocks[s, 0]]
        for x in range(W):
            v[x] = row_b[x]  # 0.0 + a: a itself (a block sum is >= 0 or NaN)
    t += 1
    while t < set_blocks.shape[1] and set_blocks[s, t] >= 0:
        row_b = rows[set_blocks[s, t]]
        for x in range(W):
            v[x] += row_b[x]
        t += 1
    return v


@numba.njit(cache=True)
def _fixed_table_row(v, fixed, prev, cur, first):
    # cur ((W + 1,) int64), a row of a set's table: v ((W,) float64, the set's image row) rounded
    # to an int64 multiple of 1 / FIXED_POINT, summed along x and, unless first, onto the row above,
    # prev. Rounded apart from the running sum: these loops vectorise (float64 -> int64 as the bits
    # of f + MAGIC_FLOAT less MAGIC_BITS, exact for integral |f| < 2^51; a row with a value out of
    # that range, or NaN, takes the scalar conversion). fixed: (W,) int64 scratch.
    W = v.shape[0]
    fixed_bits = fixed.view(np.float64)
    out_of_range = 0
    for x in range(W):
        out_of_range += not (abs(v[x]) < FIXED_LIMIT)
    if out_of_range == 0:
        for x in range(W):
            fixed_bits[x] = np.floor(v[x] * FIXED_POINT + 0.5) + MAGIC_FLOAT
        for x in range(W):
            fixed[x] -= MAGIC_BITS
    else:
        for x in range(W):
            fixed[x] = np.int64(np.floor(v[x] * FIXED_POINT + 0.5))
    cur[0] = 0
    acc = np.int64(0)
    if not first:
        for x in range(W):
            acc += fixed[x]
            cur[x + 1] = acc + prev[x + 1]
    else:
        for x in range(W):
            acc += fixed[x]
            cur[x + 1] = acc


@numba.njit(cache=True)
def _set_table_row(rows, set_blocks, set_from, set_order, y, first, sums, fixed, out):
    # Row y + 1 of every set's table out (S, H + 1, W + 1) from the block rows of image row y,
    # rows (9, W): each set's row (_set_sum, the sets in set_order: a set after the one it
    # continues; sums (S, W) scratch) summed into it (_fixed_table_row), onto row y unless y is
    # the band's first row (first). fixed: (W,) int64 scratch.
    for i in range(set_blocks.shape[0]):
        s = set_order[i]
        _fixed_table_row(_set_sum(rows, set_blocks, set_from, s, sums), fixed, out[s, y], out[s, y + 1], first)


@numba.njit(cache=True, parallel=True)
def _finish_tables(out, n_bands):
    # The tables out (S, H + 1, W + 1) whose rows 1..H the n_bands bands of rows made each from 0
    # (_set_table_row): their zero first row, and each band below the first the total of the
    # bands above it added (integers: the same tables whatever the banding).
    S, H1, W1 = out.shape
    H = H1 - 1
    out[:, 0] = 0
    carry = np.zeros((n_bands, S, W1), np.int64)  # total of the bands above each band
    for band in range(1, n_bands):
        last = band * H // n_bands  # table row of the last image row of the band above
        for s in range(S):
            for x in range(W1):
                carry[band, s, x] = carry[band - 1, s, x] + out[s, last, x]
    for band in numba.prange(1, n_bands):
        for s in range(S):
            c = carry[band, s]
            for y in range(band * H // n_bands + 1, (band + 1) * H // n_bands + 1):
                row = out[s, y]
                for x in range(W1):
                    row[x] += c[x]


@numba.njit(cache=True, parallel=True)
def _set_integrals_kernel(blocks_ad, set_blocks, set_from, set_order, n_bands, out):
    # Rows 1..H of out[s], the summed-area table of round(FIXED_POINT * sum of blocks_ad over the
    # blocks of set s) (_set_table_row), each of the n_bands bands of rows (one per thread) summed
    # from 0, row by row, each set's row made while it is in cache (then _finish_tables).
    S = set_blocks.shape[0]
    B, H, W = blocks_ad.shape
    for band in numba.prange(n_bands):
        y0 = band * H // n_bands
        y1 = (band + 1) * H // n_bands
        sums = np.empty((S, W), np.float64)
        fixed = np.empty(W, np.int64)
        for y in range(y0, y1):
            _set_table_row(blocks_ad[:, y], set_blocks, set_from, set_order, y, y == y0, sums, fixed, out)


@numba.njit(cache=True)
def ring_table_rows(gray, vu, vv, vdu, vdv, vblock, disparity, set_blocks, set_from, set_order, y0, y1,
                    ring, acc, rv, sums, fixed):
    # Rows y0 + 1..y1 of the sets' summed-area tables at one candidate (block_set_integrals_reference's
    # tables, bit for bit) into the ring (R, S, W + 1): table row r in ring[r % R], made from the
    # one above it, which must be there (row 0, zero, to begin). The block rows of acc.shape[0]
    # image rows at a time, view by view (_block_rows: a view's source rows read in one run), then,
    # while they are in cache, those rows of every set's table. acc (n, 9, W) float32, rv (2, W)
    # float32, sums (S, W) float64 and fixed (W,) int64: scratch.
    R = ring.shape[0]
    for y in range(y0, y1, acc.shape[0]):
        n = min(acc.shape[0], y1 - y)
        acc[:n] = 0.0
        _block_rows(gray, vu, vv, vdu, vdv, vblock, disparity, y, acc[:n], rv)
        for j in range(n):
            prev = ring[(y + j) % R]
            cur = ring[(y + j + 1) % R]
            for i in range(set_blocks.shape[0]):
                s = set_order[i]
                _fixed_table_row(_set_sum(acc[j], set_blocks, set_from, s, sums), fixed, prev[s], cur[s], False)


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
    _set_integrals_kernel(blocks_ad, *set_sums_plan(np.asarray(sets)), n_bands, out)
    _finish_tables(out, n_bands)
    return out


def block_set_integrals_reference(gray: np.ndarray, disparity: float, *, sets: np.ndarray,
                                  view_mask: np.ndarray | None = None) -> np.ndarray:
    """``(S, H + 1, W + 1)`` int64 summed-area tables of the view sets ``sets`` at ``disparity``,
    step by step (readable twin of the rows the joint search makes, ``ring_table_rows``): the
    block images (:func:`block_abs_diff`), then their sets' tables (:func:`set_integrals_reference`)."""
    return set_integrals_reference(block_abs_diff(gray, disparity, view_mask=view_mask), np.asarray(sets))


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
    (the last step of :func:`min_window_costs_reference`).

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
    with np.errstate(over="ignore"):  # 1e300: inf
        return best.astype(np.float32)


@numba.njit(cache=True)
def compiled_window_reach(rects):
    # window_reach within the kernels.
    up = 0
    down = 0
    for k in range(rects.shape[0]):
        up = max(up, -rects[k, 0])
        down = max(down, rects[k, 1])
    return up, down


def window_reach(rects: np.ndarray) -> tuple[int, int]:
    """``(up, down)``: how many rows above and below its pixel any of the windows ``rects``
    ``(K, 4)`` reaches: :func:`compiled_window_reach`'s count, run as Python (each compiled helper
    the estimate calls from Python is another kernel to load, ``recon/entropy/preload.py``)."""
    up, down = compiled_window_reach.py_func(rects)
    return int(up), int(down)


# nogil (here and in the first phase's other kernels): the warm-up's later imports run beside it
# (recon.methods.warm_in_background)
@numba.njit(cache=True, parallel=True, nogil=True)
def _min_window_costs_kernel(gray, vu, vv, vdu, vdv, vblock, disparities, set_blocks, set_from, set_order,
                             window_set, rects, counts, allowed, n_chunks, out):
    # The whole chain block_abs_diff -> set_integrals -> min_window_cost_reference for each of
    # the G candidates disparities (G,) into out (G, H, W), without the images in between. The
    # rows are dealt out in n_chunks chunks; a chunk walks down its rows keeping, per candidate, a
    # ring of the set images' last rows (each pixel's set value rounded to a multiple of
    # 1 / FIXED_POINT as set_integrals does, held as an integer-valued float64) and each window's
    # column sums over its rows (a row added below, one taken away above). A row comes in for
    # every candidate in turn, so the few source rows of the views that the candidates' shifts
    # read come from memory once for the group. The sums are exact integers: the caller makes
    # sure every window sum stays below 2^53, where float64 adds and subtracts integers exactly,
    # so a window's sum is the integer the summed-area tables give, in any order, and its cost
    # (min_window_cost_reference's float64 expression) the same bits. A set whose blocks begin
    # with another set's (set_from, -1: none) continues that set's float64 sum: the same additions
    # in the same order (set_order puts that set first). Rows at a chunk's edge are made by both
    # chunks next to it; no value depends on the chunking or the grouping.
    H = gray.shape[2]
    W = gray.shape[3]
    S = set_blocks.shape[0]
    K = rects.shape[0]
    up, down = compiled_window_reach(rects)
    R = up + down + 2  # and the row just above the windows, taken away from the column sums
    G = disparities.shape[0]
    per_pixel = allowed.shape[1] > 1 or allowed.shape[2] > 1  # (K, H, W), or (K, 1, 1) for all alike
    for chunk in numba.prange(n_chunks):
        c0 = chunk * H // n_chunks
        c1 = (chunk + 1) * H // n_chunks
        rings = np.empty((G, R, S, W), np.float64)
        acc = np.empty((1, N_BLOCKS, W), np.float32)
        rv = np.empty((2, W), np.float32)
        sums = np.empty((S, W), np.float64)
        all_cols = np.empty((G, K, W), np.float64)
        tot = np.empty(W, np.float64)
        everywhere = np.ones(W, np.bool_)
        best = np.empty(W, np.float64)
        nxt = max(c0 - up, 0)  # the next row to put in the ring
        for y in range(c0, c1):
            while nxt <= min(y + down, H - 1):
                for g in range(G):
                    acc[:] = 0.0
                    _block_rows(gray, vu, vv, vdu, vdv, vblock, disparities[g], nxt, acc, rv)
                    slot = rings[g, nxt % R]
                    for i in range(S):
                        s = set_order[i]
                        v = _set_sum(acc[0], set_blocks, set_from, s, sums)
                        fixed = slot[s]
                        for x in range(W):
                            fixed[x] = np.floor(v[x] * FIXED_POINT + 0.5)
                nxt += 1
            for g in range(G):
                ring = rings[g]
                cols = all_cols[g]
                for x in range(W):
                    best[x] = 1e300
                for k in range(K):
                    if not per_pixel and not allowed[k, 0, 0]:
                        continue
                    s = window_set[k]
                    ya = max(y + rects[k, 0], 0)
                    yb = min(y + rects[k, 1], H - 1) + 1
                    col = cols[k]
                    if y == c0:
                        f = ring[ya % R, s]
                        for x in range(W):
                            col[x] = f[x]
                        for r in range(ya + 1, yb):
                            f = ring[r % R, s]
                            for x in range(W):
                                col[x] += f[x]
                    else:  # the row that left the window taken away, the new one added (in one pass)
                        gone = y + rects[k, 0] - 1 >= 0
                        come = y + rects[k, 1] <= H - 1
                        f = ring[(y + rects[k, 0] - 1) % R, s]
                        h = ring[(y + rects[k, 1]) % R, s]
                        if gone and come:
                            for x in range(W):
                                col[x] += h[x] - f[x]
                        elif gone:
                            for x in range(W):
                                col[x] -= f[x]
                        elif come:
                            for x in range(W):
                                col[x] += h[x]
                    ck = counts[k]
                    ra = rects[k, 2]
                    rb = rects[k, 3]
                    # [lo, hi): the window's columns inside the image; there the sums run over slices
                    # indexed from 0 and vectorise
                    lo = min(max(-ra, 0), W)
                    hi = min(max(W - 1 - rb, lo), W)
                    for e in range(lo + W - hi):  # the pixels whose window the left or right edge cuts
                        x = e if e < lo else hi + e - lo
                        if per_pixel and not allowed[k, y, x]:
                            continue
                        xa = max(x + ra, 0)
                        xb = min(x + rb, W - 1) + 1
                        total = 0.0
                        for j in range(xa, xb):
                            total += col[j]
                        c = total * FIXED_INV / ((yb - ya) * (xb - xa) * ck)
                        if c < best[x]:
                            best[x] = c
                    n = hi - lo
                    if n > 0:  # a loop over x per window width (3 and 5: a few slices added, one pass)
                        width = rb - ra + 1
                        bs = best[lo:hi]
                        al = allowed[k, y, lo:hi] if per_pixel else everywhere[lo:hi]
                        denom = (yb - ya) * width * ck
                        s0 = col[lo + ra:hi + ra]
                        s1 = col[lo + ra + 1:hi + ra + 1]
                        s2 = col[lo + ra + 2:hi + ra + 2]
                        if width == 5:
                            s3 = col[lo + ra + 3:hi + ra + 3]
                            s4 = col[lo + ra + 4:hi + ra + 4]
                            for i in range(n):  # inf where not allowed, then a plain < : the loop vectorises
                                c = (((s0[i] + s1[i]) + (s2[i] + s3[i])) + s4[i]) * FIXED_INV / denom
                                c = c if al[i] else np.inf
                                bs[i] = c if c < bs[i] else bs[i]
                        elif width == 3:
                            for i in range(n):
                                c = ((s0[i] + s1[i]) + s2[i]) * FIXED_INV / denom
                                c = c if al[i] else np.inf
                                bs[i] = c if c < bs[i] else bs[i]
                        else:
                            t = tot[:n]
                            for i in range(n):
                                t[i] = s0[i]
                            for q in range(1, width):
                                sq = col[lo + ra + q:hi + ra + q]
                                for i in range(n):
                                    t[i] += sq[i]
                            for i in range(n):
                                c = t[i] * FIXED_INV / denom
                                c = c if al[i] else np.inf
                                bs[i] = c if c < bs[i] else bs[i]
                for x in range(W):
                    out[g, y, x] = best[x]


#: Largest window sum, in units of ``1 / FIXED_POINT``, that :func:`min_window_costs` adds up in
#: float64 (exact for integers below 2^53); a search that could exceed it uses the int64 tables.
EXACT_FLOAT_SUM = float(2 ** 53)


def min_window_costs_reference(gray: np.ndarray, disparity: float, *, sets: np.ndarray,
                               window_set: np.ndarray, rects: np.ndarray, counts: np.ndarray,
                               allowed: np.ndarray, view_mask: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` float32: each pixel's least mean absolute difference at ``disparity`` over its
    allowed windows, step by step (readable twin of :func:`min_window_costs`): the block images
    (:func:`block_abs_diff`), the summed-area tables of the view sets ``sets`` (0..10)
    (:func:`set_integrals_reference`) and the least window cost (:func:`min_window_cost_reference`;
    window ``k`` matched over set ``sets[window_set[k]]``, where ``allowed[k]`` says, ``(K, H, W)``
    or ``(K, 1, 1)`` bool)."""
    blocks = block_abs_diff(gray, disparity, view_mask=view_mask)
    integrals = set_integrals_reference(blocks, np.asarray(sets))
    return min_window_cost_reference(integrals, window_set, rects, counts, np.moveaxis(allowed, 0, -1))


def min_window_costs(gray: np.ndarray, disparities: np.ndarray, *, sets: np.ndarray, window_set: np.ndarray,
                     rects: np.ndarray, counts: np.ndarray, allowed: np.ndarray,
                     view_mask: np.ndarray | None = None, out: np.ndarray | None = None,
                     kernel: str = "auto") -> np.ndarray:
    """``(G, H, W)`` float32: :func:`min_window_costs_reference`'s map at each of the ``G``
    ``disparities`` (compiled twin, bit for bit; ``gray`` contiguous float32, ``counts`` float64,
    ``allowed`` a contiguous bool array), written into ``out`` when given. One pass over the rows
    for the group, with none of the ``(9, H, W)`` block images or ``(S, H + 1, W + 1)`` tables in
    memory; groups of :func:`min_window_group` candidates read the views' rows once for all.
    ``kernel`` (:func:`recon.native.chosen`): by default the C twin of the kernel
    (``recon/native/initial.c``, no numba start-up needed) where it loads, else numba's."""
    U, V, H, W = gray.shape
    disparities = np.ascontiguousarray(disparities, np.float32)
    if out is None:
        out = np.empty((len(disparities), H, W), np.float32)
    if chosen("initial", kernel):
        mask = None if view_mask is None else np.asarray(view_mask, bool)
        views, plan = _native_plan((U, V), None if mask is None else (mask.shape, mask.tobytes()),
                                   np.asarray(sets, np.int64).tobytes())
        threads = thread_count()
        n_chunks = max(1, min(threads, H))
        window_set, rects = np.ascontiguousarray(window_set, np.int64), np.ascontiguousarray(rects, np.int64)
        counts, allowed = np.ascontiguousarray(counts, np.float64), np.ascontiguousarray(allowed, np.bool_)
        if allowed.ndim != 3 or allowed.shape[0] != len(rects) or out.shape != (len(disparities), H, W):
            raise ValueError("allowed must be (K, H, W) or (K, 1, 1) and out (G, H, W)")
        call("initial", "lfrig_min_window_costs", np.ascontiguousarray(gray, np.float32), U, V, H, W, *views[:4],
             views[4], len(views[0]), disparities, len(disparities), *plan[:3], len(plan[0]), window_set, rects,
             len(rects), counts, allowed, allowed.shape[1], allowed.shape[2], n_chunks, threads, out)
        return out
    views = view_lists((U, V), view_mask)
    plan = set_sums_plan(np.asarray(sets))
    n_chunks = max(1, min(numba.get_num_threads(), H))
    _min_window_costs_kernel(gray, *views, disparities, *plan, window_set, rects, counts, allowed, n_chunks, out)
    return out


@lru_cache(maxsize=16)
def _native_plan(grid_shape: tuple[int, int], view_mask: tuple | None, sets: bytes):
    # view_lists and set_sums_plan of one view mask ((shape, bool bytes), None: every view) and one
    # list of sets (int64 bytes), made once for the calls of a search (backgammon's nine-view search:
    # 26 groups, 0.2 ms each); read only, as the C kernel reads them
    mask = None if view_mask is None else np.frombuffer(view_mask[1], np.bool_).reshape(view_mask[0])
    views = view_lists(grid_shape, mask)
    plan = set_sums_plan(np.frombuffer(sets, np.int64))
    for array in (*views, *plan):
        array.flags.writeable = False
    return views, plan


#: Bytes of the rings of set rows and the column sums the candidates of one group of
#: :func:`min_window_costs` keep per thread (:func:`min_window_group`): within a core's L2 cache.
#: On backgammon (512 px wide, 315 KB a candidate) two candidates a group take the nine-view
#: search 0.60-0.65 -> 0.48-0.51 s CPU on one thread; on the demo capture (1198 px, 737 KB) two
#: took it 1.80-2.08 -> 2.01-2.44 s, where one candidate's rows alone fill the cache.
MIN_WINDOW_GROUP_BYTES = 768 * 1024


def min_window_group(width: int, *, n_sets: int, n_windows: int, rects: np.ndarray) -> int:
    """How many candidates of a ``width``-pixel wide image :func:`min_window_costs` takes at once:
    as many as keep their rings of ``n_sets`` set rows (the rows the windows ``rects`` reach, and
    one) and ``n_windows`` column sums within :data:`MIN_WINDOW_GROUP_BYTES` (at least one)."""
    ring_rows = sum(window_reach(rects)) + 2  # as the kernel's
    per_candidate = 8 * width * (ring_rows * n_sets + n_windows)
    return max(MIN_WINDOW_GROUP_BYTES // per_candidate, 1)


def set_sums_plan(sets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(set_blocks, set_from, set_order)`` of :func:`_min_window_costs_kernel`: the blocks of
    each set (:func:`_set_block_lists`), per set the longest other set whose blocks begin its own
    (``-1``: none), whose sum it continues, and the order that makes each set after that one
    (fewest blocks first)."""
    table = _set_block_lists(sets)
    n = (table >= 0).sum(axis=1)
    set_from = np.full(len(sets), -1, np.int64)
    for s in range(len(sets)):
        for p in range(len(sets)):
            if n[p] < n[s] and (table[p, :n[p]] == table[s, :n[p]]).all() and (
                    set_from[s] < 0 or n[p] > n[set_from[s]]):
                set_from[s] = p
    return table, set_from, np.argsort(n, kind="stable").astype(np.int64)


def window_sum_bound(gray: np.ndarray, *, rects: np.ndarray, view_mask: np.ndarray | None = None) -> float:
    """An upper bound of every window sum :func:`min_window_costs` adds up, in units of
    ``1 / FIXED_POINT``: the largest absolute difference of two grey values of ``gray``
    (``(U, V, H, W)``) times the number of views, times the largest window's pixels, with one unit
    of rounding per pixel (``inf`` for views holding NaN or inf)."""
    U, V = gray.shape[:2]
    mask = np.ones((U, V), bool) if view_mask is None else np.asarray(view_mask, bool)
    used = gray[mask]
    lo, hi = float(used.min(initial=0.0)), float(used.max(initial=0.0))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return np.inf
    area = int(((rects[:, 1] - rects[:, 0] + 1) * (rects[:, 3] - rects[:, 2] + 1)).max())
    return (2 * (hi - lo) * int(mask.sum()) * FIXED_POINT + 1) * area


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


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: see _min_window_costs_kernel
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


def cost_ambiguity(costs: np.ndarray, delta: float, *, kernel: str = "auto") -> np.ndarray:
    """``(H, W)`` int32: how many of the ``D`` candidates of a ``(D, H, W)`` cost volume come
    within ``delta`` of the pixel's least cost. A few (a narrow valley) where the matching tells
    disparities apart; many (a plateau) where it has no information, e.g. inside a textureless
    patch, where the window matches itself at every small shift. Compiled twin of
    :func:`cost_ambiguity_reference` (same map): C (``recon/native/initial.c``) where it loads,
    else numba's (``kernel``: :func:`recon.native.chosen`)."""
    if costs.dtype != np.float32 or not costs.flags.c_contiguous or costs.ndim != 3 or costs.shape[0] == 0:
        return cost_ambiguity_reference(costs, delta)
    out = np.empty(costs.shape[1:], np.int32)
    if chosen("initial", kernel):
        call("initial", "lfrig_cost_ambiguity", costs, *costs.shape, float(np.float32(delta)), out, thread_count())
        return out
    _cost_ambiguity_kernel(costs, np.float32(delta), out)
    return out
