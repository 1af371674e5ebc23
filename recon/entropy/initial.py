"""Initial disparity from the nine views of Section 4.1: the centre and the farthest view in each of
the eight directions (the four corners and the four edge midpoints of the grid).

The paper does not say how this estimate is made. Its uses are the depth-ordered layers of the
region map (Eq. 9), the disparity-consistency term of the matching entropy (Eq. 1, Section 4.2) and,
when the light field does not say, the disparity search range; all three suffer if the estimate is
fattened at occlusion edges, which a fixed square window does (its window straddles the edge and the
side views see the background occluded). So the cost at each candidate is the least over the full
square and the eight side windows W1..W8 of one size, each matched over its own visible-viewpoint
set (``recon.entropy.windows``), i.e. the paper's own shapes and sets used as shiftable windows.
On backgammon this alone takes BadPix 0.07 from 18 % (square window, nine views) to about 9 %.
"""

from __future__ import annotations

from recon.jit import numba
import numpy as np

from recon.entropy.matching import disparity_candidates, min_window_line_search
from recon.entropy.windows import N_SHAPES, STRIP_SHAPES
from recon.native import call, chosen, thread_count


def initial_view_mask(grid_shape: tuple[int, int]) -> np.ndarray:
    """``(U, V)`` bool: the centre view and the farthest view in each of the eight directions."""
    U, V = grid_shape
    mask = np.zeros((U, V), bool)
    for u in (0, U // 2, U - 1):
        for v in (0, V // 2, V - 1):
            mask[u, v] = True
    return mask


def initial_disparity(gray: np.ndarray, *, disparity_range: tuple[float, float], step: float,
                      window: int, shiftable: bool = True, strips: bool = True,
                      ambiguity_delta: float | None = None, progress=None,
                      strip_ok: np.ndarray | None = None):
    """Line search over the nine views of :func:`initial_view_mask` (see the module docstring).

    Parameters
    ----------
    gray
        ``(U, V, H, W)`` float32 light field in ``[0, 1]``.
    disparity_range
        ``(d_min, d_max)`` searched, pixels per view step.
    step
        Candidate spacing in pixels per view step (refined to sub-step by a parabola).
    window
        Side of the square window in pixels (odd).
    shiftable
        Least cost over the square and W1..W8 with their visible sets (default) or the square alone.
    strips
        With ``shiftable``, also the two strip windows with their sets (lfrig's extension).
    strip_ok
        ``(H, W, 2)`` bool or ``None``: where the horizontal and the vertical strip may be used
        (:func:`recon.entropy.aperture.informative_strips`); default everywhere.

    Returns
    -------
    ``(disparity, cost)``: ``(H, W)`` float32 each; cost is the mean absolute difference at the minimum.
    With ``ambiguity_delta`` (grey units of ``gray``) also ``matching.cost_ambiguity`` of the cost
    curves. ``progress(fraction)`` is called after each candidate.
    """
    U, V = gray.shape[:2]
    candidates = disparity_candidates(disparity_range[0], disparity_range[1], step)
    shapes = list(range(N_SHAPES if strips else 9) if shiftable else (0,))
    allowed = None
    if strip_ok is not None and len(shapes) == N_SHAPES:
        H, W = gray.shape[2:]
        allowed = np.ones((H, W, N_SHAPES), bool)
        allowed[..., list(STRIP_SHAPES)] = strip_ok
    return min_window_line_search(gray, candidates, windows=[(s, window, s) for s in shapes],
                                  view_mask=initial_view_mask((U, V)),
                                  ambiguity_delta=ambiguity_delta, progress=progress, allowed=allowed)


def range_from_initial(d0: np.ndarray, *, percentile: float, margin: float,
                       limits: tuple[float, float], grid_shape: tuple[int, int] | None = None,
                       sure: np.ndarray | None = None) -> tuple[float, float]:
    """Search range for the full matching: robust extent of ``d0`` widened by ``margin``.

    ``[P(percentile) - margin, P(100 - percentile) + margin]`` of the initial disparity, clipped to
    ``limits`` (the range the initial search covered). With ``grid_shape`` ``(U, V)`` the
    percentiles leave out the pixels whose own disparity makes the farthest views sample outside
    the image (:func:`interior`): edge pixels repeated there match at odd disparities.
    With ``sure`` (``(H, W)`` bool) only those pixels count, when they are at least a tenth of the
    image: a textureless structure matches at any disparity (:func:`sure_pixels`).
    """
    if sure is not None and np.count_nonzero(sure) >= 0.1 * sure.size:
        d0 = np.where(sure, d0, np.nan)
    d0 = interior(d0, grid_shape=grid_shape) if grid_shape is not None else d0[np.isfinite(d0)]
    lo, hi = np.percentile(d0, [percentile, 100.0 - percentile])
    return float(max(lo - margin, limits[0])), float(min(hi + margin, limits[1]))


def interior(d: np.ndarray, *, grid_shape: tuple[int, int]) -> np.ndarray:
    """The finite values of ``(H, W)`` ``d`` whose pixel every view sees inside the image: at a
    disparity ``d`` the farthest views (``grid radius`` steps away) sample ``radius * |d|`` pixels
    off, and a pixel whose samples leave the image matched against repeated edge pixels (all finite
    values if that leaves fewer than a tenth of them)."""
    H, W = d.shape
    radius = max(grid_shape) // 2
    yy, xx = np.mgrid[0:H, 0:W]
    reach = radius * np.abs(d)
    with np.errstate(invalid="ignore"):
        inside = ((yy >= reach) & (yy <= H - 1 - reach) & (xx >= reach) & (xx <= W - 1 - reach))
    finite = np.isfinite(d)
    keep = inside & finite
    return d[keep] if np.count_nonzero(keep) >= 0.1 * np.count_nonzero(finite) else d[finite]


def downsample_views_reference(gray: np.ndarray, factor: int) -> np.ndarray:
    """``(U, V, H // factor, W // factor)`` float32: every view box-averaged over ``factor`` x
    ``factor`` blocks (the last rows/columns that do not fill a block are left out). A disparity of
    ``d`` pixels per view step in ``gray`` is ``d / factor`` in the result. Readable twin of
    :func:`downsample_views`."""
    U, V, H, W = gray.shape
    h, w = H // factor, W // factor
    blocks = gray[:, :, :h * factor, :w * factor].reshape(U, V, h, factor, w, factor)
    return blocks.mean(axis=(3, 5), dtype=np.float32)


@numba.njit(cache=True, parallel=True, nogil=True)
def _downsample_kernel(gray, factor, out):
    # downsample_views_reference's float32 sums in numpy's order: each of a block's rows summed
    # from 0 left to right (numpy's pairwise sum is sequential below 8 values), the row sums added
    # top to bottom, then divided by the count. A row of blocks at a time, all views in parallel.
    U, V, h, w = out.shape
    count = np.float32(factor * factor)
    for k in numba.prange(U * V * h):
        u = k // (V * h)
        v = (k // h) % V
        y = k % h
        for x in range(w):
            acc = np.float32(0.0)
            for i in range(factor):
                row = np.float32(0.0)
                for j in range(factor):
                    row += gray[u, v, y * factor + i, x * factor + j]
                acc += row
            out[u, v, y, x] = acc / count


def downsample_views(gray: np.ndarray, factor: int, *, kernel: str = "auto") -> np.ndarray:
    """``(U, V, H // factor, W // factor)`` float32: every view box-averaged over ``factor`` x
    ``factor`` blocks (the last rows/columns that do not fill a block are left out). A disparity of
    ``d`` pixels per view step in ``gray`` is ``d / factor`` in the result. Compiled twin of
    :func:`downsample_views_reference`, the same values; by the twin itself where numpy sums in
    another order: factors of 8 and more (their rows summed pairwise) and results one pixel wide.
    C (``recon/native/initial.c``) where it loads, else numba's (``kernel``: :func:`recon.native.chosen`)."""
    U, V, H, W = gray.shape
    if not 1 <= factor < 8 or W // factor < 2 or gray.dtype != np.float32 or not gray.flags.c_contiguous:
        return downsample_views_reference(gray, factor)
    out = np.empty((U, V, H // factor, W // factor), np.float32)
    if chosen("initial", kernel):
        call("initial", "lfrig_downsample", gray, U, V, H, W, int(factor), out, H // factor, W // factor,
             thread_count())
        return out
    _downsample_kernel(gray, int(factor), out)
    return out


def coarse_factor(shape: tuple[int, int], *, min_side_px: int = 96, max_factor: int = 4) -> int:
    """Downsampling factor of :func:`discover_range`: the largest up to ``max_factor`` that leaves
    the short side of the image at least ``min_side_px`` (1: too small to downsample)."""
    return int(max(1, min(max_factor, min(shape) // min_side_px)))


def sure_pixels(ambiguity: np.ndarray, *, step: float, width: float) -> np.ndarray:
    """``(H, W)`` bool: pixels whose cost valley (``ambiguity`` candidates of ``step`` within the
    tolerance of the least cost, :func:`recon.entropy.matching.cost_ambiguity`) is at most ``width``
    wide: the search told disparities apart there."""
    return ambiguity * step <= width


def discover_range(gray: np.ndarray, *, search_range: tuple[float, float], step: float,
                   window: int, percentile: float, margin: float, shiftable: bool = True,
                   strips: bool = True, ambiguity_delta: float = 0.5 / 255,
                   sure_width: float = 0.6) -> tuple[float, float]:
    """The disparity range of a light field whose range nobody gave, from a coarse nine-view search.

    The views are box-downsampled by :func:`coarse_factor` ``f`` (``f`` x ``f`` fewer pixels, and
    ``search_range / f`` to cover), searched with :func:`initial_disparity` at ``step`` coarse pixels
    (``f * step`` full-resolution), and the robust extent ``[P(percentile), P(100 - percentile)]``
    of the result over its sure pixels (cost valley at most ``sure_width`` full-resolution pixels
    wide at ``ambiguity_delta``, :func:`sure_pixels`: a thin textureless pole matches anywhere) away
    from the border (:func:`interior`), scaled back by ``f``, is widened by ``margin`` plus two coarse steps and clipped
    to ``search_range``. The full-resolution initial search then covers only that range: on a lab
    capture (1198 x 906, a scene at 3.6-4.1 px/view) it is about 30 candidates instead of 320 for
    ``search_range = (-8, 8)``, at the cost of about 20 full-resolution candidates.

    ``gray``: ``(U, V, H, W)`` float32 in ``[0, 1]``. Returns ``(d_min, d_max)`` in pixels per view
    step of ``gray``.
    """
    f = coarse_factor(gray.shape[2:])
    coarse = downsample_views(gray, f) if f > 1 else gray
    limits = (search_range[0] / f, search_range[1] / f)
    d, _, ambiguity = initial_disparity(coarse, disparity_range=limits, step=step, window=window,
                                        shiftable=shiftable, strips=strips,
                                        ambiguity_delta=ambiguity_delta)
    sure = sure_pixels(ambiguity, step=f * step, width=sure_width)
    if not np.isfinite(d).any():
        return float(search_range[0]), float(search_range[1])
    lo, hi = range_from_initial(d, percentile=percentile, margin=0.0, limits=limits,
                                grid_shape=gray.shape[:2], sure=sure)
    widen = margin + 2 * f * step
    return float(max(lo * f - widen, search_range[0])), float(min(hi * f + widen, search_range[1]))
