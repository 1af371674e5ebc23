"""The whole matching-entropy estimator: :func:`estimate_disparity`, the phases of
:data:`recon.entropy.plan.PLAN` run on one image (``docs/entropy-method.md`` describes each step):

1. ``initial``: flat pixels (Eq. 12) and the initial disparity ``d0`` from the nine views (the
   centre and the farthest in eight directions);
2. ``layers``: black holes of ``d0`` filled, the search range (the caller's, else the light
   field's, else the robust extent of ``d0``), the noise-limited pixels;
3. ``matching``: views filtered where noise rules, region labels (Eqs. 8-11), windows by matching
   entropy (Eq. 1), the line search of Eqs. 5-7 with sub-step refinement, centroid correction, the
   boundary test;
4. ``refine``: TV refinement of Eq. 13 in smooth regions, the confidence map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recon.entropy.options import DEFAULTS, PRESETS, EntropyOptions, check_options, make_options  # noqa: F401
from recon.entropy.plan import run_plan, start
from recon.entropy.state import State
from recon.errors import ReconError
from recon.lf.lightfield import LightField
from recon.progress import ProgressCallback


@dataclass
class EntropyResult:
    """Output of :func:`estimate_disparity`; every map is ``(H, W)`` over the centre view.

    Attributes
    ----------
    disparity
        Final disparity (float32, pixels per view step): ``matched`` after TV refinement.
    initial_disparity
        Nine-view fixed-window estimate ``d0``.
    matched_disparity
        Line-search result ``d*`` with the adaptive windows, before refinement.
    labels
        uint8 region type: 0 occluding, 1 occluded, 2 texture, 3 smooth (Eq. 8).
    window_size, window_shape, view_set
        uint8 chosen window side (pixels), shape (0 square, 1..8 = W1..W8) and visible-viewpoint
        set (0 all views, k = the set of W_k).
    entropy, cost
        float32 matching entropy of the chosen window and matching cost at the chosen disparity.
    confidence
        float32 in ``[0, 1]``: the probability that the pixel's disparity is within 0.07 px/view of
        the truth (:mod:`recon.entropy.calibration`); ``None`` when stopped before the refinement.
    disparity_range
        ``(min, max)`` searched.
    timings
        Seconds per step.
    options
        The options used.
    """

    disparity: np.ndarray
    initial_disparity: np.ndarray
    matched_disparity: np.ndarray
    labels: np.ndarray
    window_size: np.ndarray
    window_shape: np.ndarray
    view_set: np.ndarray
    entropy: np.ndarray
    cost: np.ndarray
    disparity_range: tuple[float, float]
    timings: dict[str, float]
    options: EntropyOptions
    info: dict = field(default_factory=dict)
    #: ``(H, W)`` float32 probability that :attr:`disparity` is within 0.07 px/view of the truth
    #: (:func:`recon.entropy.calibration.probability_right`); ``None`` before the refinement.
    confidence: np.ndarray | None = None

    @property
    def refined_disparity(self) -> np.ndarray:
        """Alias of :attr:`disparity` (the TV-refined map)."""
        return self.disparity




def _check(lf: LightField, opts: EntropyOptions) -> None:
    U, V = lf.grid_shape
    if U < 3 or V < 3:
        raise ReconError(f"the entropy estimator needs at least a 3x3 grid of views, got {U}x{V}")
    check_options(opts)


def estimate_disparity(lf: LightField, *, options: EntropyOptions | None = None,
                       progress: ProgressCallback | None = None, preset: str | None = None,
                       **overrides) -> EntropyResult:
    """Disparity of the centre view by the matching-entropy method.

    Parameters
    ----------
    lf
        Light field with a grid of at least 3x3 views (``views[u, v, y, x(, c)]``).
    options
        :class:`EntropyOptions`; default :data:`DEFAULTS`.
    progress
        Called as ``progress(fraction, message)`` (:mod:`recon.progress`) with the estimated share
        of the whole run done so far (``0..1``, never decreasing, weighted by each step's expected
        time) at the start of each step and after every candidate disparity of the two line
        searches, which take almost all the time; ``message`` names the current step. Ends with
        ``(1.0, "done")``.
    preset
        A key of :data:`PRESETS` (``"paper"``: the paper's literal configuration) applied before
        ``overrides``; not together with ``options``.
    **overrides
        Any :class:`EntropyOptions` field by name, e.g. ``step=0.05``.

    Returns
    -------
    :class:`EntropyResult` with the disparity (pixels per view step, ``docs/conventions.md`` sign)
    and the intermediate maps.
    """
    opts = make_options(options, preset=preset, **overrides)
    _check(lf, opts)
    return result_of(run_plan(start(lf, opts, progress=progress)))


def result_of(state: State) -> EntropyResult:
    """The :class:`EntropyResult` of a state the whole plan ran on."""
    w = state.windows
    return EntropyResult(
        disparity=state.refined, initial_disparity=state.d0.astype(np.float32),
        matched_disparity=state.matched, labels=state.labels.astype(np.uint8),
        window_size=w["size"].astype(np.uint8), window_shape=w["shape"].astype(np.uint8),
        view_set=w["set"].astype(np.uint8), entropy=w["entropy"], cost=state.cost,
        disparity_range=state.disparity_range, timings=state.timings, options=state.options,
        info={"ambiguity": state.ambiguity, "initial_ambiguity": state.ambiguity0, "holes": state.holes,
              "initial_holes": state.holes0, "noise_limited": state.noise_limited,
              "hole_delta": state.hole_delta, "flat": state.flat,
              "noise_sigma": state.region_info["noise_sigma"],
              "smooth_tolerance_abs": state.region_info["smooth_tolerance_abs"]},
        confidence=state.confidence)
