"""The line searches of Eqs. 5-7 over candidate disparities: the least cost over several windows
(the initial search), the joint minimum over disparity and window (Eq. 7), one window per pixel
(the paper's two-step reading), and the parabolic sub-step refinement (Eq. 6's minimum).

The cost at one candidate is :mod:`recon.entropy.cost`'s; the penalty volume's layout
:mod:`recon.entropy.layout`'s. Twins follow the rule of :mod:`recon.entropy`: ``name`` compiled,
``name_reference`` readable.
"""

from __future__ import annotations

import numba
import numpy as np

from recon.entropy.cost import (EXACT_FLOAT_SUM, FIXED_INV, MAGIC_BITS, MAGIC_FLOAT, MAGIC_LIMIT, N_BLOCKS,
                                WindowCost, block_abs_diff, block_abs_diff_reference, block_set_integrals,
                                cost_ambiguity, min_window_costs, min_window_costs_reference, set_view_counts,
                                window_sum_bound)
from recon.entropy.layout import offer_runs, row_order
from recon.entropy.windows import SET_BLOCKS, window_rect

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
    if allowed is None:
        allowed = np.ones((len(windows), 1, 1), np.bool_)
    elif allowed.shape != (H, W, len(windows)) or not allowed.any(axis=2).all():
        raise ValueError(f"allowed must be ({H}, {W}, {len(windows)}) bool with a window at every pixel")
    else:  # window by window: the kernels read each window's row contiguously
        allowed = np.ascontiguousarray(np.moveaxis(allowed, 2, 0), dtype=np.bool_)
    exact = window_sum_bound(gray, rects=rects, view_mask=view_mask) < EXACT_FLOAT_SUM
    costs = np.empty((len(candidates), H, W), np.float32)
    for i, d in enumerate(candidates):
        if exact:
            min_window_costs(gray, float(d), sets=sets, window_set=window_set, rects=rects, counts=wcounts,
                             allowed=allowed, view_mask=view_mask, out=costs[i])
        else:  # sums beyond float64's integers: the int64 tables
            costs[i] = min_window_costs_reference(gray, float(d), sets=sets, window_set=window_set,
                                                  rects=rects, counts=wcounts, allowed=allowed,
                                                  view_mask=view_mask)
        if progress is not None:
            progress((i + 1) / len(candidates))
    disparity, best = subpixel_argmin(costs, candidates)
    if ambiguity_delta is not None:
        return disparity, best, cost_ambiguity(costs, ambiguity_delta)
    return disparity, best




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
                       runs, scale, order, magic, out, best, best_k):
    # Window-major twin of _joint_cost_pixelwise for a group of G candidates: integrals
    # (G, S, H + 1, W + 1), out (G, H, W); the same float64 arithmetic for every pixel, window and
    # candidate, windows in ascending order, strict <, each candidate's objective folded into
    # best / best_k after the one before it: the same maps bit for bit as one candidate a call.
    # A run's penalty and occlusion flags are read once from memory for the whole group (the
    # penalty, H x K x W float32, is the kernel's largest read). For one row and one window the
    # four corners of every pixel's window lie on two rows of one integral table, contiguous in x:
    # away from the image's left and right edges the loop over x vectorises (the slices index from
    # 0, so that numba's negative-index wrap does not turn loads into gathers).
    # penalty (H, K, W): inf where the window is not offered; runs[run_start[i]:run_start[i + 1]]
    # with i = (y * K + k) * 2 + pass: column runs [lo, hi) covering the pixels of row y that offer
    # window k, matched over all views (pass 0; every pixel for a square) or over the window's
    # visible set (pass 1: occluded pixels, shaped windows). See recon.entropy.layout.offer_runs.
    # magic: every window total is below MAGIC_LIMIT (its int64 -> float64 conversion vectorises,
    # recon.entropy.cost.MAGIC_FLOAT).
    # The least objective c_best is min(old, c) with c = inf where the pass does not apply: the
    # same value as a strict < (no objective is NaN or -0.0), and a plain store, not a masked one.
    G = integrals.shape[0]
    H, K, W = penalty.shape
    for jr in numba.prange(H):
        y = order[jr]
        c_all = np.full((G, W), 1e300)
        k_all = np.full((G, W), -1, np.int64)
        tb = np.empty(W, np.int64)
        fb = tb.view(np.float64)
        tf = np.empty(W, np.float64)
        occluded = pixel_set[y]
        for k in range(K):
            ya = max(y + rects[k, 0], 0)
            yb = min(y + rects[k, 1], H - 1) + 1
            ra = rects[k, 2]
            rb = rects[k, 3]
            pen = penalty[y, k]
            for r in range(run_start[(y * K + k) * 2], run_start[(y * K + k) * 2 + 2]):
                x0 = runs[r, 0]
                x1 = runs[r, 1]
                pas = 1 if r >= run_start[(y * K + k) * 2 + 1] else 0
                s = window_shape[k] if pas == 1 else 0
                every = window_shape[k] == 0  # a square: the same set for every pixel
                want = pas == 1  # otherwise only pixels whose pixel_set is this pass's
                cnt = counts[s]
                lo = min(max(x0, -ra), x1)  # [lo, hi): the window's columns inside the image
                hi = max(min(x1, W - 1 - rb), lo)
                n = hi - lo
                denom = (yb - ya) * (rb - ra + 1) * cnt
                pn = pen[lo:hi]
                oc = occluded[lo:hi]
                for g in range(G):
                    iya = integrals[g, s, ya]
                    iyb = integrals[g, s, yb]
                    c_best = c_all[g]
                    k_best = k_all[g]
                    for x in range(x0, lo):  # left edge: the window clipped
                        _joint_edge_pixel(x, k, ya, yb, ra, rb, W, iya, iyb, cnt, scale, pen, every,
                                          want, occluded, c_best, k_best)
                    if n > 0:
                        b1 = iyb[lo + rb + 1:hi + rb + 1]
                        a1 = iya[lo + rb + 1:hi + rb + 1]
                        b0 = iyb[lo + ra:hi + ra]
                        a0 = iya[lo + ra:hi + ra]
                        if magic:
                            for i in range(n):
                                tb[i] = b1[i] - a1[i] - b0[i] + a0[i] + MAGIC_BITS
                            for i in range(n):
                                tf[i] = fb[i] - MAGIC_FLOAT
                        else:
                            for i in range(n):
                                tf[i] = b1[i] - a1[i] - b0[i] + a0[i]
                        cb = c_best[lo:hi]
                        kb = k_best[lo:hi]
                        for i in range(n):
                            c = scale * (tf[i] * FIXED_INV) / denom + pn[i]
                            c = c if (every | (oc[i] == want)) else np.inf
                            old = cb[i]
                            kb[i] = k if c < old else kb[i]
                            cb[i] = min(old, c)
                    for x in range(hi, x1):  # right edge
                        _joint_edge_pixel(x, k, ya, yb, ra, rb, W, iya, iyb, cnt, scale, pen, every,
                                          want, occluded, c_best, k_best)
        for g in range(G):
            for x in range(W):
                c32 = np.float32(c_all[g, x])
                out[g, y, x] = c32
                if c32 < best[y, x]:
                    best[y, x] = c32
                    best_k[y, x] = k_all[g, x]


#: Candidates whose objectives the joint search's kernel makes in one pass, each run of the
#: penalty read from memory once for all of them; their summed-area tables are held together
#: (nine int64 tables of ``(H + 1) x (W + 1)`` each, 19 MB a candidate at 512x512).
JOINT_GROUP = 2


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
                    if not np.isfinite(penalty[y, k, x]):
                        continue
                    s = shape if use_shape_set[y, x] else 0
                    img = np.tensordot(SET_BLOCKS[s].astype(np.float64), blocks, axes=1)
                    y0, y1, x0, x1 = window_rect(shape, size)
                    patch = img[max(y + y0, 0):min(y + y1, H - 1) + 1,
                                max(x + x0, 0):min(x + x1, W - 1) + 1]
                    c = intensity_scale * patch.sum() / (patch.size * counts[s]) + penalty[y, k, x]
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
        ``(H, K, W)`` float32, each row's windows one after another (``inf``: not offered;
        :meth:`recon.entropy.volume.SparseVolume.window_major`).
    use_shape_set
        ``(H, W)`` bool: match over the window shape's visible set (occluded pixels) instead of all
        views.
    intensity_scale
        Factor on the mean absolute difference of ``[0, 1]`` grey values (255: 8-bit levels).
    ambiguity_delta
        Tolerance of :func:`cost_ambiguity` (objective units).
    progress
        Called as ``progress(fraction)`` after each group of :data:`JOINT_GROUP` candidates.

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
    penalty = np.ascontiguousarray(penalty, dtype=np.float32)
    run_start, runs = offer_runs(penalty, pixel_set, shapes)
    all_sets = np.arange(SET_BLOCKS.shape[0])
    D = len(candidates)
    integrals = np.empty((min(JOINT_GROUP, D), len(all_sets), H + 1, W + 1), np.int64)
    costs = np.empty((D, H, W), np.float32)
    least = np.full((H, W), np.inf, np.float32)
    order = row_order(H)
    window_index = np.full((H, W), -1, np.int64)
    for i in range(0, D, JOINT_GROUP):
        group = integrals[:min(JOINT_GROUP, D - i)]
        block_set_integrals(gray, candidates[i:i + len(group)], sets=all_sets, view_mask=view_mask, out=group)
        # no window total exceeds its table's whole-image total (the set values are >= 0)
        magic = bool(group[:, :, -1, -1].max() < MAGIC_LIMIT)
        _joint_cost_kernel(group, pixel_set, rects, shapes, counts, penalty, run_start, runs,
                           float(intensity_scale), order, magic, costs[i:i + len(group)], least, window_index)
        if progress is not None:
            progress((i + len(group)) / D)
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
        block_abs_diff(gray, float(d), view_mask=view_mask, out=buf)
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
