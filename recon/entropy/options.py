"""The estimator's options, grouped by the step that reads them, and the named presets.

Each step of the estimator (``docs/entropy-method.md`` describes them in this order) has a small
frozen dataclass that checks its own values and raises a one-line ``ValueError`` naming the value
and what to give instead:

============  ==========================================================================
group         step
============  ==========================================================================
initial       the nine-view initial estimate ``d0`` and, when no range is known, its discovery
regions       layers, occlusion labels (Eqs. 8-11), flat regions (Eq. 12)
noise         the noise gate, the filter of noise-limited views, weak-texture softening
windows       window choice by matching entropy (Eq. 1), side windows and strips, curvature cap,
              strip aperture
matching      the line search (Eqs. 5-7) and its view sets
boundary      the boundary test after matching
refine        TV refinement (Eq. 13), black-hole filling, centroid correction
confidence    the confidence map
============  ==========================================================================

:class:`EntropyOptions` is the flat view callers use: one frozen dataclass with every field of every
group under the same name (``options.step``, ``make_options(gamma=0.1)``, ``lfrig reconstruct
--gamma 0.1``); ``options.windows`` and the like give a group. Constructing it checks every group.

Units: disparities and steps in pixels per view step (px/view); window sizes and sigmas in pixels;
grey levels in 8-bit levels unless a field says otherwise.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Any


def _opt(default, help: str):
    return field(default=default, metadata={"help": help})


def _need(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def _finite(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _count(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _choice(name: str, value: Any, choices: tuple[str, ...]) -> None:
    _need(value in choices, f"{name} must be one of {choices}, got {value!r}")


def _range_pair(name: str, value: Any) -> None:
    _need(value is None or (len(value) == 2 and all(_finite(v) for v in value) and value[0] < value[1]),
          f"{name} must be (min, max) with finite min < max px/view, got {value}")


#: Values of :attr:`RegionOptions.occlusion_views`.
OCCLUSION_VIEWS = ("nine", "all")
#: Values of :attr:`WindowOptions.side_windows`.
SIDE_WINDOW_SCOPES = ("occlusion", "edges", "everywhere")
#: Values of :attr:`WindowOptions.flat_windows`.
FLAT_WINDOW_SCOPES = ("largest", "all")
#: Values of :attr:`WindowOptions.strip_aperture_scope`.
STRIP_APERTURE_SCOPES = ("initial", "all")
#: Values of :attr:`NoiseOptions.noise_gate`.
NOISE_GATES = ("texture", "holes")
#: Values of :attr:`MatchingOptions.visible_sets`.
VISIBLE_SET_SCOPES = ("none", "occluded", "occlusion", "all")


@dataclass(frozen=True)
class InitialOptions:
    """The nine-view initial estimate ``d0`` (the centre and the farthest view in eight directions)
    and, when no disparity range is known, the range it finds."""

    initial_range: tuple[float, float] = _opt(
        (-8.0, 8.0), "range (min, max) the initial search covers when no range is known; with "
                     "discover_range the range the coarse search covers")
    discover_range: bool = _opt(
        True, "when no range is known, find it first by a nine-view search on views downsampled up "
              "to 4x, then search only that range at full resolution (else the whole initial_range "
              "at full resolution)")
    initial_step: float = _opt(0.05, "candidate spacing of the initial search (px/view)")
    initial_window: int = _opt(5, "window side of the initial search (pixels, odd)")
    initial_shiftable: bool = _opt(
        True, "the initial search takes the least cost over the square and the side windows W1..W8 "
              "with their visible views (else the square alone)")
    initial_hole_width: float = _opt(
        0.6, "an initial cost curve is flat (no information) when the candidates within the hole "
             "tolerance of its least cost span more than this width (px/view); wider than "
             "hole_width because the initial search's small windows and few views give wider valleys")
    range_percentile: float = _opt(
        0.5, "a range found from the initial estimate spans its percentiles [p, 100 - p] of the "
             "pixels whose initial cost curve has a valley")
    range_margin: float = _opt(0.25, "margin (px/view) added on each side of a range found from the "
                                     "initial estimate")

    def __post_init__(self) -> None:
        _range_pair("initial_range", self.initial_range)
        _need(_finite(self.initial_step) and self.initial_step > 0,
              f"initial_step must be > 0 px/view, got {self.initial_step}")
        _need(_count(self.initial_window) and self.initial_window >= 3 and self.initial_window % 2,
              f"initial_window must be an odd size >= 3 pixels, got {self.initial_window}")
        _need(_finite(self.initial_hole_width) and self.initial_hole_width > 0,
              f"initial_hole_width must be > 0 px/view, got {self.initial_hole_width}")
        _need(_finite(self.range_percentile) and 0 <= self.range_percentile < 50,
              f"range_percentile must be in [0, 50), got {self.range_percentile}")
        _need(_finite(self.range_margin) and self.range_margin >= 0,
              f"range_margin must be >= 0 px/view, got {self.range_margin}")


@dataclass(frozen=True)
class RegionOptions:
    """The layer map (median-filtered ``d0``), the region labels of Eqs. 8-11 and the flat pixels of
    Eq. 12."""

    layer_gap: float = _opt(
        0.25, "layers closer than this (px/view) count as one (Eq. 9)")
    occlusion_views: str = _opt(
        "all", "views whose warped layers Eq. 9 compares with the centre: 'nine' (the paper: the "
               "farthest in each direction) or 'all' (also finds pixels hidden only in middle views)")
    layer_median: int = _opt(5, "median filter size (pixels) applied to the initial disparity for the layers")
    layer_keep_width: float = _opt(
        0.2, "the median filter leaves d0 unchanged at textured (not Eq. 12-flat) pixels whose initial "
             "cost valley is at most this wide (px/view): there d0 is sure (0: filter everywhere)")
    smooth_neighbourhood: int = _opt(5, "side (pixels) of the square neighbourhood of psi (Eq. 12)")
    smooth_tolerance: float = _opt(
        2.0, "grey values differ (Eq. 12) when they differ by more than this times the noise sigma")

    def __post_init__(self) -> None:
        _need(_finite(self.layer_gap) and self.layer_gap > 0, f"layer_gap must be > 0 px/view, got {self.layer_gap}")
        _choice("occlusion_views", self.occlusion_views, OCCLUSION_VIEWS)
        _need(_count(self.layer_median) and self.layer_median >= 1,
              f"layer_median must be a size >= 1 pixels, got {self.layer_median}")
        _need(_finite(self.layer_keep_width) and self.layer_keep_width >= 0,
              f"layer_keep_width must be >= 0 px/view (0: filter everywhere), got {self.layer_keep_width}")
        _need(_count(self.smooth_neighbourhood) and self.smooth_neighbourhood >= 1,
              f"smooth_neighbourhood must be a size >= 1 pixels, got {self.smooth_neighbourhood}")
        _need(_finite(self.smooth_tolerance) and self.smooth_tolerance >= 0,
              f"smooth_tolerance must be >= 0 noise sigmas, got {self.smooth_tolerance}")


@dataclass(frozen=True)
class NoiseOptions:
    """Which pixels the noise, not the texture, decides, and the filters the views get where those
    pixels and pixels of weak texture land."""

    noise_gate: str = _opt(
        "texture", "which pixels are noise-limited: 'texture' (a window of the largest size whose "
                   "filtered gradient energy is below noise_texture_ratio times that of noise alone) "
                   "or 'holes' (Eq. 12-flat pixels without a valley in the initial cost curve; also "
                   "catches specular surfaces and thin textureless structures next to texture)")
    noise_texture_ratio: float = _opt(
        4.0, "for noise_gate='texture': the gradient-energy ratio to noise alone (1 = pure noise) "
             "below which a window is noise-limited")
    noise_filter: float = _opt(
        1.5, "Gaussian sigma (pixels) applied before the line search to the views where noise-limited "
             "pixels land, where the view is noise-limited too (0: off, the paper)")
    weak_texture_filter: float = _opt(
        0.6, "Gaussian sigma (pixels) applied before the line search to the views where pixels of weak "
             "texture land: it correlates the noise, which otherwise pulls a noisy surface's cost "
             "minimum towards half-pixel shifts, and keeps the texture (0: off, the paper)")
    weak_texture_ratio: float = _opt(
        12.0, "weak texture: a gradient-energy ratio to noise alone over the largest window (as for "
              "noise_texture_ratio) below this")

    def __post_init__(self) -> None:
        _choice("noise_gate", self.noise_gate, NOISE_GATES)
        _need(_finite(self.noise_texture_ratio) and self.noise_texture_ratio > 0,
              f"noise_texture_ratio must be > 0 (1 = pure noise), got {self.noise_texture_ratio}")
        _need(_finite(self.noise_filter) and self.noise_filter >= 0,
              f"noise_filter must be a sigma >= 0 pixels (0: off), got {self.noise_filter}")
        _need(_finite(self.weak_texture_filter) and self.weak_texture_filter >= 0,
              f"weak_texture_filter must be a sigma >= 0 pixels (0: off), got {self.weak_texture_filter}")
        _need(_finite(self.weak_texture_ratio) and self.weak_texture_ratio > 0,
              f"weak_texture_ratio must be > 0 (1 = pure noise), got {self.weak_texture_ratio}")


@dataclass(frozen=True)
class WindowOptions:
    """The windows each pixel is offered and the matching entropy (Eq. 1) that ranks them."""

    window_sizes: tuple[int, ...] = _opt((3, 5, 7, 9, 11, 13, 15), "window sides searched (pixels, odd)")
    grey_bins: int = _opt(32, "grey-level histogram bins of the matching entropy (Eq. 1)")
    disparity_bin: float = _opt(0.1, "bin width (px/view) of the initial-disparity histogram (Eq. 1)")
    alpha1: float = _opt(1.0, "weight of the disparity-consistency term (Eq. 1)")
    alpha2_occlusion: float = _opt(1.0, "weight of the anti-occlusion term in occlusion regions (Eq. 1)")
    alpha2_other: float = _opt(0.0, "weight of the anti-occlusion term elsewhere (Eq. 1)")
    strip_windows: bool = _opt(
        True, "also offer one-pixel strips along the rows and columns, matched over the views in line "
              "with them (for gaps between two occluders)")
    side_windows: str = _opt(
        "edges", "where texture and smooth pixels are offered the side windows and strips besides the "
                 "square: 'occlusion' (the paper: nowhere), 'edges' (at the sizes whose square would "
                 "reach a jump of the layer map) or 'everywhere'")
    side_jump: float = _opt(
        0.3, "for side_windows='edges': a layer-map difference between neighbouring pixels above "
             "this (px/view) is a jump")
    single_layer_windows: bool = _opt(
        True, "texture and smooth pixels are not offered windows that reach another layer of the "
              "layer map")
    crease_tolerance: float = _opt(
        0.01, "texture and smooth pixels are not offered a square whose mean layer value differs from "
              "the smallest square's by more than this (px/view): on a ridge, pit or curved surface a "
              "square finds the mean disparity under it (0: off, the paper)")
    crease_noise: float = _opt(
        1.5, "the crease tolerance is raised to this many times the local noise of the initial "
             "disparity over the largest window (0: the fixed tolerance alone)")
    flat_windows: str = _opt(
        "largest", "windows offered to noise-limited pixels: 'largest' (those of the largest size "
                   "offered, the square where it is) or 'all' (the same as other pixels, the paper)")
    strip_aperture: float = _opt(
        1.5, "a strip is offered only where the centre view varies along it: the mean absolute "
             "difference of neighbouring pixels along it must exceed this times what noise alone "
             "gives, and half a grey level (0: strips everywhere)")
    strip_aperture_scope: str = _opt(
        "initial", "where strip_aperture gates the strips: 'initial' (the initial search) or 'all' "
                   "(also the line search)")
    strip_aperture_length: int = _opt(
        31, "length (pixels, odd) over which strip_aperture measures the variation along a strip")

    def __post_init__(self) -> None:
        sizes = self.window_sizes
        _need(bool(sizes) and all(_count(s) and s >= 3 and s % 2 for s in sizes),
              f"window_sizes must be odd sizes >= 3, got {sizes}")
        _need(_count(self.grey_bins) and self.grey_bins >= 2,
              f"grey_bins must be a count >= 2, got {self.grey_bins}")
        _need(_finite(self.disparity_bin) and self.disparity_bin > 0,
              f"disparity_bin must be a width > 0 px/view, e.g. 0.1, got {self.disparity_bin}")
        _choice("side_windows", self.side_windows, SIDE_WINDOW_SCOPES)
        _choice("flat_windows", self.flat_windows, FLAT_WINDOW_SCOPES)
        _choice("strip_aperture_scope", self.strip_aperture_scope, STRIP_APERTURE_SCOPES)
        _need(_count(self.strip_aperture_length) and self.strip_aperture_length >= 1
              and self.strip_aperture_length % 2 == 1,
              f"strip_aperture_length must be odd and >= 1, got {self.strip_aperture_length}")
        _need(_finite(self.strip_aperture) and self.strip_aperture >= 0,
              f"strip_aperture must be a finite factor >= 0 (0: off), got {self.strip_aperture}")

    @property
    def largest_radius_px(self) -> int:
        """Half the largest window side: how far (pixels) any window reaches from its pixel."""
        return max(self.window_sizes) // 2


@dataclass(frozen=True)
class MatchingOptions:
    """The line search of Eqs. 5-7 over every view or a window's visible views."""

    disparity_range: tuple[float, float] | None = _opt(
        None, "(min, max) disparity to search (px/view); default the light field's, else found from "
              "the initial estimate")
    step: float = _opt(0.04, "candidate spacing of the line search (px/view), refined by a parabola")
    visible_sets: str = _opt(
        "occluded", "which pixels match over their window shape's visible views (others over all "
                    "views): 'none', 'occluded' (the paper), 'occlusion' (occluded and occluding) or "
                    "'all'")
    joint: bool = _opt(
        True, "minimise Eq. 7 jointly over disparity and window (else the window by largest entropy "
              "first, then the line search with it)")
    lambda_entropy: float = _opt(1.0, "lambda of Eq. 6: the weight of the matching entropy")
    intensity_scale: float = _opt(
        255.0, "grey values enter the matching cost in these units (255: 8-bit levels)")

    def __post_init__(self) -> None:
        _range_pair("disparity_range", self.disparity_range)
        _need(_finite(self.step) and self.step > 0, f"step must be > 0 px/view, got {self.step}")
        _choice("visible_sets", self.visible_sets, VISIBLE_SET_SCOPES)
        _need(_finite(self.lambda_entropy), f"lambda_entropy must be finite, got {self.lambda_entropy}")
        _need(_finite(self.intensity_scale) and self.intensity_scale > 0,
              f"intensity_scale must be > 0 (255: 8-bit levels), got {self.intensity_scale}")


@dataclass(frozen=True)
class BoundaryOptions:
    """The boundary test after matching: a pixel that lies well above a neighbour is tested by its
    own grey value against the neighbour's farther disparity (a window fattens the near surface by a
    pixel)."""

    boundary_snap: bool = _opt(
        True, "test, after matching, each pixel more than boundary_jump above a neighbour: over the "
              "views that would see it at the neighbour's farther value, it takes that value where it "
              "fits its grey value clearly better")
    boundary_snap_initial: bool = _opt(
        False, "the same test on the hole-filled initial disparity before the layers and labels are "
               "made from it")
    boundary_jump: float = _opt(
        0.5, "a pixel is tested when it exceeds the least value of its 3x3 neighbourhood by more "
             "than this (px/view)")
    boundary_support: int = _opt(
        6, "a pixel is tested only where that least value is shared (within 0.1 px/view) by at "
           "least this many pixels of the 5x5 neighbourhood: a surface behind, not an outlier")
    boundary_confidence: float = _opt(
        3.0, "the farther value must win by more than this many standard errors of noise "
             "(sigma / sqrt(views)) of the mean absolute grey difference")
    boundary_mix: float = _opt(
        0.4, "the farther value is also taken where the pixel's grey value holds less than this "
             "fraction of the near surface's (an anti-aliased rim pixel; 0: off)")
    boundary_mix_contrast: float = _opt(
        12.0, "boundary_mix applies only where near and far surfaces differ by at least this many "
              "noise sigmas")
    boundary_mix_extrapolate: bool = _opt(
        True, "boundary_mix extrapolates the near surface's grey value linearly to the pixel, so that "
              "shading towards a silhouette is not read as mixing")

    def __post_init__(self) -> None:
        _need(_finite(self.boundary_mix) and 0 <= self.boundary_mix <= 1
              and _finite(self.boundary_mix_contrast) and self.boundary_mix_contrast >= 0,
              f"boundary_mix must be a fraction in [0, 1] (0: off) and boundary_mix_contrast >= 0 noise "
              f"sigmas; got {self.boundary_mix}, {self.boundary_mix_contrast}")
        _need(_finite(self.boundary_jump) and self.boundary_jump > 0 and _finite(self.boundary_confidence)
              and self.boundary_confidence >= 0 and _count(self.boundary_support)
              and 1 <= self.boundary_support <= 25,
              f"boundary_jump must be > 0 px/view, boundary_confidence >= 0 and boundary_support 1..25 "
              f"pixels; got {self.boundary_jump}, {self.boundary_confidence}, {self.boundary_support}")


@dataclass(frozen=True)
class RefineOptions:
    """The TV refinement of Eq. 13 in smooth regions, the black holes it fills, and the centroid
    correction of side windows."""

    gamma: float = _opt(0.2, "TV weight of the refinement (Eq. 13)")
    tv_iterations: int = _opt(300, "primal-dual iterations of the TV refinement")
    fill_holes: bool = _opt(
        True, "black holes (Eq. 12-flat pixels whose cost curve is flat) get no data term: the "
              "initial estimate there is filled from its surroundings before the layers are made, "
              "and the TV refinement fills them in the final map")
    hole_width: float = _opt(
        0.3, "a cost curve is flat (no information) when the candidates within the hole tolerance of "
             "its least cost span more than this width (px/view)")
    hole_delta: float = _opt(0.5, "the hole tolerance: grey levels above a cost curve's least value")
    hole_delta_noise: float = _opt(
        0.2, "the hole tolerance is at least this many noise sigmas (in grey levels)")
    valley_weights: bool = _opt(
        True, "pixels whose cost valley is wide join the TV refinement with the data weight "
              "(hole_width / valley width)^2, the curvature of their cost, instead of none (black holes) "
              "or a fixed value (outside the smooth region); pixels without data (noise-limited, only noise "
              "in their largest window, a plateau over the whole range) keep none (needs fill_holes)")
    unsure_width: float = _opt(
        0.6, "with valley_weights, a pixel that is not Eq. 12-flat joins the refinement when its cost "
             "valley is wider than this (px/view)")
    centroid_correction: bool = _opt(
        True, "move each side window's estimate from the window's centroid back to the pixel with the "
              "slope of a plane fitted to the matched disparity over the window")
    centroid_max_residual: float = _opt(
        0.05, "no centroid correction where that plane fits worse than this RMS (px/view)")

    def __post_init__(self) -> None:
        _need(_finite(self.gamma) and self.gamma >= 0, f"gamma must be a TV weight >= 0, got {self.gamma}")
        _need(_count(self.tv_iterations) and self.tv_iterations >= 0,
              f"tv_iterations must be a count >= 0, got {self.tv_iterations}")
        _need(_finite(self.hole_width) and self.hole_width > 0, f"hole_width must be > 0 px/view, got {self.hole_width}")
        _need(_finite(self.hole_delta) and self.hole_delta >= 0 and _finite(self.hole_delta_noise)
              and self.hole_delta_noise >= 0,
              f"hole_delta and hole_delta_noise must be >= 0, got {self.hole_delta}, {self.hole_delta_noise}")
        _need(_finite(self.centroid_max_residual) and self.centroid_max_residual >= 0,
              f"centroid_max_residual must be >= 0 px/view, got {self.centroid_max_residual}")
        _need(_finite(self.unsure_width) and self.unsure_width > 0,
              f"unsure_width must be a valley width > 0 px/view, got {self.unsure_width}")


@dataclass(frozen=True)
class ConfidenceOptions:
    """The confidence map (:mod:`recon.entropy.confidence`); it changes no disparity."""

    hole_support: float = _opt(
        0.25, "a black hole's confidence (0.5) is scaled by min(1, s / this), s the measured pixels' "
              "confidence interpolated into the hole (0: off)")
    hole_ramp: float = _opt(
        0.1, "a black hole's confidence is also scaled by exp(-|grad d| / this) (px/view per pixel): "
             "a steep fill is a ramp between rims that disagree (0: off)")

    def __post_init__(self) -> None:
        _need(_finite(self.hole_ramp) and self.hole_ramp >= 0,
              f"hole_ramp must be a finite slope >= 0 px/view per pixel (0: off), got {self.hole_ramp}")
        _need(_finite(self.hole_support) and 0 <= self.hole_support <= 1,
              f"hole_support must be in [0, 1] (0: off), got {self.hole_support}")


#: Step name -> its options group, in the estimator's order.
GROUPS: dict[str, type] = {
    "initial": InitialOptions, "regions": RegionOptions, "noise": NoiseOptions,
    "windows": WindowOptions, "matching": MatchingOptions, "boundary": BoundaryOptions,
    "refine": RefineOptions, "confidence": ConfidenceOptions,
}


def _group_view(group: type):
    names = [f.name for f in dataclasses.fields(group)]
    return property(lambda self: group(**{n: getattr(self, n) for n in names}),
                    doc=f"The :class:`{group.__name__}` of these options.")


def _check_all(self) -> None:
    for group in GROUPS:
        getattr(self, group)  # each group checks its own values


EntropyOptions = dataclasses.make_dataclass(
    "EntropyOptions",
    [(f.name, f.type, dataclasses.field(default=f.default, metadata=f.metadata))
     for group in GROUPS.values() for f in dataclasses.fields(group)],
    frozen=True, module=__name__,
    namespace={"__post_init__": _check_all, **{name: _group_view(g) for name, g in GROUPS.items()}},
)
EntropyOptions.__doc__ = (
    """Every option of the estimator, flat: the fields of every group of :data:`GROUPS` under their
    own names, with their defaults; ``options.<group>`` gives one group. Checked on construction
    (``ValueError`` naming the value).""")

#: Step name -> a few words on what it does (help texts, docs).
TITLES: dict[str, str] = {
    "initial": "the nine-view initial estimate d0 and range discovery",
    "regions": "layers, occlusion labels, flat regions",
    "noise": "noise gate, flat-view filter, weak-texture softening",
    "windows": "window choice by matching entropy, curvature cap, strip aperture",
    "matching": "line search, view sets",
    "boundary": "the boundary test after matching",
    "refine": "TV refinement, hole filling, centroid correction",
    "confidence": "the confidence map",
}

#: Field name -> the step (key of :data:`GROUPS`) it belongs to.
STEP_OF: dict[str, str] = {f.name: name for name, g in GROUPS.items() for f in dataclasses.fields(g)}

#: The defaults (``dataclasses.fields(EntropyOptions)`` gives each name, type, default and
#: ``metadata["help"]``).
DEFAULTS = EntropyOptions()

#: Named option sets, applied to :data:`DEFAULTS`. ``"paper"`` is the paper's literal configuration
#: as far as its text fixes one: region labels from the median-filtered layers and the nine views,
#: the square window alone in texture and smooth regions, W1..W8 (no strips) in occlusion regions,
#: the window first by largest entropy and then the line search (Eqs. 6-7 read as two steps), every
#: pixel's data term kept in Eq. 13 (no black-hole filling, no valley weights), no centroid correction, no filters of
#: the views, no boundary test, 256 grey bins. Where the paper leaves a choice open (the initial
#: estimate, the noise tolerance of Eq. 12) it keeps lfrig's reading.
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "paper": {"occlusion_views": "nine", "strip_windows": False, "side_windows": "occlusion",
              "single_layer_windows": False, "layer_keep_width": 0.0, "joint": False,
              "centroid_correction": False, "fill_holes": False, "grey_bins": 256,
              "noise_filter": 0.0, "flat_windows": "all", "crease_tolerance": 0.0,
              "weak_texture_filter": 0.0, "boundary_snap": False, "valley_weights": False},
}


def make_options(options=None, *, preset: str | None = None, **overrides) -> EntropyOptions:
    """``options`` (default :data:`DEFAULTS`, or the named :data:`PRESETS` entry ``preset`` applied
    to the defaults) with ``overrides`` applied; unknown names and unusable values raise
    ``ValueError``."""
    if preset is not None:
        if options is not None:
            raise ValueError("give either options or preset, not both")
        if preset not in PRESETS:
            raise ValueError(f"unknown entropy preset {preset!r}; choose one of {', '.join(PRESETS)}")
        options = dataclasses.replace(DEFAULTS, **PRESETS[preset])
    base = DEFAULTS if options is None else options
    unknown = sorted(set(overrides) - set(STEP_OF))
    if unknown:
        raise ValueError(f"unknown entropy option(s) {unknown}; valid names: {sorted(STEP_OF)}")
    return dataclasses.replace(base, **overrides)


def check_options(options: EntropyOptions) -> None:
    """Raise ``ValueError`` naming an option value the estimator cannot use (every group's check)."""
    _check_all(options)


def check_value(name: str, value: Any) -> None:
    """Raise ``ValueError`` if option ``name`` cannot take ``value`` (its group's check, with the
    other fields at their defaults)."""
    group = GROUPS[STEP_OF[name]]
    defaults = {f.name: getattr(DEFAULTS, f.name) for f in dataclasses.fields(group)}
    group(**{**defaults, name: value})
