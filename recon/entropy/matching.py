"""The line searches of Eqs. 5-7 over candidate disparities: the least cost over several windows
(the initial search), the joint minimum over disparity and window (Eq. 7), one window per pixel
(the paper's two-step reading), and the parabolic sub-step refinement (Eq. 6's minimum).

The cost at one candidate is :mod:`recon.entropy.cost`'s; the penalty volume's layout
:mod:`recon.entropy.layout`'s. Twins follow the rule of :mod:`recon.entropy`: ``name`` compiled,
``name_reference`` readable.
"""

from __future__ import annotations

from recon.jit import numba
import numpy as np

from recon.entropy.cost import (EXACT_FLOAT_SUM, FIXED_INV, MAGIC_BITS, MAGIC_FLOAT, MAGIC_LIMIT, N_BLOCKS,
                                WindowCost, ring_table_rows, set_sums_plan, view_lists, compiled_window_reach,
                                block_abs_diff, block_abs_diff_reference, cost_ambiguity, min_window_costs,
                                min_window_costs_reference, min_window_group, set_view_counts, window_reach,
                                window_sum_bound)
from recon.entropy.layout import RUN_GAP, offer_runs
from recon.entropy.windows import SET_BLOCKS, window_rect
from recon.native import call, chosen, thread_count

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
    is called after each group of candidates (:func:`recon.entropy.cost.min_window_group`).
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
    group = min_window_group(W, n_sets=len(sets), n_windows=len(windows), rects=rects) if exact else 1
    for i in range(0, len(candidates), group):
        j = min(i + group, len(candidates))
        if exact:
            min_window_costs(gray, candidates[i:j], sets=sets, window_set=window_set, rects=rects, counts=wcounts,
                             allowed=allowed, view_mask=view_mask, out=costs[i:j])
        else:  # sums beyond float64's integers: the int64 tables
            costs[i] = min_window_costs_reference(gray, float(candidates[i]), sets=sets, window_set=window_set,
                                                  rects=rects, counts=wcounts, allowed=allowed,
                                                  view_mask=view_mask)
        if progress is not None:
            progress(j / len(candidates))
    disparity, best = subpixel_argmin(costs, candidates)
    if ambiguity_delta is not None:
        return disparity, best, cost_ambiguity(costs, ambiguity_delta)
    return disparity, best




@numba.njit(cache=True, inline="always")
def _joint_edge_pixel(x, k, y, ya, yb, ia, ib, s, ra, rb, W, tables, cnt, scale, penalty, every, want, pixel_set,
                      c_best, k_best):
    # _joint_row at a pixel whose window the image's left or right edge clips.
    xa = max(x + ra, 0)
    xb = min(x + rb, W - 1) + 1
    total = (tables[ib, s, xb] - tables[ia, s, xb] - tables[ib, s, xa] + tables[ia, s, xa]) * FIXED_INV
    c = scale * total / ((yb - ya) * (xb - xa) * cnt) + penalty[y, k, x]
    if (every or pixel_set[y, x] == want) and c < c_best[x]:
        c_best[x] = c
        k_best[x] = k


@numba.njit(cache=True)
def _joint_row(tables, y, pixel_set, rects, window_shape, counts, penalty, run_start, runs, scale, magic,
               c_best, k_best, tb, tf):
    # One candidate's objective at the pixels of row y, the least over the windows (ascending, strict
    # <) folded into c_best / k_best ((W,) float64 and int64). tables (R, S, W + 1): the candidate's
    # summed-area tables' rows, table row r in tables[r % R] (ring_table_rows); the same float64
    # arithmetic for every pixel and window as the pixelwise twin. For one window the four corners
    # of every pixel's window lie on two rows of one table, contiguous in x: away from the image's
    # left and right edges the loop over x vectorises. Its loads index the arrays themselves with
    # unsigned offsets: a signed index would take numba's negative-index wrap (loads turned into
    # gathers), and a slice a reference count kept twice per run (atomic, on a line that the other
    # threads' slices of the same arrays share).
    # penalty (H, K, W): inf where the window is not offered; runs[run_start[i]:run_start[i + 1]]
    # with i = (y * K + k) * 2 + pass: column runs [lo, hi) covering the pixels of row y that offer
    # window k, matched over all views (pass 0; every pixel for a square) or over the window's
    # visible set (pass 1: occluded pixels, shaped windows). See recon.entropy.layout.offer_runs.
    # magic: every window total of the row is below MAGIC_LIMIT (its int64 -> float64 conversion
    # vectorises, recon.entropy.cost.MAGIC_FLOAT; the same values as the plain conversion).
    # The least c_best is min(old, c) with c = inf where the pass does not apply: the same value as
    # a strict < (no objective is NaN or -0.0), and a plain store, not a masked one. tb (W,) int64
    # and tf (W,) float64: scratch.
    H, K, W = penalty.shape
    R = tables.shape[0]
    fb = tb.view(np.float64)
    for k in range(K):
        ya = max(y + rects[k, 0], 0)
        yb = min(y + rects[k, 1], H - 1) + 1
        ia = ya % R
        ib = yb % R
        ra = rects[k, 2]
        rb = rects[k, 3]
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
            for x in range(x0, lo):  # left edge: the window clipped
                _joint_edge_pixel(x, k, y, ya, yb, ia, ib, s, ra, rb, W, tables, cnt, scale, penalty, every, want,
                                  pixel_set, c_best, k_best)
            if n > 0:
                denom = (yb - ya) * (rb - ra + 1) * cnt
                un = np.uint64(n)
                u0 = np.uint64(lo)  # the pixels' column
                u1 = np.uint64(lo + rb + 1)  # their windows' right and left corners' (>= 0)
                ua = np.uint64(lo + ra)
                if magic:
                    for i in range(un):
                        tb[i] = (tables[ib, s, u1 + i] - tables[ia, s, u1 + i] - tables[ib, s, ua + i]
                                 + tables[ia, s, ua + i] + MAGIC_BITS)
                    for i in range(un):
                        tf[i] = fb[i] - MAGIC_FLOAT
                else:
                    for i in range(un):
                        tf[i] = (tables[ib, s, u1 + i] - tables[ia, s, u1 + i] - tables[ib, s, ua + i]
                                 + tables[ia, s, ua + i])
                for i in range(un):
                    c = scale * (tf[i] * FIXED_INV) / denom + penalty[y, k, u0 + i]
                    c = c if (every | (pixel_set[y, u0 + i] == want)) else np.inf
                    old = c_best[u0 + i]
                    k_best[u0 + i] = k if c < old else k_best[u0 + i]
                    c_best[u0 + i] = min(old, c)
            for x in range(hi, x1):  # right edge
                _joint_edge_pixel(x, k, y, ya, yb, ia, ib, s, ra, rb, W, tables, cnt, scale, penalty, every, want,
                                  pixel_set, c_best, k_best)


@numba.njit(cache=True, parallel=True)
def _joint_group_kernel(gray, vu, vv, vdu, vdv, vblock, disparities, set_blocks, set_from, set_order,
                        pixel_set, rects, window_shape, counts, penalty, run_start, runs, scale, rows, out,
                        best, best_k):
    # The joint search for a group of G candidates (disparities (G,) float32, out (G, H, W)), down
    # the image `rows` rows at a time. For each stretch of rows the candidates, in parallel, extend
    # their rings of summed-area table rows (ring_table_rows: the stretch's rows and the rows its
    # windows reach below; the ring holds the rows they reach above as well) and evaluate its rows
    # (_joint_row), so that the stretch's penalty rows and the views' source rows, the search's
    # largest reads, come from memory once for the group and from cache for every candidate; then
    # each pixel's objectives are folded into best / best_k candidate after candidate (strict <: the
    # first least wins), as one candidate at a time. The int64 tables give the same window totals
    # from any row, so the ring's rows are those of the whole image's tables.
    H, K, W = penalty.shape
    S = set_blocks.shape[0]
    G = disparities.shape[0]
    up, down = compiled_window_reach(rects)
    R = rows + up + down + 1
    tables = np.empty((G, R, S, W + 1), np.int64)
    tables[:, 0] = 0  # table row 0
    acc = np.empty((G, rows, N_BLOCKS, W), np.float32)
    rv = np.empty((G, 2, W), np.float32)
    sums = np.empty((G, S, W), np.float64)
    fixed = np.empty((G, W), np.int64)
    c_best = np.empty((G, W), np.float64)
    k_best = np.empty((G, rows, W), np.int64)
    tb = np.empty((G, W), np.int64)
    tf = np.empty((G, W), np.float64)
    made = 0  # image rows in the tables
    for y0 in range(0, H, rows):
        y1 = min(y0 + rows, H)
        need = min(y1 + down, H)
        for g in numba.prange(G):
            ring = tables[g]
            ring_table_rows(gray, vu, vv, vdu, vdv, vblock, disparities[g], set_blocks, set_from, set_order,
                            made, need, ring, acc[g], rv[g], sums[g], fixed[g])
            # no window total of the stretch exceeds its rows' total (the set values are >= 0)
            top = ring[max(y0 - up, 0) % R]
            bottom = ring[need % R]
            magic = True
            for s in range(S):
                magic = magic and bottom[s, W] - top[s, W] < MAGIC_LIMIT
            for y in range(y0, y1):
                cb = c_best[g]
                kb = k_best[g, y - y0]
                cb[:] = 1e300
                kb[:] = -1
                _joint_row(ring, y, pixel_set, rects, window_shape, counts, penalty, run_start, runs, scale,
                           magic, cb, kb, tb[g], tf[g])
                for x in range(W):
                    out[g, y, x] = np.float32(cb[x])
        made = need
        for y in numba.prange(y0, y1):
            for g in range(G):
                for x in range(W):
                    if out[g, y, x] < best[y, x]:
                        best[y, x] = out[g, y, x]
                        best_k[y, x] = k_best[g, y - y0, x]


#: Image rows the joint search takes at a time (:func:`_joint_group_kernel`): its candidates'
#: rings of summed-area table rows hold these and the rows the windows reach (15 at the default
#: sizes). Backgammon, the whole search, CPU s of two threads (medians of 3, load 7): 4, 8 and 16
#: rows 2.85, 2.64 and 3.22 (16 rows' penalty and views' rows no longer stay in cache); the demo
#: capture's step with 16 rows 6.66-8.00 s CPU against 5.34-6.57 with 8 (load 2).
JOINT_ROWS = 8
#: The candidates of a pass of the joint search share the penalty's and the views' reads; as many
#: as the rings of table rows of this many whole tables hold (nine int64 tables of
#: ``(H + 1) x (W + 1)`` each, 19 MB at 512x512): on backgammon two passes of 31 and 30
#: candidates, 22 MB of rings. One, two and four tables' worth: 2.89, 2.64 and 2.90 s CPU (as for
#: :data:`JOINT_ROWS`).
JOINT_TABLES = 2


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
                      progress=None, kernel: str = "auto"):
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
        Called as ``progress(fraction)`` after each pass over a group of candidates
        (:data:`JOINT_TABLES`).
    kernel
        :func:`recon.native.chosen`: by default the C twin of the search's kernels
        (``recon/native/joint.c``: :func:`_joint_group_kernel` and the offer runs of
        :func:`recon.entropy.layout.offer_runs`, no numba start-up needed) where it loads, else
        numba's; the same maps.

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
    views = view_lists((U, V), view_mask)
    plan = set_sums_plan(np.arange(SET_BLOCKS.shape[0]))
    native = chosen("joint", kernel)
    if native:
        _check_joint_inputs(gray, penalty, pixel_set, rects, shapes, counts, plan)
        threads = thread_count()
        run_start, runs = _offer_runs_native(penalty, pixel_set, shapes, threads)
    else:
        threads = numba.get_num_threads()
        run_start, runs = offer_runs(penalty, pixel_set, shapes)
    D = len(candidates)
    ring_rows = JOINT_ROWS + sum(window_reach(rects)) + 1  # as the kernel's rings
    group = max(JOINT_TABLES * (H + 1) // ring_rows, threads, 1)
    bounds = np.linspace(0, D, -(-D // group) + 1).astype(int)  # passes of even size
    costs = np.empty((D, H, W), np.float32)
    least = np.full((H, W), np.inf, np.float32)
    window_index = np.full((H, W), -1, np.int64)
    for i, j in zip(bounds[:-1], bounds[1:]):
        if native:
            disparities = np.ascontiguousarray(candidates[i:j], np.float32)
            call("joint", "lfrig_joint_group", gray, U, V, H, W, *views[:4], views[4], len(views[0]), disparities,
                 len(disparities), *plan, len(plan[0]), pixel_set, rects, shapes, len(rects), counts, penalty,
                 run_start, runs, float(intensity_scale), JOINT_ROWS, costs[i:j], least, window_index, threads)
        else:
            _joint_group_kernel(gray, *views, np.asarray(candidates[i:j], np.float32), *plan, pixel_set, rects,
                                shapes, counts, penalty, run_start, runs, float(intensity_scale), JOINT_ROWS,
                                costs[i:j], least, window_index)
        if progress is not None:
            progress(j / D)
    disparity, best = subpixel_argmin(costs, candidates)
    return disparity, best, window_index, cost_ambiguity(costs, ambiguity_delta)


def _check_joint_inputs(gray, penalty, pixel_set, rects, shapes, counts, plan) -> None:
    # What lfrig_joint_group reads, checked before it reads it: the penalty (H, K, W) and the pixels'
    # sets (H, W) of the views' image, windows about their pixel and over sets the tables hold.
    _, _, H, W = gray.shape
    K = len(rects)
    if penalty.shape != (H, K, W) or pixel_set.shape != (H, W):
        raise ValueError(f"penalty must be ({H}, {K}, {W}) and use_shape_set ({H}, {W}); got "
                         f"{penalty.shape} and {pixel_set.shape}")
    if K and ((rects[:, [0, 2]] > 0).any() or (rects[:, [1, 3]] < 0).any()):
        raise ValueError("every window must hold its pixel")
    if K and (shapes.min() < 0 or shapes.max() >= min(len(plan[0]), len(counts))):
        raise ValueError(f"window shapes must be 0..{min(len(plan[0]), len(counts)) - 1}")


def _offer_runs_native(penalty: np.ndarray, pixel_set: np.ndarray, shapes: np.ndarray,
                       threads: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`recon.entropy.layout.offer_runs` of the ``(H, K, W)`` float32 penalty, ``(H, W)`` bool
    pixel sets and ``(K,)`` int64 window shapes (contiguous) by its C twin (``recon/native/joint.c``):
    the same ``(run_start, runs)``."""
    H, K, W = penalty.shape
    run_start = np.empty(H * K * 2 + 1, np.int64)
    call("joint", "lfrig_offer_counts", penalty, H, K, W, pixel_set, shapes, RUN_GAP, run_start, threads)
    runs = np.empty((int(run_start[-1]), 2), np.int32)
    call("joint", "lfrig_offer_runs", penalty, H, K, W, pixel_set, shapes, RUN_GAP, run_start, runs, threads)
    return run_start, runs


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


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: see recon.entropy.cost._min_window_costs_kernel
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


def subpixel_argmin(costs: np.ndarray, candidates: np.ndarray, *,
                    kernel: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel arg-min of a ``(D, H, W)`` cost volume refined by a parabola: ``(disparity, cost
    at the arg-min)``, ``(H, W)`` float32 each. The arg-min is the first least candidate (the first
    NaN if any, as ``np.argmin``); the parabola through it and its two neighbours moves it by at
    most half a step (not at the ends of the range, nor where the curve is not convex there).
    Compiled twin of :func:`subpixel_argmin_reference` (the same float64 arithmetic, same maps): C
    (``recon/native/initial.c``) where it loads, else numba's (``kernel``: :func:`recon.native.chosen`)."""
    costs = np.asarray(costs)
    if costs.dtype != np.float32 or not costs.flags.c_contiguous or costs.ndim != 3 or costs.shape[0] == 0:
        return subpixel_argmin_reference(costs, candidates)
    D, H, W = costs.shape
    candidates = np.asarray(candidates)
    step = float(candidates[1] - candidates[0]) if D > 1 else 0.0
    disparity = np.empty((H, W), np.float32)
    best = np.empty((H, W), np.float32)
    if chosen("initial", kernel):
        values = np.ascontiguousarray(candidates, np.float64)
        if len(values) != D:
            raise ValueError(f"{len(values)} candidates for a cost volume of {D}")
        call("initial", "lfrig_subpixel_argmin", costs, D, H, W, values, step, disparity, best, thread_count())
        return disparity, best
    _subpixel_argmin_kernel(costs, np.ascontiguousarray(candidates, np.float64), step, disparity, best)
    return disparity, best
