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


def confidence_map(*, refined: np.ndarray, matched: np.ndarray, ambiguity: np.ndarray, step: float,
                   disparity_range: tuple[float, float], holes: np.ndarray | None = None,
                   valley_px: float = 0.3, change_px: float = 0.1,
                   hole_confidence: float = 0.5, hole_support: float = 0.25,
                   hole_ramp: float = 0.1) -> np.ndarray:
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
    """
    if valley_px <= 0 or change_px <= 0 or step <= 0:
        raise ValueError(f"valley_px, change_px and step must be > 0, got {valley_px}, {change_px}, {step}")
    if not (np.isfinite(hole_ramp) and hole_ramp >= 0):
        raise ValueError(f"hole_ramp must be a finite slope >= 0 (0: off), got {hole_ramp}")
    if not 0 <= hole_support <= 1 or not 0 <= hole_confidence <= 1:
        raise ValueError(f"hole_confidence and hole_support must be in [0, 1], got {hole_confidence}, {hole_support}")
    refined = np.asarray(refined, np.float64)
    matched = np.asarray(matched, np.float64)
    finite = np.isfinite(refined)
    width = np.maximum(np.asarray(ambiguity, np.float64) - 1, 0) * step
    valley = np.exp(-width / valley_px)
    agree = np.exp(-np.abs(refined - matched) / change_px)
    median = median_filter_nearest(np.where(finite, refined, np.nanmedian(refined) if finite.any() else 0.0),
                                   size=5)
    neighbours = np.exp(-np.abs(refined - median) / change_px)
    lo, hi = disparity_range
    on_end = (np.abs(matched - lo) < 0.5 * step) | (np.abs(matched - hi) < 0.5 * step)
    conf = valley * agree * neighbours * ~on_end
    if holes is not None and np.any(holes):
        holes = np.asarray(holes, bool)
        factor = hole_confidence * neighbours
        if hole_support > 0:
            measured = np.where(holes | ~finite, 0.0, np.nan_to_num(conf)).astype(np.float32)
            support = harmonic_fill(measured, holes).astype(np.float64)
            factor = factor * np.clip(support / hole_support, 0.0, 1.0)
        if hole_ramp > 0:
            filled = np.where(finite, refined, 0.0)
            gy, gx = (np.gradient(filled, axis=a) if filled.shape[a] > 1 else np.zeros_like(filled)
                      for a in (0, 1))
            factor = factor * np.exp(-np.hypot(gy, gx) / hole_ramp)
        conf = np.where(holes, factor, conf)
    inside = finite & (refined >= lo - 1e-6) & (refined <= hi + 1e-6)
    return np.where(inside, np.nan_to_num(conf), 0.0).astype(np.float32)
