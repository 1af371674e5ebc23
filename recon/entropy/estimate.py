"""The whole matching-entropy estimator: :func:`estimate_disparity`.

Steps (paper Sections 3-4; ``docs/entropy-method.md`` says which reading each follows):

1. initial disparity ``d0`` from the nine views (centre + farthest in eight directions),
2. search range: the caller's, else the light field's, else the robust extent of ``d0``,
3. region labels (Eqs. 8-12),
4. window per pixel by largest matching entropy (Eq. 1); visible-view set of the shape for occluded
   pixels, all views elsewhere,
5. line search of Eq. 5 over all views with sub-step parabolic refinement (Eqs. 6-7),
6. TV refinement of Eq. 13 in smooth regions.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from recon.entropy.aperture import informative_strips
from recon.entropy.boundary import snap_boundaries
from recon.entropy.calibration import matching_cost, probability_right
from recon.entropy.entropy import quantise_disparity, quantise_grey, select_windows
from recon.entropy.initial import discover_range, initial_disparity, range_from_initial, sure_pixels
from recon.entropy.noise import (filter_flat_views, noise_limited_windows, soften_views,
                                 texture_to_noise, warp_mask_to_views, weak_texture_pixels)
from recon.entropy.matching import (cost_ambiguity, disparity_candidates, joint_line_search,
                                    line_search)
from recon.entropy.windows import N_SHAPES
from recon.entropy.refine import centroid_correction, harmonic_fill, tv_refine, valley_weights
from recon.entropy.windows import STRIP_SHAPES, curvature_size_cap, window_rect
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH
from recon.entropy.regions import flat_pixels, jump_distance, layer_jumps, layer_map, region_labels
from recon.errors import ReconError
from recon.progress import ProgressCallback
from recon.lf.lightfield import LightField


def _opt(default, help: str):
    return field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class EntropyOptions:
    """Every parameter of the estimator; the defaults are the paper's values where it gives one.

    Units: disparities and steps in pixels per view step; window sizes in pixels (odd).
    """

    disparity_range: tuple[float, float] | None = _opt(
        None, "(min, max) disparity to search; default: the light field's, else found from the "
              "initial estimate")
    initial_range: tuple[float, float] = _opt(
        (-8.0, 8.0), "range the initial nine-view search covers when no range is known (with "
                     "discover_range: the range the coarse search covers)")
    discover_range: bool = _opt(
        True, "when no range is known, find it first by a nine-view search on views downsampled "
              "up to 4x (initial.discover_range), then search only that range at full resolution "
              "(else: the whole initial_range at full resolution)")
    initial_step: float = _opt(0.05, "candidate spacing of the initial nine-view search")
    initial_window: int = _opt(5, "window side of the initial nine-view search")
    initial_shiftable: bool = _opt(
        True, "initial search takes the least cost over the square and W1..W8 with their visible "
              "sets (else the square alone)")
    range_percentile: float = _opt(
        0.5, "the search range found from the initial estimate spans its percentiles "
             "[p, 100 - p] ...")
    range_margin: float = _opt(0.25, "... widened by this margin on each side")
    step: float = _opt(
        0.04, "candidate spacing of the line search (refined by a parabola); 0.04 scores as well as "
              "0.02 or better on the bench scenes at half the time (docs/entropy-method.md)")
    layer_gap: float = _opt(
        0.25, "layers (median-filtered initial disparity) closer than this count as one (Eq. 9)")
    occlusion_views: str = _opt(
        "all", "views whose warped layers Eq. 9 compares with the centre: 'nine' (the paper: the "
               "farthest in each direction) or 'all' (also finds pixels hidden only in middle views)")
    layer_median: int = _opt(5, "median filter size applied to the initial disparity for the layers")
    layer_keep_width: float = _opt(
        0.2, "... except at textured (not Eq. 12-flat) pixels where the initial search's cost valley "
             "(candidates within hole_delta of the least cost) is at most this wide: there d0 is "
             "sure and kept unfiltered")
    smooth_neighbourhood: int = _opt(5, "side of the square neighbourhood of psi (Eq. 12)")
    smooth_tolerance: float = _opt(
        2.0, "grey values differ (Eq. 12) when they differ by more than this times the noise sigma")
    grey_bins: int = _opt(32, "grey-level histogram bins of the matching entropy (Eq. 1)")
    disparity_bin: float = _opt(0.1, "bin width of the initial-disparity histogram (Eq. 1)")
    window_sizes: tuple[int, ...] = _opt((3, 5, 7, 9, 11, 13, 15), "window sizes searched")
    alpha1: float = _opt(1.0, "weight of the disparity-consistency term (Eq. 1)")
    alpha2_occlusion: float = _opt(1.0, "weight of the anti-occlusion term in occlusion regions")
    alpha2_other: float = _opt(0.0, "weight of the anti-occlusion term elsewhere")
    strip_windows: bool = _opt(
        True, "also offer one-pixel strips along the rows/columns with the views in line with them "
              "(lfrig's extension for gaps between two occluders)")
    side_windows: str = _opt(
        "edges", "where texture and smooth pixels are offered the side windows and strips besides "
                 "the square: 'occlusion' (the paper: nowhere, square only), 'edges' (at the sizes "
                 "whose square would reach a jump of the layer map) or 'everywhere'")
    side_jump: float = _opt(
        0.3, "for side_windows='edges': a difference of the layer map between neighbouring pixels "
             "larger than this is a jump")
    single_layer_windows: bool = _opt(
        True, "texture and smooth pixels are not offered windows that reach another layer of the "
              "layer map (a rich texture across a depth edge otherwise draws the window to it)")
    crease_tolerance: float = _opt(
        0.01, "texture and smooth pixels are not offered a square window whose mean layer value "
             "differs from the smallest square's by more than this (px/view): on a ridge, pit, crease "
             "or curved surface a square finds the mean disparity under it, not the pixel's (a "
             "plane alone does not count; not at noise-limited pixels, whose layer value is a fill); "
             "0: off (the paper)")
    crease_noise: float = _opt(
        1.5, "... raised to this many times the local noise of the initial disparity (robust, over "
             "the largest window; recon.entropy.windows.curvature_size_cap): render noise makes the "
             "layer means wander without a crease (0: the fixed tolerance alone)")
    visible_sets: str = _opt(
        "occluded", "which pixels match over their window shape's visible-viewpoint set (others use "
                    "all views): 'none', 'occluded' (the paper), 'occlusion' (occluded and "
                    "occluding) or 'all'")
    joint: bool = _opt(
        True, "minimise Eq. 7 jointly over disparity and window (else: window by largest entropy "
              "first, then the line search with it)")
    lambda_entropy: float = _opt(1.0, "lambda of Eq. 6 (weight of the matching entropy)")
    intensity_scale: float = _opt(
        255.0, "grey values enter the matching cost in these units (255: 8-bit levels)")
    centroid_correction: bool = _opt(
        True, "move each side window's estimate from the window's centroid back to the pixel with "
              "the slope of a plane fitted to the matched disparity over the window")
    centroid_max_residual: float = _opt(
        0.05, "no centroid correction where that plane fits worse than this RMS (px/view)")
    gamma: float = _opt(0.2, "TV weight of the refinement (Eq. 13)")
    fill_holes: bool = _opt(
        True, "black holes (Eq. 12-flat pixels whose matching cost curve is flat) get no data term: "
              "the initial estimate there is filled from its surroundings before the layers are "
              "made, and the TV refinement fills them in the final map")
    hole_width: float = _opt(
        0.3, "a pixel's cost curve is flat (no information) when the candidates within hole_delta "
             "of its least cost span more than this disparity width ...")
    initial_hole_width: float = _opt(
        0.6, "the same width for the initial nine-view search (its small windows and few views "
             "give wider valleys)")
    hole_delta: float = _opt(0.5, "... with hole_delta in grey levels ...")
    hole_delta_noise: float = _opt(
        0.2, "... or this times the noise sigma in grey levels, whichever is larger")
    tv_iterations: int = _opt(300, "primal-dual iterations of the TV refinement")
    noise_filter: float = _opt(
        1.5, "Gaussian sigma (px) applied, before the line search, to the views where noise-limited "
             "pixels (see noise_gate) land and the view is noise-limited too: there the noise, not "
             "the texture, shapes the cost curve (0: off, the paper; see docs/entropy-method.md)")
    strip_aperture: float = _opt(
        1.5, "a strip window is offered (see strip_aperture_scope) only where the centre view "
             "varies along it: the mean absolute difference of neighbouring pixels along the strip, "
             "over strip_aperture_length pixels, must exceed this times what noise alone gives "
             "(2 sigma / sqrt(pi)), at least half a grey level; a strip matches over the views in "
             "line with it only, so a structure that does not vary along it (a thin pole, an edge "
             "along the strip) matches at every disparity (recon/entropy/aperture.py; 0: strips "
             "everywhere, as before)")
    strip_aperture_scope: str = _opt(
        "initial", "where strip_aperture gates the strips: 'initial' (the nine-view search, whose "
                   "5-px strips over three views in line are the most easily fooled, and whose "
                   "estimate sets the search range and the layers) or 'all' (also the full line "
                   "search: better on occlusion-v1, worse on suite/noisy)")
    strip_aperture_length: int = _opt(
        31, "length (pixels, odd) over which strip_aperture measures the variation along a strip "
            "(at least the strip's own size)")
    hole_support: float = _opt(
        0.25, "confidence map only: a black hole's confidence (0.5) is scaled by min(1, s / this), "
              "s = the measured pixels' confidence interpolated into the hole (an interpolated value "
              "is no surer than its sources; recon/entropy/confidence.py; 0: off)")
    hole_ramp: float = _opt(
        0.1, "confidence map only: a black hole's confidence is also scaled by "
             "exp(-|grad d| / this) (px/view per pixel): a steep fill is a ramp between rims that "
             "disagree (0: off)")
    flat_windows: str = _opt(
        "largest", "windows offered to noise-limited pixels: 'largest' (those of the largest size "
                   "offered, the square where it is: the least noisy cost where there is no texture "
                   "to choose by) or 'all' (the same as the other pixels, the paper)")
    noise_gate: str = _opt(
        "texture", "which pixels are noise-limited: 'texture' (the filtered "
                   "gradient energy over the largest window below noise_texture_ratio times the "
                   "noise's: nothing but noise in the window) or 'holes' (the first version: "
                   "Eq. 12-flat and no valley in the initial cost; also catches specular surfaces "
                   "and thin textureless structures next to texture)")
    noise_texture_ratio: float = _opt(
        4.0, "for noise_gate='texture': a window is noise-limited when its filtered gradient energy "
             "is below this many times that of the noise alone (1 = pure noise)")
    weak_texture_filter: float = _opt(
        0.6, "Gaussian sigma (px) applied, before the line search, to the views where pixels of weak "
             "texture (below weak_texture_ratio) land: bilinear sampling averages noise more at half "
             "pixels than at whole ones, which pulls a noisy surface's cost minimum towards "
             "half-pixel shifts; a mild filter correlates the noise so the pull goes, and keeps the "
             "texture (0: off, the paper; see docs/entropy-method.md)")
    weak_texture_ratio: float = _opt(
        12.0, "weak_texture_filter applies where the filtered gradient energy over the largest window "
              "(as for noise_texture_ratio) is below this many times the noise's")
    boundary_snap: bool = _opt(
        True, "after matching, test each pixel whose value lies more than boundary_jump above a "
              "neighbour's by its own grey value: over the views that would see it at the "
              "neighbour's (farther) value, does that value fit it clearly better than its own? "
              "Then it takes it (a window fattens the near surface by a pixel; "
              "recon/entropy/boundary.py)")
    boundary_snap_initial: bool = _opt(
        False, "the same test on the (hole-filled) initial disparity d0 before the layers and labels "
               "are made from it (over the initial search range): better on the blender-dev scenes, "
               "worse on backgammon's BadPix and some suite scenes (docs/entropy-method.md)")
    boundary_jump: float = _opt(
        0.5, "... a pixel is tested when its matched value exceeds the least of its 3x3 "
             "neighbourhood by more than this (px/view)")
    boundary_support: int = _opt(
        6, "... and that least value is shared (within 0.1 px/view) by at least this many pixels of "
           "the 5x5 neighbourhood (a surface behind, not an outlier)")
    boundary_confidence: float = _opt(
        3.0, "... and the farther value wins by more than this many standard errors of noise "
             "(sigma / sqrt(views)) of the mean absolute grey difference")
    boundary_mix: float = _opt(
        0.4, "... or the pixel's centre grey value holds less than this fraction of the near "
             "surface's: alpha = (c - B) / (F - B), B = the far surface's grey value there (median "
             "over the views that see it), F = the near neighbour's opposite; the truth is the "
             "surface at the pixel centre, which an anti-aliased rim pixel with alpha < 0.5 shows "
             "behind it (0.4, not 0.5: a margin for shading and texture at a silhouette; 0: off)")
    boundary_mix_contrast: float = _opt(
        12.0, "... alpha is used only where |F - B| is at least this many noise sigmas")
    boundary_mix_extrapolate: bool = _opt(
        True, "... F is the near surface's grey carried on linearly to the pixel (2 F - F2, F2 two "
              "pixels inside), so that shading towards a silhouette is not read as mixing "
              "(occlusion-v1's metal post; docs/entropy-method.md, 'Boundaries')")
    valley_weights: bool = _opt(
        True, "pixels whose matching cost valley is wide join the TV refinement with the data weight "
              "(hole_width / valley width)^2, the curvature of their cost, instead of none (black "
              "holes) or a fixed value (outside the smooth region); noise-limited black holes keep "
              "no data term (recon.entropy.refine.valley_weights; needs fill_holes)")
    unsure_width: float = _opt(
        0.6, "... a pixel that is not Eq. 12-flat joins when its valley is wider than this (px/view)")


#: The defaults, for the command line to turn into flags (``dataclasses.fields(EntropyOptions)``
#: gives each name, type, default and ``metadata["help"]``).
DEFAULTS = EntropyOptions()

#: Named option sets. ``"paper"`` is the paper's literal configuration as far as the text fixes one
#: (``docs/entropy-method.md``, "Deviations"): region labels from the median-filtered layers and the
#: nine views, the square window alone in texture and smooth regions, W1..W8 (no strips) in occlusion
#: regions, window first by largest entropy and then the line search (Eqs. 6-7 read as two steps),
#: every pixel's data term kept in Eq. 13 (no black-hole filling), no centroid correction, 256 grey
#: bins. Where the paper leaves a choice open (the initial estimate, the noise tolerance of Eq. 12)
#: it keeps lfrig's reading.
PRESETS: dict[str, dict] = {
    "default": {},
    "paper": {"occlusion_views": "nine", "strip_windows": False, "side_windows": "occlusion",
              "single_layer_windows": False, "layer_keep_width": 0.0, "joint": False,
              "centroid_correction": False, "fill_holes": False, "grey_bins": 256,
              "noise_filter": 0.0, "flat_windows": "all", "crease_tolerance": 0.0,
              "weak_texture_filter": 0.0, "boundary_snap": False, "valley_weights": False},
}


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


#: Values of :attr:`EntropyOptions.side_windows`.
SIDE_WINDOW_SCOPES = ("occlusion", "edges", "everywhere")
#: Values of :attr:`EntropyOptions.flat_windows`.
FLAT_WINDOW_SCOPES = ("largest", "all")
#: Values of :attr:`EntropyOptions.strip_aperture_scope`.
STRIP_APERTURE_SCOPES = ("initial", "all")
#: Values of :attr:`EntropyOptions.noise_gate`.
NOISE_GATES = ("texture", "holes")
#: Values of :attr:`EntropyOptions.visible_sets`.
VISIBLE_SET_SCOPES = ("none", "occluded", "occlusion", "all")


class _Reporter:
    """Turns the estimator's steps into one overall fraction for ``progress`` (:mod:`recon.progress`).

    Each step has a weight in "initial-candidate units" (the time one candidate of the nine-view
    search takes): a candidate of the full line search costs :data:`MATCH_CANDIDATE_WEIGHT` of them
    (81 views and up to 77 windows against 9 views and 11), and the fixed steps a measured share
    (2-core machine, 512x512, backgammon: initial 2.5 s for 52 candidates, matching 10 s for 121,
    regions 0.2 s, windows 1.5 s, TV 1 s; the TV refinement compiled since: ~0.25 s with the
    confidence map). The fraction never goes back.
    """

    FIXED = {"regions": 4.0, "windows": 30.0, "refine": 5.0}

    def __init__(self, report, n_initial: int, n_matching: int) -> None:
        self.report = report
        self.weights = {"initial": float(n_initial), **self.FIXED,
                        "matching": MATCH_CANDIDATE_WEIGHT * n_matching}
        self.order = ["initial", "regions", "windows", "matching", "refine"]
        self.current = "initial"
        self.note = ""
        self.last = 0.0

    def set_matching(self, n_matching: int) -> None:
        self.weights["matching"] = MATCH_CANDIDATE_WEIGHT * n_matching

    def _emit(self, within: float) -> None:
        if self.report is None:
            return
        before = sum(self.weights[k] for k in self.order[:self.order.index(self.current)])
        total = sum(self.weights.values())
        fraction = min(max((before + within * self.weights[self.current]) / total, self.last), 1.0)
        self.last = fraction
        self.report(fraction, self.note)

    def step(self, name: str, message: str) -> None:
        self.current = name
        self.note = message
        self._emit(0.0)

    def within(self, fraction: float) -> None:
        self._emit(fraction)

    def done(self) -> None:
        self.current = self.order[-1]
        self.note = "done"
        self._emit(1.0)


#: Time of one full line-search candidate in units of one nine-view candidate (see ``_Reporter``).
MATCH_CANDIDATE_WEIGHT = 1.8


def make_options(options: EntropyOptions | None = None, *, preset: str | None = None,
                 **overrides) -> EntropyOptions:
    """``options`` (default :data:`DEFAULTS`, or the named :data:`PRESETS` entry ``preset`` applied
    to the defaults) with ``overrides`` applied; unknown names raise."""
    if preset is not None:
        if options is not None:
            raise ValueError("give either options or preset, not both")
        if preset not in PRESETS:
            raise ValueError(f"unknown entropy preset {preset!r}; choose one of {', '.join(PRESETS)}")
        options = dataclasses.replace(DEFAULTS, **PRESETS[preset])
    base = DEFAULTS if options is None else options
    names = {f.name for f in dataclasses.fields(EntropyOptions)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ValueError(f"unknown entropy option(s) {unknown}; valid names: {sorted(names)}")
    return dataclasses.replace(base, **overrides)


def _check(lf: LightField, opts: EntropyOptions) -> None:
    U, V = lf.grid_shape
    if U < 3 or V < 3:
        raise ReconError(f"the entropy estimator needs at least a 3x3 grid of views, got {U}x{V}")
    check_options(opts)


def check_options(opts: EntropyOptions) -> None:
    """Raise ``ValueError`` naming an option value the estimator cannot use."""
    sizes = opts.window_sizes
    if not sizes or any(s < 3 or s % 2 == 0 for s in sizes):
        raise ValueError(f"window_sizes must be odd sizes >= 3, got {sizes}")
    if opts.step <= 0 or opts.initial_step <= 0:
        raise ValueError(f"step and initial_step must be > 0, got {opts.step}, {opts.initial_step}")
    if opts.side_windows not in SIDE_WINDOW_SCOPES:
        raise ValueError(f"side_windows must be one of {SIDE_WINDOW_SCOPES}, got {opts.side_windows!r}")
    if opts.visible_sets not in VISIBLE_SET_SCOPES:
        raise ValueError(f"visible_sets must be one of {VISIBLE_SET_SCOPES}, got {opts.visible_sets!r}")
    if opts.flat_windows not in FLAT_WINDOW_SCOPES:
        raise ValueError(f"flat_windows must be one of {FLAT_WINDOW_SCOPES}, got {opts.flat_windows!r}")
    if opts.strip_aperture_scope not in STRIP_APERTURE_SCOPES:
        raise ValueError(f"strip_aperture_scope must be one of {STRIP_APERTURE_SCOPES}, got {opts.strip_aperture_scope!r}")
    if opts.strip_aperture_length < 1 or opts.strip_aperture_length % 2 == 0:
        raise ValueError(f"strip_aperture_length must be odd and >= 1, got {opts.strip_aperture_length}")
    if not (np.isfinite(opts.hole_ramp) and opts.hole_ramp >= 0):
        raise ValueError(f"hole_ramp must be a finite slope >= 0 px/view per pixel (0: off), got {opts.hole_ramp}")
    if not 0 <= opts.hole_support <= 1:
        raise ValueError(f"hole_support must be in [0, 1] (0: off), got {opts.hole_support}")
    if not (np.isfinite(opts.strip_aperture) and opts.strip_aperture >= 0):
        raise ValueError(f"strip_aperture must be a finite factor >= 0 (0: off), got {opts.strip_aperture}")
    if opts.noise_gate not in NOISE_GATES:
        raise ValueError(f"noise_gate must be one of {NOISE_GATES}, got {opts.noise_gate!r}")
    if not opts.noise_texture_ratio > 0:
        raise ValueError(f"noise_texture_ratio must be > 0 (1 = pure noise), got {opts.noise_texture_ratio}")
    if not opts.noise_filter >= 0:
        raise ValueError(f"noise_filter must be a sigma >= 0 pixels (0: off), got {opts.noise_filter}")
    if not opts.weak_texture_filter >= 0:
        raise ValueError(f"weak_texture_filter must be a sigma >= 0 pixels (0: off), got {opts.weak_texture_filter}")
    if not opts.weak_texture_ratio > 0:
        raise ValueError(f"weak_texture_ratio must be > 0 (1 = pure noise), got {opts.weak_texture_ratio}")
    if not (np.isfinite(opts.unsure_width) and opts.unsure_width > 0):
        raise ValueError(f"unsure_width must be a valley width > 0 px/view, got {opts.unsure_width}")
    if not 0 <= opts.boundary_mix <= 1 or not opts.boundary_mix_contrast >= 0:
        raise ValueError(f"boundary_mix must be a fraction in [0, 1] (0: off) and boundary_mix_contrast "
                         f">= 0 noise sigmas; got {opts.boundary_mix}, {opts.boundary_mix_contrast}")
    if not (opts.boundary_jump > 0 and opts.boundary_confidence >= 0 and 1 <= opts.boundary_support <= 25):
        raise ValueError(f"boundary_jump must be > 0 px/view, boundary_confidence >= 0 and boundary_support "
                         f"1..25 pixels; got {opts.boundary_jump}, {opts.boundary_confidence}, "
                         f"{opts.boundary_support}")
    rng = opts.disparity_range
    if rng is not None and not rng[0] < rng[1]:
        raise ValueError(f"disparity_range must be (min, max) with min < max, got {rng}")


def estimate_disparity(lf: LightField, *, options: EntropyOptions | None = None,
                       progress: ProgressCallback | None = None,
                       noise_sigma: float | None = None,
                       initial: tuple[np.ndarray, np.ndarray] | None = None,
                       disparity_origin: float | None = None,
                       noise_limited: np.ndarray | None = None,
                       stop_after: str | None = None,
                       preset: str | None = None,
                       **overrides) -> EntropyResult:
    """Disparity of the centre view by the matching-entropy method.

    Parameters
    ----------
    lf
        Light field with a grid of at least 3x3 views (``views[u, v, y, x(, c)]``).
    options
        :class:`EntropyOptions`; default :data:`DEFAULTS` (the paper's values).
    progress
        Called as ``progress(fraction, message)`` (:mod:`recon.progress`) with the estimated share of the whole
        run done so far (``0..1``, never decreasing, weighted by each step's expected time) at the
        start of each step and after every candidate disparity of the two line searches, which
        take almost all the time; ``message`` names the current step. Ends with ``(1.0, "done")``.
    noise_sigma, initial, disparity_origin, stop_after
        For tiling (``recon.scale.tiles``; the default ``None`` computes everything here, from this
        light field). ``noise_sigma``: the centre view's noise sigma in ``[0, 1]`` grey units
        (default: estimated from this centre view). ``stop_after="initial"``: return after the raw
        nine-view search (``initial_disparity`` not hole-filled; ``info`` has
        ``initial_ambiguity`` and ``flat``), the whole-image step :func:`fill_initial` is the
        caller's. ``initial=(d0, ambiguity0)``: an already filled initial estimate (skips the
        initial search). ``disparity_origin``: bin origin of the disparity histogram (default the
        layer map's minimum, :func:`layer_origin`). ``noise_limited``: the ``(H, W)`` bool mask of
        :func:`noise_limited_pixels` of the whole image (its window-scale test reaches 2-3 window
        radii; default: computed here). ``stop_after="matching"``: return before the whole-image
        refinement (``disparity`` is the matched map; :func:`refine_global` finishes).
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
    if stop_after not in (None, "initial", "matching"):
        raise ValueError(f"stop_after must be None, 'initial' or 'matching', got {stop_after!r}")
    timings: dict[str, float] = {}
    t = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t
        now = time.perf_counter()
        timings[name] = now - t
        t = now

    gray = np.ascontiguousarray(lf.gray(), dtype=np.float32)
    U, V, H, W = gray.shape
    lap("load")

    u0, v0 = U // 2, V // 2
    flat, flat_info = flat_pixels(gray[u0, v0], size=opts.smooth_neighbourhood,
                                  tolerance=opts.smooth_tolerance, sigma=noise_sigma)
    noise = flat_info["noise_sigma"]
    raw_gray = gray  # the unfiltered views; dropped once filtered (read again from lf for the boundary test)
    raw_centre = gray[u0, v0].copy()
    hole_delta = hole_tolerance(opts, noise)
    known = opts.disparity_range or lf.disparity_range
    initial_rng = known if known is not None else opts.initial_range
    if known is not None:  # search a little beyond a known range: edges of the range are refined
        initial_rng = (known[0] - opts.initial_step, known[1] + opts.initial_step)
    elif opts.discover_range and initial is None:
        initial_rng = unknown_range(gray, options=opts, noise_sigma=noise)
    n_initial = len(disparity_candidates(initial_rng[0], initial_rng[1], opts.initial_step))
    guess = known if known is not None else initial_rng
    reporter = _Reporter(progress, n_initial,
                         len(disparity_candidates(guess[0], guess[1], opts.step)))
    reporter.step("initial", "initial disparity (nine views)")
    holes0 = None
    if initial is None:
        strip_ok0 = _strip_ok(gray[u0, v0], (opts.initial_window,), noise, opts)
        strip_ok0 = None if strip_ok0 is None else strip_ok0[..., 0]
        d0, _, ambiguity0 = initial_disparity(
            gray, disparity_range=initial_rng, step=opts.initial_step, window=opts.initial_window,
            shiftable=opts.initial_shiftable, strips=opts.strip_windows,
            ambiguity_delta=hole_delta / opts.intensity_scale, progress=reporter.within,
            strip_ok=strip_ok0)
        if stop_after == "initial":
            lap("initial")
            return _partial(d0, flat, ambiguity0, noise, timings, opts, known or initial_rng)
        d0, holes0 = fill_initial(d0, ambiguity0, flat, options=opts)
    else:
        d0, ambiguity0 = (np.asarray(a) for a in initial)
        if d0.shape != (H, W) or ambiguity0.shape != (H, W):
            raise ValueError(f"initial maps must be {H}x{W} like the views, got {d0.shape[::-1]}")
    if opts.boundary_snap_initial:  # docs/entropy-method.md, "Boundaries"
        d0 = _snap(raw_gray, d0, noise, initial_rng, opts)
    # Noise-limited pixels (docs/entropy-method.md): matched on views filtered where they land,
    # with the largest window.
    if noise_limited is None:
        noise_limited = noise_limited_pixels(raw_gray[u0, v0], flat, ambiguity0, noise=noise, options=opts)
    elif noise_limited.shape != (H, W):
        raise ValueError(f"noise_limited must be {H}x{W} like the views, got {noise_limited.shape[::-1]}")
    if opts.noise_filter > 0 and noise_limited.any():
        texture = opts.noise_gate == "texture"
        gray = filter_flat_views(raw_gray, sigma_px=opts.noise_filter, noise_sigma=noise,
                                 size=opts.smooth_neighbourhood, tolerance=opts.smooth_tolerance,
                                 where=warp_mask_to_views(noise_limited, d0, (U, V)),
                                 texture_ratio=opts.noise_texture_ratio if texture else None,
                                 radius_px=max(opts.window_sizes) // 2)
    if opts.weak_texture_filter > 0:  # the rest of the weak texture, mildly
        weak = weak_texture_pixels(_texture_ratio(raw_centre, noise, opts),
                                   texture_ratio=opts.weak_texture_ratio) & ~noise_limited
        if weak.any():
            gray = soften_views(gray, sigma_px=opts.weak_texture_filter,
                                where=warp_mask_to_views(weak, d0, (U, V)),
                                # in place (one copy of the views, not two) unless they are lf's own
                                out=None if np.shares_memory(gray, lf.views) else gray)
            raw_gray = None
    if gray is not raw_gray:
        raw_gray = None
    lap("initial")
    if known is not None:
        rng = (float(known[0]), float(known[1]))
    else:
        rng = range_from_initial(d0, percentile=opts.range_percentile, margin=opts.range_margin,
                                 limits=initial_rng, grid_shape=(U, V),
                                 sure=sure_pixels(ambiguity0, step=opts.initial_step,
                                                  width=opts.initial_hole_width))

    reporter.step("regions", "region types")
    labels, region_info = region_labels(
        np.broadcast_to(raw_centre, (U, V, H, W)), d0, layer_gap=opts.layer_gap, layer_median=opts.layer_median,
        smooth_neighbourhood=opts.smooth_neighbourhood, smooth_tolerance=opts.smooth_tolerance,
        occlusion_views=opts.occlusion_views, noise=noise,
        keep=_layer_keep(ambiguity0, flat, opts))
    lap("regions")

    reporter.step("windows", "window selection (matching entropy)")
    grey_q = quantise_grey(raw_centre, opts.grey_bins)
    disp_q = quantise_disparity(region_info["layers"], opts.disparity_bin, origin=disparity_origin)
    sizes = tuple(sorted(opts.window_sizes))
    if opts.side_windows == "edges":
        side_radius = jump_distance(layer_jumps(region_info["layers"], layer_gap=opts.side_jump))
    else:
        side_radius = None if opts.side_windows == "occlusion" else np.zeros((H, W), np.int64)
    shape_map, size_map, entropy, all_entropy = select_windows(
        grey_q, disp_q, labels, sizes=sizes, alpha1=opts.alpha1,
        alpha2_occlusion=opts.alpha2_occlusion, alpha2_other=opts.alpha2_other,
        strips=opts.strip_windows, side_radius=side_radius,
        layers=region_info["layers"] if opts.single_layer_windows else None,
        layer_gap=opts.layer_gap, return_all=True,
        max_size=None if opts.crease_tolerance <= 0 else np.where(
            noise_limited, max(sizes),  # a harmonic fill there: its curvature was not measured
            curvature_size_cap(region_info["layers"], sizes, tolerance=opts.crease_tolerance,
                               measured=~noise_limited, initial=d0,
                               noise_factor=opts.crease_noise)))
    lap("windows")

    candidates = disparity_candidates(rng[0], rng[1], opts.step)
    reporter.set_matching(len(candidates))
    reporter.step("matching", f"line search over [{rng[0]:.2f}, {rng[1]:.2f}] step {opts.step}")
    occluded = {"none": np.zeros(labels.shape, bool), "occluded": labels == OCCLUDED,
                "occlusion": (labels == OCCLUDED) | (labels == OCCLUDING),
                "all": np.ones(labels.shape, bool)}[opts.visible_sets]
    if opts.joint:
        windows = [(s, z) for s in range(N_SHAPES if opts.strip_windows else 9) for z in sizes]
        matched, cost, k, ambiguity = joint_line_search(  # penalty: a temporary, freed in there
            gray, candidates, windows=windows,
            penalty=_gate_strips_if(_search_penalty(all_entropy, noise_limited, opts, len(sizes)),
                                    raw_centre, sizes=sizes, noise=noise, opts=opts),
            use_shape_set=occluded, intensity_scale=opts.intensity_scale,
            ambiguity_delta=hole_delta, progress=reporter.within)
        shape_map = k // len(sizes)
        size_map = np.asarray(sizes)[k % len(sizes)]
        entropy = np.take_along_axis(all_entropy, k[..., None], 2)[..., 0]
    del all_entropy
    set_map = np.where(occluded, shape_map, 0)
    if not opts.joint:
        matched, cost, costs = line_search(gray, candidates, shape_map=shape_map,
                                           size_map=size_map, set_map=set_map, return_costs=True,
                                           progress=reporter.within)
        ambiguity = cost_ambiguity(costs, hole_delta / opts.intensity_scale)
        del costs
    if opts.centroid_correction:
        rect_table = np.array([[window_rect(sh, z) if z % 2 else (0, 0, 0, 0)
                                for z in range(max(sizes) + 1)] for sh in range(N_SHAPES)], np.int64)
        matched = centroid_correction(matched, rect_table[shape_map, size_map],
                                      max_residual=opts.centroid_max_residual, max_shift=opts.step * 10)
    if opts.boundary_snap:  # docs/entropy-method.md, "Boundaries"
        gray = None  # the matching's views: the test reads the unfiltered ones
        matched = _snap(np.ascontiguousarray(lf.gray(), dtype=np.float32) if raw_gray is None else raw_gray,
                        matched, noise, rng, opts)
    lap("matching")

    if stop_after == "matching":
        refined, holes, confidence = matched, None, None
    else:
        reporter.step("refine", "TV refinement of smooth regions")
        refined, holes = refine_global(matched, labels, flat, ambiguity, options=opts,
                                       no_data=no_data_pixels(raw_centre, noise_limited,
                                                              noise=noise, options=opts),
                                       disparity_range=rng)
        confidence = probability_right(  # recon/entropy/calibration.py
            refined=refined, matched=matched, initial=d0, ambiguity=ambiguity, labels=labels,
            holes=holes, noise_limited=noise_limited, window_size=size_map,
            cost=matching_cost(cost, entropy, lambda_entropy=opts.lambda_entropy,
                               intensity_scale=opts.intensity_scale),
            noise_sigma=noise, step=opts.step, disparity_range=rng, valley_px=opts.hole_width,
            hole_support=opts.hole_support, hole_ramp=opts.hole_ramp)
        lap("refine")
        reporter.done()

    return EntropyResult(
        disparity=refined, initial_disparity=d0.astype(np.float32),
        matched_disparity=matched, labels=labels.astype(np.uint8),
        window_size=size_map.astype(np.uint8), window_shape=shape_map.astype(np.uint8),
        view_set=set_map.astype(np.uint8), entropy=entropy, cost=cost, disparity_range=rng,
        timings=timings, options=opts,
        info={"ambiguity": ambiguity, "initial_ambiguity": ambiguity0, "holes": holes,
              "noise_limited": noise_limited,
              "initial_holes": holes0, "hole_delta": hole_delta, "flat": flat,
              "noise_sigma": region_info["noise_sigma"],
              "smooth_tolerance_abs": region_info["smooth_tolerance_abs"]},
        confidence=confidence)


def _snap(gray: np.ndarray, disparity: np.ndarray, noise: float, rng: tuple[float, float],
          opts: EntropyOptions) -> np.ndarray:
    """:func:`recon.entropy.boundary.snap_boundaries` with the options' parameters."""
    return snap_boundaries(gray, disparity, noise_sigma=noise, disparity_range=rng,
                           jump=opts.boundary_jump, support=opts.boundary_support,
                           confidence=opts.boundary_confidence, mix=opts.boundary_mix,
                           mix_contrast=opts.boundary_mix_contrast,
                           mix_extrapolate=opts.boundary_mix_extrapolate)[0]


def _search_penalty(all_entropy: np.ndarray, noise_limited: np.ndarray, opts: EntropyOptions,
                    n_sizes: int) -> np.ndarray:
    """``(H, W, K)`` float32 penalty of the joint search: ``-lambda E`` (``inf``: window not
    offered), with ``flat_windows="largest"`` applied. The float32 product of ``E`` and ``-lambda``
    (what numpy makes of ``-lambda * E``) in one pass, without a float temporary of the volume (a
    float64 one was once the run's largest allocation; a masked ``np.where`` by rows took 0.25 s)."""
    with np.errstate(invalid="ignore"):  # lambda = 0 times -inf: NaN, set to inf below
        out = np.multiply(all_entropy, np.float32(-opts.lambda_entropy), dtype=np.float32)
    out[~np.isfinite(all_entropy)] = np.inf
    if opts.flat_windows == "largest":
        out = _largest_windows_only(out, noise_limited, n_sizes)
    return out


def hole_tolerance(options: EntropyOptions, noise_sigma: float) -> float:
    """How far above a cost curve's least value a candidate still counts as part of its valley, in
    the cost's units (``intensity_scale``): ``hole_delta``, or ``hole_delta_noise`` times the
    noise sigma (``[0, 1]`` grey units) if that is larger."""
    return max(options.hole_delta, options.hole_delta_noise * noise_sigma * options.intensity_scale)


def unknown_range(gray: np.ndarray, *, options: EntropyOptions, noise_sigma: float
                  ) -> tuple[float, float]:
    """The range the initial search covers when nobody gave one: :func:`initial.discover_range`
    over ``options.initial_range`` with the estimator's own window, step, percentiles and hole
    tolerance (``noise_sigma`` of the centre view in ``[0, 1]`` grey units)."""
    hole_delta = hole_tolerance(options, noise_sigma)
    return discover_range(gray, search_range=options.initial_range, step=options.initial_step,
                          window=options.initial_window, percentile=options.range_percentile,
                          margin=options.range_margin, shiftable=options.initial_shiftable,
                          strips=options.strip_windows,
                          ambiguity_delta=hole_delta / options.intensity_scale,
                          sure_width=options.initial_hole_width)


def _largest_windows_only(penalty: np.ndarray, flat: np.ndarray, n_sizes: int) -> np.ndarray:
    """``penalty`` ``(H, W, K)`` (window ``k`` has shape ``k // n_sizes`` and the ``k % n_sizes``-th
    size, smallest first; ``inf`` = not offered) with every window but those of the largest offered
    size barred at the ``flat`` pixels (the square alone where it is offered, as Eq. 12 gives the
    smooth region). A flat window's cost curve is noise: offered several windows, the joint minimum
    picks whichever window's noise dips lowest, most often the smallest and noisiest."""
    ys, xs = np.nonzero(flat)  # only those pixels change (none on most textured scenes)
    if ys.size == 0:
        return penalty
    sub = penalty[ys, xs]
    N, K = sub.shape
    by_size = np.isfinite(sub).reshape(N, K // n_sizes, n_sizes)
    offered = by_size.any(axis=1)
    largest = n_sizes - 1 - np.argmax(offered[:, ::-1], axis=1)
    size_of = np.arange(K) % n_sizes
    bar = size_of[None, :] != largest[:, None]
    has_square = by_size[np.arange(N), 0, largest]
    bar |= has_square[:, None] & (np.arange(K) >= n_sizes)[None, :]
    out = penalty.astype(np.float32, copy=True)
    out[ys, xs] = np.where(bar, np.inf, sub)
    return out


#: Least variation along a strip that counts as texture: Eq. 12's floor, half an 8-bit grey level.
STRIP_FLOOR = 0.5 / 255


def _strip_ok(centre: np.ndarray, sizes: tuple[int, ...], noise: float,
              opts: EntropyOptions) -> np.ndarray | None:
    """``(H, W, 2, len(sizes))`` :func:`informative_strips`, or ``None`` when not gated."""
    if not opts.strip_windows or opts.strip_aperture == 0:
        return None
    return informative_strips(centre, sizes=sizes, noise_sigma=noise, factor=opts.strip_aperture,
                              floor=STRIP_FLOOR, length=opts.strip_aperture_length)


def _gate_strips_if(penalty: np.ndarray, centre: np.ndarray, *, sizes: tuple[int, ...], noise: float,
                    opts: EntropyOptions) -> np.ndarray:
    """:func:`_gate_strips` when ``opts.strip_aperture_scope`` is ``"all"``, else ``penalty`` itself."""
    if opts.strip_windows and opts.strip_aperture > 0 and opts.strip_aperture_scope == "all":
        return _gate_strips(penalty, centre, sizes=sizes, noise=noise, factor=opts.strip_aperture,
                            length=opts.strip_aperture_length)
    return penalty


def _gate_strips(penalty: np.ndarray, centre: np.ndarray, *, sizes: tuple[int, ...], noise: float,
                 factor: float, length: int) -> np.ndarray:
    """``penalty`` ``(H, W, K)`` (window ``k``: shape ``k // len(sizes)``, size ``sizes[k % len]``)
    with the strip windows barred where they cannot measure disparity
    (:func:`recon.entropy.aperture.informative_strips`; the floor is Eq. 12's, half a grey level)."""
    n = len(sizes)
    ok = informative_strips(centre, sizes=sizes, noise_sigma=noise, factor=factor, floor=STRIP_FLOOR,
                            length=length)
    out = penalty.copy()
    for j, shape in enumerate(STRIP_SHAPES):
        block = out[..., shape * n:(shape + 1) * n]
        block[~ok[..., j, :]] = np.inf
    # A pixel offered nothing but uninformative strips keeps them: some window must be matched.
    none_left = ~np.isfinite(out).any(axis=2)
    out[none_left] = penalty[none_left]
    return out.astype(np.float32)


def noise_limited_pixels(centre: np.ndarray, flat: np.ndarray, ambiguity0: np.ndarray, *,
                         noise: float, options: EntropyOptions) -> np.ndarray:
    """``(H, W)`` bool: the pixels whose matching the noise, not the texture, decides
    (``options.noise_gate``): ``"texture"``: inside a window of the largest size whose every pixel
    has nothing but noise around it (:func:`recon.entropy.noise.texture_to_noise` below
    ``noise_texture_ratio``, with the ``noise_filter`` sigma, 1.5 px when the filter is off;
    :func:`recon.entropy.noise.noise_limited_windows`); Eq. 12's per-pixel count is not used: on a
    wall under noise it flips from pixel to pixel. ``"holes"`` (the first version): Eq. 12-flat
    with no valley in the initial nine-view cost."""
    if options.noise_gate == "holes":
        return flat & (ambiguity0 * options.initial_step > options.initial_hole_width)
    return noise_limited_windows(_texture_ratio(centre, noise, options) < options.noise_texture_ratio,
                                 radius_px=max(options.window_sizes) // 2)


def texture_sigma_px(options: EntropyOptions) -> float:
    """Sigma (px) of the filter with which the texture gates measure texture against noise
    (:func:`recon.entropy.noise.texture_to_noise`): ``noise_filter``, 1.5 px when it is off."""
    return options.noise_filter if options.noise_filter > 0 else 1.5


def no_data_pixels(centre: np.ndarray, noise_limited: np.ndarray, *, noise: float,
                   options: EntropyOptions) -> np.ndarray:
    """``(H, W)`` bool: pixels whose matched value carries no information about the surface, so
    that the refinement's valley weights give them none: the noise-limited pixels
    (:func:`noise_limited_pixels`) and every pixel whose own largest window holds nothing but noise
    (:func:`recon.entropy.noise.texture_to_noise` below ``noise_texture_ratio``; a textureless
    patch narrower than the noise gate's window is not noise-limited, yet matches itself at every
    shift). ``centre``: ``(H, W)`` grey centre view; ``noise``: its sigma, ``[0, 1]`` grey units."""
    return np.asarray(noise_limited, bool) | (_texture_ratio(centre, noise, options) < options.noise_texture_ratio)


def _texture_ratio(centre: np.ndarray, noise: float, options: EntropyOptions) -> np.ndarray:
    # texture_to_noise over the largest window
    return texture_to_noise(centre, noise_sigma=noise, sigma_px=texture_sigma_px(options),
                            radius_px=max(options.window_sizes) // 2)


def _layer_keep(ambiguity0: np.ndarray, flat: np.ndarray, opts: EntropyOptions) -> np.ndarray:
    return (ambiguity0 * opts.initial_step <= opts.layer_keep_width) & ~flat


def _partial(d0, flat, ambiguity0, noise, timings, opts, known) -> EntropyResult:
    # The result of stop_after="initial": the raw initial estimate and what fill_initial needs.
    empty = np.zeros(d0.shape, np.uint8)
    return EntropyResult(
        disparity=d0.astype(np.float32), initial_disparity=d0.astype(np.float32),
        matched_disparity=d0.astype(np.float32), labels=empty, window_size=empty,
        window_shape=empty, view_set=empty, entropy=np.zeros(d0.shape, np.float32),
        cost=np.zeros(d0.shape, np.float32),
        disparity_range=tuple(known) if known is not None else opts.initial_range,
        timings=timings, options=opts,
        info={"initial_ambiguity": ambiguity0, "flat": flat, "noise_sigma": noise})


def fill_initial(d0: np.ndarray, ambiguity0: np.ndarray, flat: np.ndarray, *,
                 options: EntropyOptions) -> tuple[np.ndarray, np.ndarray | None]:
    """Whole-image step after the initial search: black holes of ``d0`` (flat pixels whose
    nine-view cost curve is flat) filled from their surroundings (:func:`harmonic_fill`).

    ``(H, W)`` maps in, ``(filled d0 float32, holes bool or None)`` out."""
    holes0 = (flat & (ambiguity0 * options.initial_step > options.initial_hole_width)
              if options.fill_holes else None)
    if holes0 is not None and holes0.any():
        d0 = harmonic_fill(d0, holes0)
    return d0, holes0


def layer_origin(d0: np.ndarray, ambiguity0: np.ndarray, flat: np.ndarray, *,
                 options: EntropyOptions) -> float:
    """The disparity histogram's bin origin the whole image uses: the layer map's minimum."""
    layers = layer_map(d0, median_size=options.layer_median,
                       keep=_layer_keep(ambiguity0, flat, options))
    return float(np.nanmin(layers))


def refine_global(matched: np.ndarray, labels: np.ndarray, flat: np.ndarray,
                  ambiguity: np.ndarray, *, options: EntropyOptions,
                  no_data: np.ndarray | None = None,
                  disparity_range: tuple[float, float] | None = None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Whole-image last step: the TV refinement of Eq. 13 over the smooth region, black holes
    (flat pixels whose matching cost curve is flat) filled by it; with ``valley_weights`` the
    pixels with a wide cost valley join it with their valley's weight
    (:func:`recon.entropy.refine.valley_weights`; ``no_data``, the ``(H, W)`` bool mask of
    :func:`no_data_pixels`, keep none, and so do plateaus over the whole searched
    ``disparity_range``).

    ``(H, W)`` maps in (matched disparity, labels, flat mask, cost ambiguity in candidates);
    ``(refined float32, holes bool or None)`` out (the black holes, whose data term is dropped)."""
    holes = flat & (ambiguity * options.step > options.hole_width) if options.fill_holes else None
    joined, weight = holes, None
    if holes is not None and options.valley_weights:
        span = (np.inf if disparity_range is None else
                len(disparity_candidates(disparity_range[0], disparity_range[1], options.step)) * options.step)
        joined, weight = valley_weights(ambiguity * options.step, flat=flat, no_data=no_data,
                                        hole_width=options.hole_width, unsure_width=options.unsure_width,
                                        plateau_width=span)
    refined = tv_refine(matched, labels == SMOOTH, gamma=options.gamma,
                        iterations=options.tv_iterations, holes=joined, hole_weight=weight)
    return refined, holes
