"""``confidence.pfm`` as a probability: the chance that a pixel's disparity is within 0.07 px/view
of the truth (BadPix 0.07's threshold), from what the estimator knows about the pixel.

A logistic model over a few per-pixel features (:data:`FEATURES`) of the estimator's own maps:

- the **cost valley's width** (``log``): the disparity span of the candidates within the hole
  tolerance of the least objective (:func:`recon.entropy.matching.cost_ambiguity`);
- the **refinement's change** ``|refined - matched|`` and the **disagreement with the neighbours**
  ``|refined - median5(refined)|`` and with the **nine-view initial estimate** ``|refined - d0|``
  (logs);
- the **region type** (occluding, occluded, texture; smooth is the base), the **black holes** (no
  data term) and the **noise-limited** pixels (:func:`recon.entropy.steps.noise_limited_pixels`);
- the **matching cost** at the chosen disparity against the noise sigma (log), the **window size**,
  the **slope** of the final map (log), and the heuristic product of
  :func:`recon.entropy.confidence.confidence_map`;
- the **nearest of the 8 neighbours** ``min |d - d_n|`` (log) and the **share of the 8 neighbours
  within 0.07 px/view**: a pixel unlike every neighbour is a spike;
- the **distance to the nearest disparity jump** (a step over ``JUMP_PX`` between 4-neighbours;
  pixels, capped at ``JUMP_REACH_PX``, log): most wrong pixels sit at outlines;
- the **spread** of the final map in the 5x5 box (standard deviation, log) and the chosen window's
  **matching entropy** (the ``E`` of Eq. 6: the texture the match had), raised to
  :data:`ENTROPY_FLOOR`: below it a window has next to no texture, its disparity comes from the
  refinement's fill, and a lower entropy says no more about it (a plain scene's entropies lie
  mostly below every textured scene's: left linear, the model would call its filled walls wrong).

``p = 1 / (1 + exp(-(b + sum_i c_i f_i)))``; ``p = 0`` where the disparity is not finite, lies
outside the searched range or sits on its first or last candidate. The coefficients
(``recon/entropy/confidence_fit.py``, a constant that script writes) are fitted by
``bench/confidence_fit.py`` on the scenes under
``../shared/data`` and the rendered suite (``docs/entropy-method.md``, "Confidence").
"""

from __future__ import annotations

import numpy as np

from recon.entropy.confidence import confidence_map, finite_median5
from recon.entropy.labels import OCCLUDED, OCCLUDING, TEXTURE
from recon.entropy.median import median_filter_nearest
from recon.native import call, chosen, thread_count

#: The model's inputs, in the order of the coefficients.
FEATURES = ("log_width", "log_change", "log_neighbour", "log_initial", "occluding", "occluded",
            "texture", "hole", "noise_limited", "log_cost", "window_size", "log_slope", "heuristic",
            "log_nearest_neighbour", "neighbours_agreeing", "log_jump_distance", "log_spread", "entropy")

#: The disparity tolerance the probability is about (px/view): BadPix 0.07's.
TOLERANCE_PX = 0.07

_EPS = 0.01  # px/view (or noise sigmas) added before the logs: a floor below any difference that matters

#: The matching entropy feature is ``max(E, ENTROPY_FLOOR)`` (the module docstring).
ENTROPY_FLOOR = 0.5

#: A step between 4-neighbours over this (px/view) is a disparity jump (an outline).
JUMP_PX = 0.25
#: The distance to the nearest jump is capped here (pixels): farther is "far".
JUMP_REACH_PX = 10


def neighbour_agreement(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(nearest, agreeing)`` of an ``(H, W)`` float64 map: ``min |d - d_n|`` over the 8 neighbours
    (px/view) and how many of them lie within :data:`TOLERANCE_PX` (0..8); the border continued
    by the nearest pixel."""
    H, W = d.shape
    pad = np.pad(d, 1, mode="edge")
    nearest = np.full(d.shape, np.inf)
    agreeing = np.zeros(d.shape, np.int64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                diff = np.abs(d - pad[1 + dy:1 + dy + H, 1 + dx:1 + dx + W])
                np.minimum(nearest, diff, out=nearest)
                agreeing += diff <= TOLERANCE_PX
    return nearest, agreeing


def neighbours_and_slope(d: np.ndarray, rows: tuple[int, int], *, kernel: str = "auto"
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows ``[r0, r1)`` of :func:`neighbour_agreement`'s ``(nearest, agreeing)`` of ``d`` and of its
    slope (``np.hypot`` of ``np.gradient`` along each axis of more than one pixel, else 0), float64,
    int64 and float64: the C kernel (``recon/native/confidence.c``, the same bits) where it loads and
    ``d`` is finite, else numpy (``kernel`` as :func:`jump_distance`'s)."""
    d = np.asarray(d, np.float64)
    r0, r1 = int(rows[0]), int(rows[1])
    if d.ndim == 2 and chosen("confidence", kernel) and np.isfinite(d).all():
        d = np.ascontiguousarray(d)
        H, W = d.shape
        nearest, slope = np.empty((max(r1 - r0, 0), W)), np.empty((max(r1 - r0, 0), W))
        agreeing = np.empty((max(r1 - r0, 0), W), np.int64)
        call("confidence", "lfrig_neighbours", d, H, W, r0, r1, float(TOLERANCE_PX), nearest, agreeing, slope)
        return nearest, agreeing, slope
    nearest, agreeing = neighbour_agreement(d)
    gy, gx = (np.gradient(d, axis=a) if d.shape[a] > 1 else np.zeros_like(d) for a in (0, 1))
    return nearest[r0:r1], agreeing[r0:r1], np.hypot(gy, gx)[r0:r1]


def jump_distance(d: np.ndarray, *, rows: tuple[int, int] | None = None, kernel: str = "auto") -> np.ndarray:
    """``(H, W)`` float64 distance (pixels, Euclidean, at most :data:`JUMP_REACH_PX`) to the nearest
    pixel on either side of a step over :data:`JUMP_PX` between 4-neighbours of ``d``; ``rows``
    ``(r0, r1)``: only those rows of it (``(r1 - r0, W)``).

    ``kernel``: ``"auto"`` the C kernel (``recon/native/confidence.c``, the same bits) where it
    loads, ``"native"`` that one or ``RuntimeError``, ``"numba"`` the reference: scipy's Euclidean
    distance transform (:func:`recon.native.chosen`; this kernel has no numba twin)."""
    d = np.asarray(d, np.float64)
    r0, r1 = (0, d.shape[0]) if rows is None else (int(rows[0]), int(rows[1]))
    if chosen("confidence", kernel) and d.ndim == 2:
        d = np.ascontiguousarray(d)
        H, W = d.shape
        out = np.empty((max(r1 - r0, 0), W))
        call("confidence", "lfrig_jump_distance", d, H, W, float(JUMP_PX), int(JUMP_REACH_PX), r0, r1, out)
        return out
    return jump_distance_reference(d)[r0:r1]


def jump_distance_reference(d: np.ndarray) -> np.ndarray:
    """:func:`jump_distance` of the whole map by scipy's Euclidean distance transform (its readable twin)."""
    jump = np.zeros(d.shape, bool)
    for axis in (0, 1):
        step = np.abs(np.diff(d, axis=axis)) > JUMP_PX
        lead = [slice(None)] * 2
        lead[axis] = slice(None, -1)
        jump[tuple(lead)] |= step
        lead[axis] = slice(1, None)
        jump[tuple(lead)] |= step
    if not jump.any():
        return np.full(d.shape, float(JUMP_REACH_PX))
    from scipy import ndimage

    return np.minimum(ndimage.distance_transform_edt(~jump), JUMP_REACH_PX)


def local_spread(d: np.ndarray, size: int = 5) -> np.ndarray:
    """``(H, W)`` standard deviation of ``d`` in each ``size`` box (px/view; borders reflected)."""
    from scipy import ndimage

    mean = ndimage.uniform_filter(d, size)
    return np.sqrt(np.maximum(ndimage.uniform_filter(d * d, size) - mean * mean, 0.0))


#: Rows of the image whose features are computed at once (each band with :data:`HALO_ROWS` more
#: above and below): the step holds a band's ``(rows, W, F)`` features, not the image's.
BAND_ROWS = 64
#: Rows around a band that its features read: the jump distance's reach (a jump is a step between
#: 4-neighbours, so one row more); the 5x5 median, the box spread and the slope read less.
HALO_ROWS = JUMP_REACH_PX + 1
#: Pixels whose model sum (``f . c``) is taken in one call: a multiple of 4 and too few for BLAS to
#: split between threads, so every pixel's sum is taken by the same kernel in the same order
#: whatever the band, the image size or the number of threads.
LOGISTIC_CHUNK = 256
#: Chunks whose features are copied to float64 and summed at once (a copy of 590 kB).
LOGISTIC_BLOCK = 16
#: The features a band is given last, band after band (:func:`probability_right`): the box spread
#: carries its running sums down the image, the heuristic is made beside the other features.
LATE_FEATURES = ("log_spread", "heuristic")
#: Bands whose features are made while the heuristic is, beyond one per thread: the features of up
#: to ``threads + BANDS_AHEAD`` bands are held at once (2 threads: 8 bands, 74 MB at 2000 pixels a row;
#: 9.2 MB a band). On backgammon the bands made while the heuristic is cover all of its 8 bands.
BANDS_AHEAD = 6


class FeatureInputs:
    """The ``(H, W)`` maps the features are computed from (the whole image's, as given: no copies)
    and the numbers they share; arguments as :func:`confidence_features`. :meth:`band` gives the
    features of a band of rows."""

    def __init__(self, *, refined, matched, initial, ambiguity, labels, holes, noise_limited, window_size,
                 cost, noise_sigma, step, heuristic, entropy, median=None) -> None:
        self.refined = np.asarray(refined)
        self.shape = self.refined.shape
        self.matched, self.initial, self.ambiguity = np.asarray(matched), np.asarray(initial), np.asarray(ambiguity)
        self.labels, self.window_size, self.cost = np.asarray(labels), np.asarray(window_size), np.asarray(cost)
        self.holes = None if holes is None else np.asarray(holes)
        self.noise_limited = None if noise_limited is None else np.asarray(noise_limited)
        self.heuristic = None if heuristic is None else np.asarray(heuristic)  # None: set before the bands
        self.entropy = np.asarray(entropy)
        self.median = median  # the 5x5 median of d when every value is finite (finite_median5), or None
        self.step = float(step)
        self.noise = max(float(noise_sigma), 0.5 / 255)
        self.spread = _BoxSpread(self.d_rows, self.shape)

    def d_rows(self, a: int, b: int) -> np.ndarray:
        """``d``: the final disparity of rows ``[a, b)``, float64, 0 where not finite."""
        refined = np.asarray(self.refined[a:b], np.float64)
        return np.where(np.isfinite(refined), refined, 0.0)

    def band(self, y0: int, y1: int, skip: tuple[str, ...] = ()) -> np.ndarray:
        """``(y1 - y0, W, len(FEATURES))`` float32 features of rows ``[y0, y1)``, the same values
        as of the whole image (bands taken top to bottom: the box spread carries its running sums).
        The features named in ``skip`` are left unset (:meth:`finish` sets them)."""
        band = Band(self, y0, y1)
        # a feature a plane (contiguous stores), then the planes interleaved at once: 16 stores with
        # a stride of F values took twice as long
        planes = np.empty((len(FEATURES), y1 - y0, self.shape[1]), np.float32)
        for i, name in enumerate(FEATURES):
            if name not in skip:
                planes[i] = FEATURE_FUNCTIONS[name](band)
        return np.ascontiguousarray(planes.transpose(1, 2, 0))

    def finish(self, features: np.ndarray, y0: int, y1: int, names: tuple[str, ...]) -> np.ndarray:
        """``features`` of rows ``[y0, y1)`` (:meth:`band`'s) with the features ``names`` set."""
        band = Band(self, y0, y1)
        for name in names:
            features[..., FEATURES.index(name)] = FEATURE_FUNCTIONS[name](band)
        return features


class Band:
    """Rows ``[y0, y1)`` of :class:`FeatureInputs` with :data:`HALO_ROWS` around them (clipped to
    the image): ``d`` over the halo'd rows, ``core`` its rows ``[y0, y1)``, the maps the
    features share computed once."""

    def __init__(self, inputs: FeatureInputs, y0: int, y1: int) -> None:
        H = inputs.shape[0]
        self.inputs, self.y0, self.y1 = inputs, y0, y1
        self.a, self.b = max(y0 - HALO_ROWS, 0), min(y1 + HALO_ROWS, H)
        self.core = slice(y0 - self.a, y1 - self.a)
        self.d_halo = inputs.d_rows(self.a, self.b)
        self.d = self.d_halo[self.core]
        self._cache: dict[str, object] = {}

    def rows(self, name: str, dtype=np.float64) -> np.ndarray:
        """The input map ``name`` over the band's rows as ``dtype``."""
        return np.asarray(getattr(self.inputs, name)[self.y0:self.y1], dtype)

    def shared(self, name: str, make) -> object:
        if name not in self._cache:
            self._cache[name] = make()
        return self._cache[name]

    def median(self) -> np.ndarray:
        if self.inputs.median is not None:
            return self.rows("median")
        return self.shared("median", lambda: median_filter_nearest(
            self.d_halo.astype(np.float32), size=5).astype(np.float64)[self.core])

    def _neighbours_and_slope(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.shared("neighbours", lambda: neighbours_and_slope(self.d_halo, (self.core.start, self.core.stop)))

    def slope(self) -> np.ndarray:
        return self._neighbours_and_slope()[2]

    def neighbours(self) -> tuple[np.ndarray, np.ndarray]:
        return self._neighbours_and_slope()[:2]


def _flag(name: str):
    def feature(b: Band) -> np.ndarray:
        value = getattr(b.inputs, name)
        return np.zeros(b.d.shape, bool) if value is None else np.asarray(value[b.y0:b.y1], bool)
    return feature


#: One function per feature: ``f(band) -> (rows, W)`` values of the band's rows (any dtype; stored
#: as float32). A new feature is one more entry here and its name in :data:`FEATURES`.
FEATURE_FUNCTIONS = {
    "log_width": lambda b: np.log(np.maximum(b.rows("ambiguity") - 1, 0) * b.inputs.step + b.inputs.step),
    "log_change": lambda b: np.log(np.abs(b.d - np.nan_to_num(b.rows("matched"))) + _EPS),
    "log_neighbour": lambda b: np.log(np.abs(b.d - b.median()) + _EPS),
    "log_initial": lambda b: np.log(np.abs(b.d - np.nan_to_num(b.rows("initial"))) + _EPS),
    "occluding": lambda b: b.rows("labels", None) == OCCLUDING,
    "occluded": lambda b: b.rows("labels", None) == OCCLUDED,
    "texture": lambda b: b.rows("labels", None) == TEXTURE,
    "hole": _flag("holes"),
    "noise_limited": _flag("noise_limited"),
    "log_cost": lambda b: np.log(np.maximum(np.nan_to_num(b.rows("cost")), 0.0) / b.inputs.noise + _EPS),
    "window_size": lambda b: b.rows("window_size") / 15.0,
    "log_slope": lambda b: np.log(b.slope() + _EPS),
    "heuristic": lambda b: b.rows("heuristic"),
    "log_nearest_neighbour": lambda b: np.log(b.neighbours()[0] + _EPS),
    "neighbours_agreeing": lambda b: b.neighbours()[1] / 8.0,
    "log_jump_distance": lambda b: np.log(jump_distance(b.d_halo, rows=(b.core.start, b.core.stop)) + 1.0),
    "log_spread": lambda b: np.log(b.inputs.spread.rows(b.y0, b.y1) + _EPS),
    "entropy": lambda b: np.maximum(np.nan_to_num(b.rows("entropy")), ENTROPY_FLOOR),
}


class _BoxSpread:
    """:func:`local_spread` (``size`` 5, borders reflected) of the rows of ``d_rows(a, b)`` band by
    band, top to bottom, with the very values of the whole image's. ``scipy.ndimage.uniform_filter``
    filters down the columns first with a running sum (the first ``size`` samples summed in order,
    then ``+= (entering - leaving)``, each output the sum over ``size``), then along the rows; the
    running sums down the columns are carried from band to band, the rows are whole."""

    def __init__(self, d_rows, shape: tuple[int, int], size: int = 5) -> None:
        self.d_rows, self.shape, self.size = d_rows, shape, size
        H = shape[0]
        half = size // 2
        # the row each extended row (``half`` reflected rows above and ``size - half - 1`` below) reads
        self.source = np.pad(np.arange(H), (half, size - half - 1), mode="symmetric")
        self.next_row = 0
        self.sums: tuple[np.ndarray, np.ndarray] | None = None

    def _extended(self, e0: int, e1: int) -> tuple[np.ndarray, np.ndarray]:
        """``d`` and ``d * d`` of the extended rows ``[e0, e1)``."""
        rows = self.source[e0:e1]
        lo = int(rows.min())
        d = self.d_rows(lo, int(rows.max()) + 1)[rows - lo]
        return d, d * d

    def rows(self, y0: int, y1: int) -> np.ndarray:
        """``(y1 - y0, W)`` float64 spread of rows ``[y0, y1)``, the rows after the last ones asked."""
        if y0 != self.next_row:
            raise ValueError(f"the box spread goes top to bottom: rows from {self.next_row} next, not {y0}")
        size, carried = self.size, self.sums is not None
        # extended row y + k is the k-th sample of row y; a carried sum first drops row y0 - 1's
        e0 = y0 - 1 if carried else y0
        off = y0 - e0
        columns, sums = [], []
        n = y1 - y0
        for q, values in enumerate(self._extended(e0, y1 + size - 1)):
            if carried:
                tmp, first = self.sums[q], 0
            else:
                tmp = values[0].copy()
                for k in range(1, size):
                    tmp += values[k]
                first = 1
            # row y's sum is row y - 1's plus (entering - leaving): a running sum down the columns,
            # which np.cumsum takes in that order, one addition a row (an accumulation, not pairwise)
            running = np.empty((n + 1 - first, self.shape[1]))
            running[0] = tmp
            np.subtract(values[off + first + size - 1:off + n + size - 1], values[off + first - 1:off + n - 1],
                        out=running[1:])
            np.cumsum(running, axis=0, out=running)
            columns.append(running[1 - first:] / size)
            sums.append(running[-1].copy())
        self.sums = (sums[0], sums[1])
        self.next_row = y1
        from recon.entropy.filters import uniform_filter1d

        mean, mean2 = (uniform_filter1d(c, size, axis=1) for c in columns)
        return np.sqrt(np.maximum(mean2 - mean * mean, 0.0))


def confidence_features(*, refined: np.ndarray, matched: np.ndarray, initial: np.ndarray,
                        ambiguity: np.ndarray, labels: np.ndarray, holes: np.ndarray | None,
                        noise_limited: np.ndarray | None, window_size: np.ndarray, cost: np.ndarray,
                        noise_sigma: float, step: float, disparity_range: tuple[float, float],
                        heuristic: np.ndarray, entropy: np.ndarray) -> np.ndarray:
    """``(H, W, len(FEATURES))`` float32 features of every pixel (module docstring).

    ``refined``, ``matched``, ``initial``: ``(H, W)`` final, matched and initial disparity (px/view);
    ``ambiguity``: candidates within the hole tolerance of the least objective; ``labels``: region
    types; ``holes``, ``noise_limited``: ``(H, W)`` bool or ``None``; ``window_size``: pixels;
    ``cost``: matching cost (mean absolute difference, without the entropy term) at the chosen
    disparity, ``[0, 1]`` grey units like ``noise_sigma`` (:func:`matching_cost`);
    ``step``: candidate spacing; ``heuristic``: :func:`recon.entropy.confidence.confidence_map`;
    ``entropy``: ``(H, W)`` matching entropy of the chosen window. Computed in bands of
    :data:`BAND_ROWS` rows (:class:`FeatureInputs`); :func:`probability_right` keeps one band's.
    """
    inputs = FeatureInputs(refined=refined, matched=matched, initial=initial, ambiguity=ambiguity, labels=labels,
                           holes=holes, noise_limited=noise_limited, window_size=window_size, cost=cost,
                           noise_sigma=noise_sigma, step=step, heuristic=heuristic, entropy=entropy)
    H, W = inputs.shape
    out = np.empty((H, W, len(FEATURES)), np.float32)
    for y0 in range(0, H, BAND_ROWS):
        out[y0:y0 + BAND_ROWS] = inputs.band(y0, min(y0 + BAND_ROWS, H))
    return out


def load_coefficients() -> tuple[float, tuple[float, ...]]:
    """``(bias, coefficients)`` of the fitted model (``recon/entropy/confidence_fit.py``), in
    :data:`FEATURES` order."""
    from recon.entropy.confidence_fit import FIT

    if tuple(FIT["features"]) != FEATURES:
        raise ValueError(f"recon/entropy/confidence_fit.py was fitted for features {FIT['features']}, the "
                         f"code has {list(FEATURES)}; refit with bench/confidence_fit.py")
    return float(FIT["bias"]), tuple(float(c) for c in FIT["coefficients"])


def logistic(features: np.ndarray, bias: float, coefficients) -> np.ndarray:
    """``(..., F)`` features -> ``(...)`` float64 probability ``1 / (1 + exp(-(b + f . c)))``."""
    return _squash(bias + np.asarray(features, np.float64) @ np.asarray(coefficients, np.float64))


def _squash(z: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(z, -40, 40)))


def valid_pixels(refined: np.ndarray, matched: np.ndarray, *, step: float,
                 disparity_range: tuple[float, float]) -> np.ndarray:
    """``(H, W)`` bool: finite, inside the searched range, and not matched on its first or last
    candidate (no minimum inside the range: the true one may lie outside)."""
    lo, hi = disparity_range
    refined = np.asarray(refined, np.float64)
    matched = np.asarray(matched, np.float64)
    on_end = (np.abs(matched - lo) < 0.5 * step) | (np.abs(matched - hi) < 0.5 * step)
    with np.errstate(invalid="ignore"):
        inside = np.isfinite(refined) & (refined >= lo - 1e-6) & (refined <= hi + 1e-6)
    return inside & ~on_end


def probability_right(*, refined: np.ndarray, matched: np.ndarray, initial: np.ndarray,
                      ambiguity: np.ndarray, labels: np.ndarray, holes: np.ndarray | None,
                      noise_limited: np.ndarray | None, window_size: np.ndarray, cost: np.ndarray,
                      entropy: np.ndarray, noise_sigma: float, step: float,
                      disparity_range: tuple[float, float], hole_support: float = 0.25, hole_ramp: float = 0.1,
                      valley_px: float = 0.3, coefficients: tuple[float, tuple[float, ...]] | None = None,
                      threads: int | None = None) -> np.ndarray:
    """``(H, W)`` float32: the probability that ``|refined - truth| <= 0.07`` px/view per pixel.

    Inputs as :func:`confidence_features`; ``hole_support``, ``hole_ramp``, ``valley_px`` are the
    heuristic's (:func:`recon.entropy.confidence.confidence_map`); ``coefficients`` ``(bias,
    coefficients)``, default the fitted ones (:func:`load_coefficients`). The features are made and
    used a band of :data:`BAND_ROWS` rows at a time: the step's memory is the heuristic's, the
    output and a few bands' features, not ``(H, W, F)``. ``threads``: how many make them (default
    :func:`recon.native.thread_count`; the values are the same for any number)."""
    median = finite_median5(refined)  # the heuristic's and the features' 5x5 median, made once

    def heuristic() -> np.ndarray:
        return confidence_map(refined=refined, matched=matched, ambiguity=ambiguity, step=step,
                              disparity_range=disparity_range, holes=holes, valley_px=valley_px,
                              hole_support=hole_support, hole_ramp=hole_ramp, median=median)

    inputs = FeatureInputs(refined=refined, matched=matched, initial=initial, ambiguity=ambiguity, labels=labels,
                           holes=holes, noise_limited=noise_limited, window_size=window_size, cost=cost,
                           noise_sigma=noise_sigma, step=step, heuristic=None, entropy=entropy, median=median)
    bias, coef = coefficients if coefficients is not None else load_coefficients()
    H, W = inputs.shape
    out = np.empty((H, W), np.float32)
    bands = [(y0, min(y0 + BAND_ROWS, H)) for y0 in range(0, H, BAND_ROWS)]

    def finish(features: np.ndarray, y0: int, y1: int) -> None:
        p = logistic_in_chunks(features, bias, coef)
        ok = valid_pixels(refined[y0:y1], matched[y0:y1], step=step, disparity_range=disparity_range)
        out[y0:y1] = np.where(ok, p, 0.0)

    threads = min(thread_count(), len(bands) + 1) if threads is None else int(threads)
    if threads <= 1:
        inputs.heuristic = heuristic()
        for y0, y1 in bands:
            finish(inputs.band(y0, y1), y0, y1)
        return out
    # the heuristic (its holes' harmonic fill the longest part) beside the box spread (carried from
    # band to band: one job, top to bottom) and the bands' other features; a band's last features and
    # its model sums once both are made: every band's values are those of one thread, in one order
    from concurrent.futures import ThreadPoolExecutor

    def spreads() -> list[np.ndarray]:
        return [FEATURE_FUNCTIONS["log_spread"](Band(inputs, y0, y1)).astype(np.float32) for y0, y1 in bands]

    ahead = threads + BANDS_AHEAD
    with ThreadPoolExecutor(max_workers=threads) as pool:
        made, spread = pool.submit(heuristic), pool.submit(spreads)
        made_bands = [pool.submit(inputs.band, y0, y1, LATE_FEATURES) for y0, y1 in bands[:ahead]]
        inputs.heuristic, spread_rows = made.result(), spread.result()
        finished = []
        for i, (y0, y1) in enumerate(bands):
            features = made_bands[i].result()
            made_bands[i] = None  # the job that takes the model's sums holds the band's features until done
            features[..., FEATURES.index("log_spread")] = spread_rows[i]
            finished.append(pool.submit(finish, inputs.finish(features, y0, y1, ("heuristic",)), y0, y1))
            if i + ahead < len(bands):
                made_bands.append(pool.submit(inputs.band, *bands[i + ahead], LATE_FEATURES))
        for job in finished:
            job.result()
    return out


def logistic_in_chunks(features: np.ndarray, bias: float, coefficients) -> np.ndarray:
    """:func:`logistic` of ``(..., F)`` features, the sums ``f . c`` taken :data:`LOGISTIC_CHUNK`
    pixels at a time (each pixel's sum taken by the same BLAS kernel whatever the band), the rest
    over all pixels at once. The chunks go :data:`LOGISTIC_BLOCK` at a time through one float64 copy
    and one stacked product (numpy's matmul calls the same matrix-vector kernel on each chunk)."""
    flat = features.reshape(-1, features.shape[-1])
    c = np.asarray(coefficients, np.float64)
    n = flat.shape[0]
    z = np.empty(n)
    step = LOGISTIC_CHUNK * LOGISTIC_BLOCK
    for i in range(0, n, step):
        j = min(i + step, n)
        whole = i + (j - i) // LOGISTIC_CHUNK * LOGISTIC_CHUNK
        block = np.asarray(flat[i:j], np.float64)
        if whole > i:
            np.matmul(block[:whole - i].reshape(-1, LOGISTIC_CHUNK, block.shape[1]), c,
                      out=z[i:whole].reshape(-1, LOGISTIC_CHUNK))
        if j > whole:
            z[whole:j] = block[whole - i:] @ c
    return _squash(bias + z).reshape(features.shape[:-1])


def calibration_scores(confidence: np.ndarray, right: np.ndarray, *, bins: int = 10,
                       threshold: float = 0.5) -> dict[str, float]:
    """How well ``confidence`` (``(N,)`` probabilities) predicts ``right`` (``(N,)`` bool).

    ``ece``: expected calibration error over ``bins`` equal-width bins (the pixel-weighted mean of
    ``|mean confidence - share right|`` per bin); ``kept``: share of pixels at ``>= threshold``;
    ``bad_kept``: BadPix (%) among them, against ``bad_all`` (%) of all; ``right_kept``: share of
    the right pixels that are kept."""
    c = np.asarray(confidence, np.float64).ravel()
    r = np.asarray(right, bool).ravel()
    if c.size == 0:
        raise ValueError("no pixels to score")
    index = np.minimum((c * bins).astype(np.int64), bins - 1)
    ece = 0.0
    for b in range(bins):
        m = index == b
        if m.any():
            ece += m.sum() / c.size * abs(c[m].mean() - r[m].mean())
    kept = c >= threshold
    return {"ece": float(ece), "kept": float(kept.mean()),
            "bad_all": float(100 * (1 - r.mean())),
            "bad_kept": float(100 * (1 - r[kept].mean())) if kept.any() else float("nan"),
            "right_kept": float(kept[r].mean()) if r.any() else float("nan")}


def reliability(confidence: np.ndarray, right: np.ndarray, *, bins: int = 10
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reliability diagram data: per equal-width bin, ``(mean confidence, share right, pixels)``
    (NaN for empty bins)."""
    c = np.asarray(confidence, np.float64).ravel()
    r = np.asarray(right, bool).ravel()
    index = np.minimum((c * bins).astype(np.int64), bins - 1)
    n = np.bincount(index, minlength=bins).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_c = np.bincount(index, c, minlength=bins) / n
        share = np.bincount(index, r.astype(np.float64), minlength=bins) / n
    return mean_c, share, n


def sparsification(confidence: np.ndarray, error: np.ndarray, *, steps: int = 20
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Sparsification curve: ``(fraction removed, BadPix 0.07 % of the rest)`` when the least
    confident pixels are removed first, at ``steps`` evenly spaced fractions in ``[0, 1)``.
    ``error``: ``(N,)`` absolute disparity errors (non-finite counts as wrong)."""
    c = np.asarray(confidence, np.float64).ravel()
    bad = ~(np.abs(np.asarray(error, np.float64).ravel()) <= TOLERANCE_PX)
    order = np.argsort(-c, kind="stable")  # most confident first
    bad_sorted = bad[order]
    n = c.size
    fractions = np.arange(steps) / steps
    out = []
    for f in fractions:
        keep = max(1, int(round(n * (1 - f))))
        out.append(100.0 * bad_sorted[:keep].mean())
    return fractions, np.asarray(out)


def matching_cost(objective: np.ndarray, entropy: np.ndarray, *, lambda_entropy: float,
                  intensity_scale: float) -> np.ndarray:
    """``(H, W)`` mean absolute grey difference (``[0, 1]`` units) at the chosen disparity from Eq.
    7's objective ``intensity_scale * cost - lambda * E`` and the chosen window's entropy ``E``."""
    return (np.asarray(objective, np.float64) + lambda_entropy * np.asarray(entropy, np.float64)) / intensity_scale


def result_features(result) -> tuple[np.ndarray, np.ndarray]:
    """``(features (H, W, F) float32, valid (H, W) bool)`` of an
    :class:`recon.entropy.estimate.EntropyResult` (its maps and ``info``), as
    :func:`probability_right` computes them: the data of ``bench/confidence_fit.py``."""
    opts = result.options
    info = result.info
    common = dict(refined=result.disparity, matched=result.matched_disparity, ambiguity=info["ambiguity"],
                  step=opts.step, disparity_range=result.disparity_range, holes=info["holes"])
    heuristic = confidence_map(**common, valley_px=opts.hole_width, hole_support=opts.hole_support,
                               hole_ramp=opts.hole_ramp)
    features = confidence_features(**common, initial=result.initial_disparity, labels=result.labels,
                                   noise_limited=info.get("noise_limited"), window_size=result.window_size,
                                   cost=matching_cost(result.cost, result.entropy, lambda_entropy=opts.lambda_entropy,
                                                      intensity_scale=opts.intensity_scale),
                                   noise_sigma=info["noise_sigma"], heuristic=heuristic, entropy=result.entropy)
    valid = valid_pixels(result.disparity, result.matched_disparity, step=opts.step,
                         disparity_range=result.disparity_range)
    return features, valid
