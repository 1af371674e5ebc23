"""The baseline estimator: a fixed square window, SAD over all views, parabolic sub-pixel refinement.

It is the yardstick the matching-entropy method must beat, so it is an honest one: every view
takes part, the disparity search is dense, and the plane sweep runs in a compiled kernel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from recon.progress import ProgressCallback, report
from recon.sweep import sweep_least_cost, view_offsets
from recon.lf.lightfield import LightField

#: Most candidates per call of the sweep kernel; the calls take nearly equal shares and progress is
#: reported after each. A call reads each view's rows once for all of its candidates: on backgammon
#: (121 candidates) four calls take ~0.1 s less CPU than sixteen of 8.
SWEEP_CHUNK = 32

#: The search range used when neither the caller nor the light field gives one (pixels per view step).
DEFAULT_DISPARITY_RANGE = (-4.0, 4.0)


@dataclass
class BaselineResult:
    """Disparity of the centre view, ``(H, W)`` float32 in pixels per view step, and the winning cost."""

    disparity: np.ndarray
    cost: np.ndarray
    candidates: np.ndarray


def disparity_candidates(disparity_range: tuple[float, float], step: float) -> np.ndarray:
    """``disp_min, disp_min + step, ...`` up to and including ``disp_max`` (within rounding)."""
    lo, hi = disparity_range
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ValueError(f"disparity range must be finite with min < max; got {disparity_range}")
    if not step > 0:
        raise ValueError(f"disparity step must be positive; got {step}")
    count = int(np.floor((hi - lo) / step + 1e-6)) + 1
    return lo + step * np.arange(count)


def parabolic_refine(volume: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel minimum of a cost volume ``(D, H, W)`` by a parabola through the best and its neighbours.

    Returns ``(disparity, cost)`` ``(H, W)`` float32. At the ends of the range (and with fewer than three
    candidates) the integer minimum is kept. The readable twin of the sweep in :func:`estimate_baseline`,
    which keeps only the best candidate and its two neighbours instead of the volume.
    """
    best = np.argmin(volume, axis=0)
    rows, cols = np.indices(best.shape)
    inner = np.clip(best, 1, len(candidates) - 2) if len(candidates) >= 3 else best
    return parabola_vertex(best, volume[inner - 1, rows, cols], volume[best, rows, cols],
                           volume[inner + 1 if len(candidates) >= 3 else inner, rows, cols], candidates)


def parabola_vertex(best: np.ndarray, c_minus: np.ndarray, c_zero: np.ndarray, c_plus: np.ndarray,
                    candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(disparity, cost)`` ``(H, W)`` float32 from the index of each pixel's least cost ``best``
    ``(H, W)`` int, that cost ``c_zero`` and its neighbours' ``c_minus``, ``c_plus`` (float32; read
    only where ``0 < best < D - 1``): the vertex of the parabola through the three, within half a
    step of the best candidate; at the ends of the range the best candidate itself."""
    if len(candidates) < 3:  # no neighbours on both sides: the best candidate as it is
        return candidates[best].astype(np.float32), c_zero.astype(np.float32)
    curvature = c_minus - 2 * c_zero + c_plus
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        delta = np.where(curvature > 0, 0.5 * (c_minus - c_plus) / curvature, 0.0)
    delta = np.clip(delta, -0.5, 0.5)
    delta[(best == 0) | (best == len(candidates) - 1)] = 0.0
    step = candidates[1] - candidates[0]
    disparity = candidates[best] + delta * step
    return disparity.astype(np.float32), c_zero.astype(np.float32)


def check_options(*, window: int = 7, step: float = 0.02, disparity_range: tuple[float, float] | None = None,
                  **unknown: object) -> None:
    """Raise ``ValueError`` naming an option value :func:`estimate_baseline` cannot use."""
    if unknown:
        raise ValueError(f"unknown baseline option(s) {sorted(unknown)}; valid names: disparity_range, step, window")
    if isinstance(window, bool) or not isinstance(window, int) or window < 1 or window % 2 == 0:
        raise ValueError(f"window must be an odd number of pixels >= 1; got {window}")
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"step must be a positive number of pixels per view step; got {step}")
    if disparity_range is not None:
        low, high = disparity_range
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f"disparity_range must be finite (min, max) with min < max; got {tuple(disparity_range)}")


def load_kernels(kernel: str = "auto") -> None:
    """Load the sweep's compiled kernel by running it on a tiny light field, so that a caller can
    load it while it reads the views (:func:`recon.methods.warm_in_background`);
    :func:`estimate_baseline` does not need it. The C kernel (:mod:`recon.sweep`) loads in
    milliseconds (it is built here the first time); numba's, where the C one cannot be had, brings
    numba's start-up (its imports and its first cache load). ``kernel`` as
    :func:`recon.sweep.sweep_least_cost`'s."""
    offsets = view_offsets((3, 3))
    sweep_least_cost(np.zeros((3, 3, 4, 4), np.float32), np.zeros(1), offsets=offsets,
                     indices=(offsets + 1).astype(np.int64), window=1, kernel=kernel)


def estimate_baseline(
    lf: LightField,
    *,
    window: int = 7,
    step: float = 0.02,
    disparity_range: tuple[float, float] | None = None,
    progress: ProgressCallback | None = None,
) -> BaselineResult:
    """Fixed-window SAD disparity of the centre view.

    Parameters
    ----------
    lf
        The light field; all views but the centre are matched against the centre view (grey levels).
    window
        Side of the square window in pixels (odd, >= 1).
    step
        Spacing of the candidate disparities in pixels per view step.
    disparity_range
        ``(min, max)`` to search; defaults to ``lf.disparity_range``, else :data:`DEFAULT_DISPARITY_RANGE`.
    progress
        ``progress(fraction, message)`` after each call of the sweep, at most :data:`SWEEP_CHUNK`
        candidates (:mod:`recon.progress`).

    Returns
    -------
    BaselineResult with ``disparity`` ``(H, W)`` in the benchmark's sign convention.
    """
    check_options(window=window, step=step, disparity_range=disparity_range)
    disparity_range = disparity_range or lf.disparity_range or DEFAULT_DISPARITY_RANGE
    candidates = disparity_candidates(disparity_range, step)
    gray = np.ascontiguousarray(lf.gray(), dtype=np.float32)
    offsets = view_offsets(lf.grid_shape)
    indices = (offsets + np.array(lf.centre_index)).astype(np.int64)
    # One plane sweep (recon.sweep.sweep_least_cost): each candidate's window cost is compared
    # with the least so far; the volume of every candidate's cost is never held (what
    # parabolic_refine would read of it is kept). In a few calls of nearly equal size, for the progress.
    calls = -(-len(candidates) // SWEEP_CHUNK)
    bounds = [len(candidates) * i // calls for i in range(calls + 1)]
    state = None
    for first, stop in zip(bounds, bounds[1:]):
        state = sweep_least_cost(gray, candidates[first:stop], offsets=offsets, indices=indices, window=window,
                                 state=state, first=first)
        report(progress, stop / len(candidates), "disparity candidates")
    best_index, best = state["best_index"], state["best"]
    disparity, cost = parabola_vertex(best_index, state["c_minus"], best, state["c_plus"], candidates)
    return BaselineResult(disparity=disparity, cost=cost, candidates=candidates)
