"""Region types of Section 4.1: occluding (0), occluded (1), texture (2), smooth (3) (Eq. 8).

Segmentation (Eq. 9). The paper segments the nine views by alpha matting so that closer objects get
larger values of ``M``. Here the depth-ordered layers are the initial disparity itself, median
filtered (``M = median(d0)``: larger is closer, as the paper requires), and two pixels are in
*different layers* when their ``M`` differ by more than ``layer_gap`` pixels per view step (default
0.25: a depth step that moves one surface over the other by at least one pixel between the centre
and the farthest view of a 9x9 grid). This gives what the matting is used for, a depth order, without
a second, unrelated segmentation whose boundaries would not agree with the disparity, and a slanted
surface stays one layer because only neighbours *landing on the same pixel* are compared.

The segmentation of a side view ``(ui, vj)`` is the centre segmentation forward-warped into it with
the initial disparity (each centre pixel lands at ``(y - du d0, x - dv d0)``, rounded): at each
pixel of the side view we keep the largest layer that lands there (what that view sees) and the
smallest (what is hidden behind it). Eq. 9 compares ``M_centre(p)`` with the side view *where p
lands* (the README's reading of the shift ``(x + du, y + dv)``):

- occluded (Eq. 10): a closer layer lands on p's spot in at least one view
  (``sum_ij min(0, M_c(p) - M_ij^max(p_ij) + gap) < 0``),
- occluding (Eq. 11): p lands on a farther layer in at least one view and p is not occluded,
- smooth (Eq. 12): ``psi(p) < tau = N / 2`` where ``psi`` counts the ``N`` neighbours (a square of
  side ``smooth_neighbourhood`` without its centre) whose grey value differs from p's by more than a
  tolerance ``smooth_tolerance * sigma_noise`` (sigma estimated from the centre view, Immerkaer 1996),
- texture: the rest.
"""

from __future__ import annotations

from recon.jit import numba
import numpy as np

from recon.entropy.initial import initial_view_mask
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH, TEXTURE
from recon.entropy.median import median_filter_nearest
from recon.native import call, chosen, thread_count


def layer_map(d0: np.ndarray, *, median_size: int, keep: np.ndarray | None = None) -> np.ndarray:
    """Depth-ordered layer value ``M`` of the centre view: the median-filtered initial disparity,
    except at the ``keep`` pixels (``(H, W)`` bool, e.g. where ``d0`` was matched unambiguously),
    which keep ``d0`` itself, so that a structure thinner than the median (a slit, a wire) that was
    matched well is not erased."""
    if median_size <= 1:
        return d0.astype(np.float32)
    d0 = d0.astype(np.float32)
    smooth = median_filter_nearest(d0, size=median_size)
    if keep is None:
        return smooth
    # Only a pixel that lies on a line of like values (a row or a column of three) is kept: a
    # one-pixel slit survives, an isolated outlier does not.
    row = median_filter_nearest(d0, size=(1, 3))
    col = median_filter_nearest(d0, size=(3, 1))
    tol = 0.1
    on_line = (np.abs(d0 - row) <= tol) | (np.abs(d0 - col) <= tol)
    return np.where(keep & on_line, d0, smooth)


def occlusion_diffs_reference(layers: np.ndarray, offsets: list[tuple[int, int]], *,
                              layer_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 9 split by sign (readable reference).

    Parameters
    ----------
    layers
        ``(H, W)`` float32 layer value ``M`` (disparity-like: larger is closer).
    offsets
        ``(du, dv)`` of the side views compared with the centre.
    layer_gap
        Layers closer than this count as equal.

    Returns
    -------
    ``(diff_occluded, diff_occluding)``, ``(H, W)`` float32: the sum over views of the negative parts
    (something closer lands on the pixel's spot) and of the positive parts (the pixel covers something
    farther) of ``M_c(p) - M_ij(p_ij)``, each counted only beyond ``layer_gap``.
    """
    H, W = layers.shape
    neg = np.zeros((H, W), np.float64)
    pos = np.zeros((H, W), np.float64)
    for du, dv in offsets:
        top = np.full((H, W), -np.inf)
        bottom = np.full((H, W), np.inf)
        land = np.empty((H, W, 2), np.int64)
        for y in range(H):
            for x in range(W):
                ly = int(np.floor(y - du * layers[y, x] + 0.5))
                lx = int(np.floor(x - dv * layers[y, x] + 0.5))
                land[y, x] = ly, lx
                if 0 <= ly < H and 0 <= lx < W:
                    top[ly, lx] = max(top[ly, lx], layers[y, x])
                    bottom[ly, lx] = min(bottom[ly, lx], layers[y, x])
        for y in range(H):
            for x in range(W):
                ly, lx = land[y, x]
                if 0 <= ly < H and 0 <= lx < W:
                    m = layers[y, x]
                    if top[ly, lx] - m > layer_gap:
                        neg[y, x] += m - top[ly, lx]
                    if m - bottom[ly, lx] > layer_gap:
                        pos[y, x] += m - bottom[ly, lx]
    return neg.astype(np.float32), pos.astype(np.float32)


@numba.njit(cache=True)
def _landing(y, x, m, du, dv):
    # Where pixel (y, x) of layer value m lands in view (du, dv), rounded to a pixel.
    return int(np.floor(y - du * m + 0.5)), int(np.floor(x - dv * m + 0.5))


@numba.njit(cache=True, parallel=True)
def _occlusion_kernel(layers, offsets, layer_gap, row_shift, band_rows, row_start, runs, neg, pos):
    # The rows in bands of band_rows, run in parallel, every view of a band in turn (the band's pixels
    # stay in the cache from view to view); of each row only the runs of pixels
    # runs[row_start[y]:row_start[y + 1]] (x0, x1) (the others are neither occluded nor occluding nor
    # the top or bottom layer that decides another pixel's test: occlusion_diffs). In view k a pixel
    # lands between row_shift[k, 0] and row_shift[k, 1] rows from its own, so a band's pixels read the
    # top and bottom layers of the rows that far from the band, and only pixels that far from those
    # land there: each band forward-warps those into its own copy of that stretch of rows (a spot that
    # holds another view's layers starts again). A maximum and a minimum do not depend on the order of
    # their values, and each pixel sums its views in their order: the serial kernel's maps.
    H, W = layers.shape
    span = np.max(row_shift[:, 1] - row_shift[:, 0])
    for b in numba.prange((H + band_rows - 1) // band_rows):
        lo, hi = b * band_rows, min((b + 1) * band_rows, H)
        top = np.empty((hi - lo + span, W), np.float32)
        bottom = np.empty((hi - lo + span, W), np.float32)
        view = np.full((hi - lo + span, W), -1, np.int32)  # the view whose pixels a spot holds
        for k in range(offsets.shape[0]):
            du = offsets[k, 0]
            dv = offsets[k, 1]
            a, c = row_shift[k, 0], row_shift[k, 1]
            t0, t1 = max(lo + a, 0), min(hi - 1 + c, H - 1) + 1  # the rows the band reads
            s0, s1 = max(t0 - c, 0), min(t1 - 1 - a, H - 1) + 1  # the rows that land there
            for y in range(s0, s1):
                for i in range(row_start[y], row_start[y + 1]):
                    for x in range(runs[i, 0], runs[i, 1]):
                        m = layers[y, x]
                        ly, lx = _landing(y, x, m, du, dv)
                        if t0 <= ly < t1 and 0 <= lx < W:  # selects, not branches: both ways are common
                            first = view[ly - t0, lx] != k  # the first pixel of this view there
                            view[ly - t0, lx] = k
                            t = top[ly - t0, lx]
                            top[ly - t0, lx] = m if first or m > t else t
                            d = bottom[ly - t0, lx]
                            bottom[ly - t0, lx] = m if first or m < d else d
            for y in range(lo, hi):
                for i in range(row_start[y], row_start[y + 1]):
                    for x in range(runs[i, 0], runs[i, 1]):
                        m = layers[y, x]
                        ly, lx = _landing(y, x, m, du, dv)
                        if t0 <= ly < t1 and 0 <= lx < W:
                            # adding +0.0 leaves a sum of differences of one sign (never -0.0) as it is
                            t = top[ly - t0, lx]
                            neg[y, x] += m - t if t - m > layer_gap else np.float32(0)
                            d = bottom[ly - t0, lx]
                            pos[y, x] += m - d if m - d > layer_gap else np.float32(0)


#: Rows of the occlusion test's bands (:func:`occlusion_diffs`).
OCCLUSION_BAND_ROWS = 64


def box_extreme(image: np.ndarray, size, *, maximum: bool, kernel: str = "auto") -> np.ndarray:
    """``scipy.ndimage.maximum_filter`` (``maximum``) or ``minimum_filter`` of the ``(H, W)`` map
    ``image`` over a box of ``size`` (an int or ``(rows, columns)``, any size: an even one reaches
    one pixel less after the centre than before it) with the border continued by the nearest pixel
    (``mode="nearest"``), the same bits.

    ``kernel``: ``"scipy"`` (the reference) or ``"auto"``: OpenCV's dilation or erosion (a box of
    ones, the border replicated) where it gives scipy's bits, scipy's elsewhere. A maximum or
    minimum is one of the values in the box, so the two differ only where the box holds a NaN
    (their comparisons meet it in other orders) or zeros of both signs (which of two equal values
    is kept shows in the sign of a zero): OpenCV takes a float32 or float64 map without NaN and
    without -0.0 (a few passes over the map to check; infinities are fine). 5-10x faster than
    scipy's running extremes."""
    if kernel not in ("auto", "scipy"):
        raise ValueError(f"kernel must be 'auto' or 'scipy', got {kernel!r}")
    image = np.asarray(image)
    rows, columns = (int(size), int(size)) if np.ndim(size) == 0 else (int(size[0]), int(size[1]))
    if kernel == "auto" and image.ndim == 2 and image.size and image.dtype in (np.float32, np.float64):
        zeros = image == 0
        if not np.isnan(image).any() and not (zeros.any() and np.signbit(image[zeros]).any()):
            import cv2

            box = np.ones((rows, columns), np.uint8)
            image = np.ascontiguousarray(image)
            return (cv2.dilate if maximum else cv2.erode)(image, box, borderType=cv2.BORDER_REPLICATE)
    from scipy import ndimage

    return (ndimage.maximum_filter if maximum else ndimage.minimum_filter)(image, (rows, columns), mode="nearest")


def occlusion_diffs(layers: np.ndarray, offsets: list[tuple[int, int]], *,
                    layer_gap: float, kernel: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Compiled twin of :func:`occlusion_diffs_reference`, in bands of rows run in parallel (the C
    twin of the kernel, ``recon/native/regions.c``, where it loads, else numba's; ``kernel``:
    :func:`recon.native.chosen`).

    Two pixels that land on one spot of a view lie at most ``1 + |du| (M_max - M_min)`` rows
    (``|dv|`` columns) apart, so a pixel whose layer is within ``layer_gap`` of every layer in that
    box around it (most of a surface away from its depth edges) is neither occluded nor
    occluding, and where it is the top or bottom layer of a spot, no pixel landing there is told
    apart from it either: the test leaves such pixels out (their differences are 0). The rows a
    band reads around it follow from the spread of the layers' shifts, not from their size."""
    native = chosen("regions", kernel)
    layers = np.ascontiguousarray(layers, np.float32)
    offsets = np.ascontiguousarray(offsets, np.float64).reshape(-1, 2)
    H, W = layers.shape
    neg = np.zeros((H, W), np.float32)
    pos = np.zeros((H, W), np.float32)
    finite = np.isfinite(layers)
    if offsets.shape[0] == 0 or not finite.any():  # no view, or no pixel lands anywhere
        return neg, pos
    m_lo, m_hi = float(layers[finite].min()), float(layers[finite].max())
    # rows between a pixel and where it lands, least and most, per view (one more each side for
    # the rounding of y - du m + 0.5)
    shifts = np.stack([-offsets[:, 0] * m_lo, -offsets[:, 0] * m_hi], axis=1)
    row_shift = np.stack([np.floor(shifts.min(axis=1) + 0.5) - 1,
                          np.floor(shifts.max(axis=1) + 0.5) + 1], axis=1).astype(np.int64)
    # the box within which two pixels landing on one spot lie
    reach = [int(np.ceil(np.abs(offsets[:, j]).max() * (m_hi - m_lo))) + 2 for j in (0, 1)]
    box = (2 * reach[0] + 1, 2 * reach[1] + 1)
    gap = np.float32(layer_gap)
    # float32 differences, as the kernel's test takes them (a pixel that is not finite lands nowhere)
    highest = box_extreme(np.where(finite, layers, np.float32(-np.inf)), box, maximum=True)
    lowest = box_extreme(np.where(finite, layers, np.float32(np.inf)), box, maximum=False)
    tested = (highest - layers > gap) | (layers - lowest > gap)
    # the tested pixels as runs along the rows: (x0, x1) in row order, row y's from row_start[y]
    edges = np.diff(np.pad(tested, ((0, 0), (1, 1))).view(np.int8), axis=1)
    ys, starts = np.nonzero(edges == 1)
    ends = np.nonzero(edges == -1)[1]
    row_start = np.zeros(H + 1, np.int64)
    np.cumsum(np.bincount(ys, minlength=H), out=row_start[1:])
    runs = np.stack([starts, ends], axis=1).astype(np.int64)
    if native:
        call("regions", "lfrig_occlusion", layers, H, W, offsets, offsets.shape[0], float(gap), row_shift,
             int(OCCLUSION_BAND_ROWS), row_start, runs, neg, pos, thread_count())
    else:
        _occlusion_kernel(layers, offsets, gap, row_shift, OCCLUSION_BAND_ROWS, row_start, runs, neg, pos)
    return neg, pos


def layer_jumps(layers: np.ndarray, *, layer_gap: float) -> np.ndarray:
    """``(H, W)`` bool: pixels at a jump of the layer map ``M``: where the two pixels either side
    along a row or column differ by more than ``layer_gap`` (``|M(x + 1) - M(x - 1)|``; the pixel
    between and both sides are marked). A slant of less than ``layer_gap / 2`` per pixel never
    counts, and a jump the estimate spread over two pixels still does."""
    m = layers.astype(np.float32)
    out = np.zeros(m.shape, bool)
    jy = np.abs(m[2:] - m[:-2]) > layer_gap
    jx = np.abs(m[:, 2:] - m[:, :-2]) > layer_gap
    for k in range(3):
        out[k:m.shape[0] - 2 + k] |= jy
        out[:, k:m.shape[1] - 2 + k] |= jx
    return out


def jump_distance(jumps: np.ndarray) -> np.ndarray:
    """``(H, W)`` int64 chessboard distance to the nearest ``jumps`` pixel (0 on it; large if none)."""
    from recon.entropy.filters import chessboard_distance

    if not jumps.any():
        return np.full(jumps.shape, 1 << 30, np.int64)
    return chessboard_distance(~jumps).astype(np.int64)


#: Immerkaer's noise operator: the difference of two Laplacians, blind to a linear ramp.
IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)


def noise_sigma(image: np.ndarray) -> float:
    """Standard deviation of additive white noise in a grey image (Immerkaer 1996), same units: the
    mean absolute :data:`IMMERKAER` response inside the image's one-pixel border, in numpy (the
    estimate's first step, which so does not wait for scipy's import: the warm-up loads it beside
    the estimate, :func:`recon.methods.warm_in_background`). The same value bit for bit as
    :func:`noise_sigma_reference`: each product is exact (weights 1, 2 and 4) and the nine are
    summed in scipy's order, the footprint's row by row from 0.0."""
    x = image.astype(np.float64)
    response = np.zeros((max(x.shape[0] - 2, 0), max(x.shape[1] - 2, 0)))
    h, w = response.shape
    for (dy, dx), weight in np.ndenumerate(IMMERKAER):
        response += x[dy:dy + h, dx:dx + w] * weight
    return float(np.sqrt(np.pi / 2) * np.abs(response).mean() / 6.0)


def noise_sigma_reference(image: np.ndarray) -> float:
    """:func:`noise_sigma` through ``scipy.ndimage.convolve`` (its readable twin)."""
    from scipy import ndimage

    response = ndimage.convolve(image.astype(np.float64), IMMERKAER, mode="reflect")[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2) * np.abs(response).mean() / 6.0)


def different_neighbours(image: np.ndarray, *, size: int, tolerance: float) -> np.ndarray:
    """``psi`` of Eq. 12: per pixel, the number of neighbours in the ``size x size`` square (centre
    excluded, image edge repeated) whose value differs by more than ``tolerance``. ``(H, W)`` int."""
    r = size // 2
    padded = np.pad(image, r, mode="edge")
    H, W = image.shape
    psi = np.zeros((H, W), np.int64)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx == 0:
                continue
            shifted = padded[r + dy:r + dy + H, r + dx:r + dx + W]
            psi += np.abs(shifted - image) > tolerance
    return psi


def smooth_tolerance_abs(tolerance: float, sigma: float) -> float:
    """Eq. 12's grey-level tolerance (``[0, 1]`` grey units): ``tolerance`` noise sigmas, at least
    half an 8-bit grey level."""
    return max(tolerance * sigma, 0.5 / 255)


def flat_pixels(centre: np.ndarray, *, size: int, tolerance: float,
                sigma: float | None = None) -> tuple[np.ndarray, dict]:
    """Eq. 12's test alone: ``psi < N / 2`` on the ``(H, W)`` centre view, whatever the occlusion
    labels. ``tolerance`` is in units of the noise sigma (Immerkaer), floored at 0.5/255; ``sigma``
    (grey units of ``centre``), when given, is used instead of estimating it from ``centre`` (a tile
    passes the whole image's, so its pixels are tested alike). Returns ``(mask, info)`` with
    ``psi``, ``noise_sigma`` and ``smooth_tolerance_abs``."""
    centre = centre.astype(np.float32)
    sigma = noise_sigma(centre) if sigma is None else float(sigma)
    tol = smooth_tolerance_abs(tolerance, sigma)
    psi = different_neighbours(centre, size=size, tolerance=tol)
    n = size ** 2 - 1
    return psi < n / 2, {"psi": psi, "noise_sigma": sigma, "smooth_tolerance_abs": tol}


def region_labels(gray: np.ndarray, d0: np.ndarray, *, layer_gap: float, layer_median: int,
                  smooth_neighbourhood: int, smooth_tolerance: float, occlusion_views: str = "all",
                  keep: np.ndarray | None = None, fast: bool = True,
                  noise: float | None = None, flat: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Region map of Eq. 8 for the centre view.

    Parameters
    ----------
    gray
        ``(U, V, H, W)`` float32 light field (only the centre view's grey values are used; the side
        views enter through the initial disparity ``d0``, which was matched on them).
    d0
        ``(H, W)`` initial disparity, pixels per view step.
    layer_gap, layer_median, smooth_neighbourhood, smooth_tolerance
        See the module docstring.
    occlusion_views
        Views whose warped segmentation Eq. 9 compares with the centre: ``"nine"`` (the paper: the
        farthest view in each of the eight directions) or ``"all"`` (every view of the grid; a
        pixel between two close occluders, e.g. background 1 px from a thin bar, can be hidden in
        the middle views only and visible again in the farthest ones).
    keep
        ``(H, W)`` bool: pixels whose ``d0`` enters the layer map unfiltered (:func:`layer_map`).
    noise
        Noise sigma of the centre view (grey units); default: estimated from it (:func:`noise_sigma`).
    flat
        ``(H, W)`` bool: Eq. 12's flat pixels of the centre view when they are known already
        (:func:`flat_pixels` with ``smooth_neighbourhood``, ``smooth_tolerance`` and ``noise``);
        default: tested here.

    Returns
    -------
    ``(labels, info)``: ``(H, W)`` uint8 labels 0..3, and a dict with ``diff_occluded``,
    ``diff_occluding`` (``(H, W)`` float32) and ``layers``, and unless ``flat`` was given
    :func:`flat_pixels`' ``psi``, ``noise_sigma`` and ``smooth_tolerance_abs``.
    """
    U, V = gray.shape[:2]
    u0, v0 = U // 2, V // 2
    if occlusion_views not in ("nine", "all"):
        raise ValueError(f"occlusion_views must be 'nine' or 'all', got {occlusion_views!r}")
    mask = initial_view_mask((U, V)) if occlusion_views == "nine" else np.ones((U, V), bool)
    offsets = [(u - u0, v - v0) for u, v in zip(*np.nonzero(mask)) if (u, v) != (u0, v0)]
    layers = layer_map(d0, median_size=layer_median, keep=keep)
    diffs = occlusion_diffs if fast else occlusion_diffs_reference
    neg, pos = diffs(layers, offsets, layer_gap=layer_gap)
    flat_info = {}
    if flat is None:
        flat, flat_info = flat_pixels(gray[u0, v0], size=smooth_neighbourhood, tolerance=smooth_tolerance,
                                      sigma=noise)
    labels = np.full(d0.shape, TEXTURE, np.uint8)
    labels[flat] = SMOOTH
    occluded = neg < 0
    labels[(pos > 0) & ~occluded] = OCCLUDING
    labels[occluded] = OCCLUDED
    info = {"diff_occluded": neg, "diff_occluding": pos, "layers": layers, **flat_info}
    return labels, info
