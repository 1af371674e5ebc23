"""Per-pixel confidence of the final disparity, from the matching cost curve (lfrig's, not the paper's).

The factors, each in ``(0, 1]``, multiply:

- **sharpness of the cost valley**: ``width`` = the disparity span of the candidates whose objective
  comes within the hole tolerance of the pixel's least (``matching.cost_ambiguity`` minus one, times
  the candidate step). A narrow valley pins the disparity; a wide one (a plateau: no texture, an
  edge along the parallax, a repetitive pattern with near-equal minima, whose span covers them all)
  does not. Factor ``exp(-width / valley_px)``, ``valley_px`` = the hole width (0.3 px/view).
- **agreement with the refinement**: the TV refinement of Eq. 13 moves a pixel toward its
  neighbours where data and surroundings disagree. Factor ``exp(-|refined - matched| / change_px)``,
  ``change_px`` = 0.1 px/view.
- **agreement with the neighbours**: ``exp(-|refined - median5(refined)| / change_px)`` (5x5 median):
  a speck on a thin, textureless pole (the demo scene's) has a sharp valley in the wrong place, but
  it does not agree with the pole around it. A structure at least 3 px wide keeps the median on its
  side; a 1-2 px structure loses confidence here.
- **black holes** (flat pixels whose valley is a plateau: data term dropped, value interpolated by
  the refinement) have neither a valley nor a matched value: they get ``hole_confidence`` (0.5)
  times the neighbour factor, below an exactly matched pixel but kept by a threshold under 0.5 ...
- ... times their **support**: an interpolated value is no surer than the values it is interpolated
  from. ``support`` = the harmonic interpolation (:func:`recon.entropy.refine.harmonic_fill`, the
  same fill the refinement starts from) into the holes of the measured pixels' confidence; factor
  ``min(1, support / hole_support)``. A hole whose rim was matched surely keeps ``hole_confidence``;
  one whose rim is unsure (the rim of a thin textureless pole matched at a wrong disparity, a plain
  floor whose every measured pixel has a wide valley) falls with it; and times
  ``exp(-|grad refined| / hole_ramp)``: a fill that climbs steeply (more than ``hole_ramp`` = 0.1
  px/view per pixel) is a ramp between rims that disagree (one side of a thin pole matched right,
  the other wrong), not a surface.

It is 0 where the disparity is not finite or lies outside the searched range, and where the matched
value sits on the first or last candidate (no minimum inside the range: the true one may lie
outside). ``lfrig export`` leaves out pixels below ``recon.export.MIN_CONFIDENCE`` (0.4).
"""

from __future__ import annotations

import numpy as np

from recon.entropy.median import median_filter_nearest
from recon.entropy.refine import harmonic_fill
from recon.native import call, chosen


def confidence_map(*, refined: np.ndarray, matched: np.ndarray, ambiguity: np.ndarray, step: float,
                   disparity_range: tuple[float, float], holes: np.ndarray | None = None,
                   valley_px: float = 0.3, change_px: float = 0.1,
                   hole_confidence: float = 0.5, hole_support: float = 0.25,
                   hole_ramp: float = 0.1, median: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` float32 confidence in ``[0, 1]`` (see the module docstring).

    Parameters
    ----------
    refined, matched
        ``(H, W)`` final (TV-refined) and matched disparity, pixels per view step.
    ambiguity
        ``(H, W)`` number of candidates within the hole tolerance of the least objective.
    step
        Candidate spacing, pixels per view step.
    disparity_range
        ``(min, max)`` searched; a refined value outside it gets 0.
    holes
        ``(H, W)`` bool black holes (data term dropped), or ``None``.
    valley_px, change_px, hole_confidence, hole_support, hole_ramp
        See the module docstring; ``hole_support`` 0 and ``hole_ramp`` 0 give every hole
        ``hole_confidence`` times the neighbour factor, whatever its rim and slope.
    median
        ``(H, W)`` the 5x5 median of ``refined`` when every value is finite
        (:func:`finite_median5`; made band by band when not given).

    Computed in bands of :data:`BAND_ROWS` rows (float64 temporaries of a band, not of the map,
    but for the neighbour factor at the holes, kept for their own factor); the holes' support is
    filled over the whole map.
    """
    if valley_px <= 0 or change_px <= 0 or step <= 0:
        raise ValueError(f"valley_px, change_px and step must be > 0, got {valley_px}, {change_px}, {step}")
    if not (np.isfinite(hole_ramp) and hole_ramp >= 0):
        raise ValueError(f"hole_ramp must be a finite slope >= 0 (0: off), got {hole_ramp}")
    if not 0 <= hole_support <= 1 or not 0 <= hole_confidence <= 1:
        raise ValueError(f"hole_confidence and hole_support must be in [0, 1], got {hole_confidence}, {hole_support}")
    refined, matched = np.asarray(refined), np.asarray(matched)
    # what a band's own median puts in place of a value that is not finite (unused with ``median``)
    fill = (None if median is not None else
            np.nanmedian(np.asarray(refined, np.float64)) if np.isfinite(refined).any() else 0.0)
    H = refined.shape[0]
    bands = [(y0, min(y0 + BAND_ROWS, H)) for y0 in range(0, H, BAND_ROWS)]
    parts = dict(refined=refined, matched=matched, ambiguity=ambiguity, step=step, disparity_range=disparity_range,
                 fill=fill, valley_px=valley_px, change_px=change_px, median=median)
    out = np.empty(refined.shape, np.float32)
    holes = None if holes is None or not np.any(holes) else np.asarray(holes, bool)
    measured = None if holes is None or hole_support <= 0 else np.empty(refined.shape, np.float32)
    hole_neighbours = []  # per band: the neighbour factor at its holes, for their own factor below
    for y0, y1 in bands:
        conf, neighbours, finite = _band_factors(y0, y1, **parts)
        out[y0:y1] = np.where(_inside(refined[y0:y1], finite, disparity_range), np.nan_to_num(conf), 0.0)
        if holes is not None:
            hole_neighbours.append(neighbours[holes[y0:y1]])
        if measured is not None:
            measured[y0:y1] = np.where(holes[y0:y1] | ~finite, 0.0, np.nan_to_num(conf))
    if holes is None:
        return out
    support = None if measured is None else harmonic_fill(measured, holes)
    del measured
    for (y0, y1), factor in zip(bands, hole_neighbours):
        h = holes[y0:y1]
        factor = hole_confidence * factor
        if support is not None:
            factor = factor * np.clip(support[y0:y1][h].astype(np.float64) / hole_support, 0.0, 1.0)
        if hole_ramp > 0:
            a, b = max(y0 - 1, 0), min(y1 + 1, H)
            halo = np.asarray(refined[a:b], np.float64)
            filled = np.where(np.isfinite(halo), halo, 0.0)
            factor = factor * np.exp(-slope_rows(filled, y0 - a, y1 - a)[h] / hole_ramp)
        r = refined[y0:y1][h]
        out[y0:y1][h] = np.where(_inside(r, np.isfinite(r), disparity_range), np.nan_to_num(factor), 0.0)
    return out


def slope_rows(d: np.ndarray, r0: int, r1: int, *, kernel: str = "auto") -> np.ndarray:
    """Rows ``[r0, r1)`` of ``np.hypot`` of ``np.gradient`` of the finite ``(H, W)`` float64 map ``d``
    along each axis of more than one pixel (0 along one of a pixel): the C kernel
    (``recon/native/confidence.c``, the same bits) where it loads, else numpy (``kernel`` as
    :func:`recon.native.chosen`'s, ``"numba"`` numpy's)."""
    if chosen("confidence", kernel) and d.ndim == 2:
        d = np.ascontiguousarray(d, np.float64)
        H, W = d.shape
        slope = np.empty((max(r1 - r0, 0), W))
        call("confidence", "lfrig_neighbours", d, H, W, r0, r1, 0.0, None, None, slope)
        return slope
    gy, gx = (np.gradient(d, axis=k) if d.shape[k] > 1 else np.zeros_like(d) for k in (0, 1))
    return np.hypot(gy, gx)[r0:r1]


def finite_median5(refined: np.ndarray) -> np.ndarray | None:
    """``(H, W)`` float32 5x5 median of ``refined`` (borders continued by the nearest pixel) when
    it is float32 and every value is finite, else ``None``. What the heuristic's neighbour factor
    and the model's ``log_neighbour`` feature (:mod:`recon.entropy.calibration`) each take: they
    differ only in what they put in place of a value that is not finite, and a float32 map's
    median taken in float64 is the same number."""
    refined = np.asarray(refined)
    if refined.dtype != np.float32 or not np.isfinite(refined).all():
        return None
    return median_filter_nearest(refined, size=5)


def _inside(refined: np.ndarray, finite: np.ndarray, disparity_range: tuple[float, float]) -> np.ndarray:
    """Where ``refined`` is finite (``finite``) and within ``disparity_range`` (to 1e-6)."""
    r = np.asarray(refined, np.float64)
    lo, hi = disparity_range
    return finite & (r >= lo - 1e-6) & (r <= hi + 1e-6)


#: Rows of the map computed at once (each with the rows the 5x5 median and the slope read around it).
BAND_ROWS = 64


def _band_factors(y0: int, y1: int, *, refined, matched, ambiguity, step, disparity_range, fill, valley_px,
                  change_px, median) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows ``[y0, y1)`` of ``(valley * agree * neighbours * ~on_end, neighbours, finite)`` (float64,
    float64, bool), the 5x5 median ``median``'s rows or, when it is ``None``, the median over the
    band with 2 rows around it (non-finite values replaced by ``fill``, the finite values' median),
    the same values as over the whole map."""
    if median is None:
        H = refined.shape[0]
        a, b = max(y0 - 2, 0), min(y1 + 2, H)
        halo = np.asarray(refined[a:b], np.float64)
        median = median_filter_nearest(np.where(np.isfinite(halo), halo, fill), size=5)[y0 - a:y1 - a]
    else:
        median = np.asarray(median[y0:y1], np.float64)
    r = np.asarray(refined[y0:y1], np.float64)
    m = np.asarray(matched[y0:y1], np.float64)
    width = np.maximum(np.asarray(ambiguity[y0:y1], np.float64) - 1, 0) * step
    valley = np.exp(-width / valley_px)
    agree = np.exp(-np.abs(r - m) / change_px)
    neighbours = np.exp(-np.abs(r - median) / change_px)
    lo, hi = disparity_range
    on_end = (np.abs(m - lo) < 0.5 * step) | (np.abs(m - hi) < 0.5 * step)
    return valley * agree * neighbours * ~on_end, neighbours, np.isfinite(r)
