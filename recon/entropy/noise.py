"""Noise-limited matching: the views low-pass filtered where they carry no texture above the noise.

Where a view's texture is weaker than the camera noise, the matching cost there is dominated by
the noise, in two ways that have nothing to do with disparity:

- its level: the mean absolute difference of two noisy samples is ``~1.13 sigma`` whatever the
  candidate, so the faint texture's contribution (a fraction of a grey level) is buried, and
- its *shape*: a view sampled at a sub-pixel position is a bilinear mix of four pixels, which averages
  their noise, the more so the closer the position is to a half pixel (the noise variance of the
  sample is ``((1 - fy)^2 + fy^2) ((1 - fx)^2 + fx^2)``, 1 at whole pixels, 1/4 at half pixels). The
  cost of a flat window is therefore lowest at the candidates whose shifts in most views fall near
  half pixels: on a plain wall the arg-min follows this pattern, not the wall (blender-dev
  weaktexture-v1: every estimate of the wall off by about 0.17 px/view, the cost curve with bumps at
  every whole and half pixel of the outer views' shifts).

The estimator calls a pixel *noise-limited* (``noise_gate="texture"``, the default) when it lies in a
window of the largest size in which nothing but noise varies: the filtered gradient energy around
every pixel of that window is below a few times what the noise alone gives
(:func:`texture_to_noise`, :func:`noise_limited_windows`). Eq. 12's 5x5 count is not used for this:
on a wall under noise it flips from pixel to pixel, and it calls the inside of a brick, a specular
patch or a thin textureless pole flat although their windows reach texture that matches well
unfiltered (the first version, ``noise_gate="holes"``: Eq. 12-flat and no valley in the initial
nine-view cost, caught those too). A Gaussian filter of ``sigma_px`` (1.5 px) on the views where
the noise-limited pixels land (and the view is noise-limited by the same test) removes both
effects: the noise falls by the filter's gain ``1 / (2 sqrt(pi) sigma_px)`` (0.19), and the noise
that remains is correlated over a few pixels, so a bilinear sample averages it hardly more at half
pixels than at whole pixels. Textured pixels keep their unfiltered values (the filter would blur
away the texture the matching uses there). The mask of each view is blended with a 1-px Gaussian so that the
filtered and unfiltered parts join without a seam.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import cv2
import numpy as np

from recon.entropy.regions import flat_pixels
from recon.native import call, chosen, thread_count


def filter_gain(sigma_px: float) -> float:
    """Factor by which a Gaussian filter of ``sigma_px`` scales the standard deviation of white noise
    (``1 / (2 sqrt(pi) sigma_px)``, at most 1)."""
    if sigma_px <= 0:
        return 1.0
    return float(min(1.0, 1.0 / (2.0 * np.sqrt(np.pi) * sigma_px)))


#: Gaussian filters reach ``ceil(TRUNCATE * sigma)`` pixels (scipy's default truncation).
TRUNCATE = 4.0
#: Sigma (px) of the blur that softens each view's flat mask.
MASK_SIGMA_PX = 1.0


def filter_reach_px(sigma_px: float, *, size: int, radius_px: int | None = None) -> int:
    """How far (pixels) a filtered value depends on the unfiltered view: the filter itself, and the
    mask's blur of the flat test (Eq. 12's ``size``, or with ``radius_px`` the reach of
    :func:`texture_to_noise`); 0 when off."""
    if sigma_px <= 0:
        return 0
    test = size // 2 + 1 if radius_px is None else texture_reach_px(sigma_px, radius_px=radius_px)
    return max(int(np.ceil(TRUNCATE * sigma_px)), int(np.ceil(TRUNCATE * MASK_SIGMA_PX)) + test)


def soften_reach_px(sigma_px: float) -> int:
    """How far (pixels) a value of :func:`soften_views` depends on the view and on ``where``: the
    filter and the soft mask; 0 when off."""
    if sigma_px <= 0:
        return 0
    return max(int(np.ceil(TRUNCATE * sigma_px)), int(np.ceil(TRUNCATE * MASK_SIGMA_PX)))


class Landings(NamedTuple):
    """A centre-view mask's pixels ``(ys, xs)`` and their disparity ``d`` (float64), to be warped into
    the views of a ``(U, V)`` grid (:func:`warp_landings`): those that can land within a row of the
    image rows ``[top, bottom)``, which the one-pixel growth reads as the rows ``[a, b)``."""
    ys: np.ndarray
    xs: np.ndarray
    d: np.ndarray
    grid_shape: tuple[int, int]
    a: int
    b: int
    top: int
    bottom: int
    W: int


def mask_landings(mask: np.ndarray, disparity: np.ndarray, grid_shape: tuple[int, int], *,
                  rows: range | None = None, image_rows: range | None = None,
                  max_disparity: float | None = None) -> Landings:
    """The pixels of ``mask`` that :func:`warp_mask_to_views` warps (its parameters), found once
    for as many of the grid rows ``rows`` as :func:`warp_landings` is asked for."""
    U, V = grid_shape
    rows = range(U) if rows is None else rows
    H, W = mask.shape
    top, bottom = (0, H) if image_rows is None else (image_rows.start, image_rows.stop)
    a, b = max(top - 1, 0), min(bottom + 1, H)  # the rows the one-pixel growth reads
    lo, hi = 0, H  # the centre rows whose pixels can land there
    if (a, b) != (0, H):
        largest = float(np.nanmax(np.abs(disparity))) if max_disparity is None else max_disparity
        reach = np.ceil(max(abs(u - U // 2) for u in rows) * largest) + 1
        lo, hi = int(max(a - reach, 0)), int(min(b + reach, H))
    ys, xs = (np.ascontiguousarray(c) for c in np.nonzero(mask[lo:hi]))  # numpy's are strided views
    ys += lo
    d = np.asarray(disparity, np.float64)[ys, xs]
    return Landings(ys, xs, d, (U, V), a, b, top, bottom, W)


def warp_landings(landings: Landings, views: list[tuple[int, int]], *, kernel: str = "auto",
                  threads: int | None = None) -> np.ndarray:
    """``(len(views), bottom - top, W)`` bool: where the pixels of ``landings`` land in each view
    ``(u, v)`` of the grid, grown by one pixel (:func:`warp_mask_to_views`). Compiled: the C twin,
    ``recon/native/views.c``, where it loads (``threads``: default :func:`recon.native.thread_count`),
    else numpy and OpenCV's dilation (``kernel``: :func:`recon.native.chosen`, ``"numba"`` the
    latter)."""
    ys, xs, d, (U, V), a, b, top, bottom, W = landings
    out = np.empty((len(views), bottom - top, W), bool)
    if chosen("views", kernel):
        du = np.array([u - U // 2 for u, _ in views], np.int64)
        dv = np.array([v - V // 2 for _, v in views], np.int64)
        call("views", "lfrig_warp_mask", ys, xs, d, ys.size, du, dv, len(views), a, b, top, bottom, W,
             out.view(np.uint8), thread_count() if threads is None else threads)
        return out
    landed = np.empty((b - a, W), bool)
    for i, (u, v) in enumerate(views):
        ly = np.floor(ys - (u - U // 2) * d + 0.5).astype(np.int64)
        lx = np.floor(xs - (v - V // 2) * d + 0.5).astype(np.int64)
        ok = (ly >= a) & (ly < b) & (lx >= 0) & (lx < W)
        landed[...] = False
        landed[ly[ok] - a, lx[ok]] = True
        grown = cv2.dilate(landed.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
        out[i] = grown[top - a:bottom - a]
    return out


def warp_mask_to_views(mask: np.ndarray, disparity: np.ndarray, grid_shape: tuple[int, int], *,
                       rows: range | None = None, image_rows: range | None = None,
                       max_disparity: float | None = None, kernel: str = "auto") -> np.ndarray:
    """``(len(rows), V, len(image_rows), W)`` bool: where the centre-view pixels of ``mask`` land in
    the views of the rows ``rows`` of the ``(U, V)`` grid (default all ``U``) with ``disparity``
    (``docs/conventions.md``: ``p - (u - u0, v - v0) d``, rounded), grown by one pixel to close the
    gaps of the forward warp; the image rows ``image_rows`` of each view (default all ``H``: the
    same bits as those rows of the whole view's mask), from the mask's pixels that can land within
    a row of them. ``max_disparity``: ``nanmax |disparity|``, for a caller that warps several
    masks or grid rows with one disparity map (made from the map otherwise: a pass over it).
    ``kernel``: :func:`warp_landings`'."""
    U, V = grid_shape
    rows = range(U) if rows is None else rows
    landings = mask_landings(mask, disparity, grid_shape, rows=rows, image_rows=image_rows,
                             max_disparity=max_disparity)
    out = warp_landings(landings, [(u, v) for u in rows for v in range(V)], kernel=kernel)
    return out.reshape(len(rows), V, *out.shape[1:])


def _gaussian(image: np.ndarray, sigma_px: float) -> np.ndarray:
    # Edge pixels repeated (scipy's "nearest"), the kernel cut at TRUNCATE sigmas.
    radius = int(np.ceil(TRUNCATE * sigma_px))
    return cv2.GaussianBlur(image, (2 * radius + 1, 2 * radius + 1), sigma_px, borderType=cv2.BORDER_REPLICATE)


def filter_flat_views(gray: np.ndarray, *, sigma_px: float, noise_sigma: float, size: int,
                      tolerance: float, where: np.ndarray | None = None,
                      texture_ratio: float | None = None, radius_px: int = 7) -> np.ndarray:
    """``(U, V, H, W)`` float32 views with their flat parts Gaussian filtered: Eq. 12-flat, or with
    ``texture_ratio``, noise-limited at the window scale (:func:`texture_to_noise` below it).

    Parameters
    ----------
    gray
        ``(U, V, H, W)`` float32 grey views in ``[0, 1]``.
    sigma_px
        Gaussian sigma in pixels (``<= 0``: ``gray`` is returned unchanged).
    noise_sigma
        Noise sigma of the views in grey units of ``gray`` (the centre view's, for every view).
    size, tolerance
        Eq. 12's neighbourhood side and tolerance in noise sigmas (:func:`regions.flat_pixels`).
    where
        ``(U, V, H, W)`` bool, optional: filter only there (and where the view is flat), e.g. where
        the noise-limited pixels of the centre view land (:func:`warp_mask_to_views`).
    texture_ratio, radius_px
        When given, a view is flat where :func:`texture_to_noise` (filter ``sigma_px``, window
        radius ``radius_px``) is below ``texture_ratio`` (``size`` and ``tolerance`` unused); else
        where Eq. 12 calls it flat.
    """
    if sigma_px <= 0:
        return gray
    out = np.empty_like(gray, dtype=np.float32)
    U, V = gray.shape[:2]
    for u in range(U):
        for v in range(V):
            out[u, v] = filter_flat_view(gray[u, v], sigma_px=sigma_px, noise_sigma=noise_sigma, size=size,
                                         tolerance=tolerance, where=None if where is None else where[u, v],
                                         texture_ratio=texture_ratio, radius_px=radius_px)
    return out


def filter_flat_view(view: np.ndarray, *, sigma_px: float, noise_sigma: float, size: int, tolerance: float,
                     where: np.ndarray | None = None, texture_ratio: float | None = None,
                     radius_px: int = 7) -> np.ndarray:
    """``(H, W)`` float32: one view of :func:`filter_flat_views` (its parameters, ``where`` the
    view's ``(H, W)``; ``sigma_px > 0``); the view itself where nothing is filtered."""
    view = np.ascontiguousarray(view, dtype=np.float32)
    if where is not None and not where.any():
        return view
    if texture_ratio is None:
        flat, _ = flat_pixels(view, size=size, tolerance=tolerance, sigma=noise_sigma)
    else:
        flat = texture_to_noise(view, noise_sigma=noise_sigma, sigma_px=sigma_px,
                                radius_px=radius_px) < texture_ratio
    if where is not None:
        flat &= where
    if not flat.any():
        return view
    return _blend_filtered(view, flat, sigma_px)


def _blend_filtered(view: np.ndarray, mask: np.ndarray, sigma_px: float, *, out: np.ndarray | None = None,
                    rows: slice = slice(None), kernel: str = "auto") -> np.ndarray:
    # The view Gaussian filtered where mask is set, joined to the rest through a soft mask: the
    # rows ``rows`` of it, into ``out`` when given (C-contiguous float32, those rows' shape; it may
    # be ``view`` itself when ``rows`` are all). The join in C (recon/native/views.c) where it
    # loads, in one pass straight into ``out``; else OpenCV's, the twin.
    weight = _gaussian(mask.view(np.uint8).astype(np.float32), MASK_SIGMA_PX)
    filtered = _gaussian(view, sigma_px)
    if chosen("views", kernel):
        parts = [np.ascontiguousarray(p[rows]) for p in (view, weight, filtered)]
        if out is None:
            out = np.empty_like(parts[0])
        call("views", "lfrig_blend", *parts, parts[0].size, out)
        return out
    joined = cv2.add(view, cv2.multiply(weight, cv2.subtract(filtered, view)))[rows]
    if out is None:
        return joined
    out[...] = joined
    return out


def soften_views(gray: np.ndarray, *, sigma_px: float, where: np.ndarray,
                 out: np.ndarray | None = None, rows: slice = slice(None)) -> np.ndarray:
    """``(U, V, H, W)`` float32 views Gaussian filtered with ``sigma_px`` where ``where``
    (``(U, V, H, W)`` bool, e.g. :func:`warp_mask_to_views` of the weak-texture pixels), blended in
    with a 1-px soft mask; views without a pixel of ``where`` are passed through.

    The filter for textured but noisy surfaces (:func:`weak_texture_pixels`): a mild one (0.6 px
    by default) whose job is not to lower the noise but to correlate it over neighbouring pixels, so
    that a bilinear sample between pixels averages it little more than a sample at a pixel.
    ``out``: a float32 array of the same shape to write to (may be ``gray`` itself, to save a copy of
    the light field); default a new one. ``rows``: the image rows of the result to keep (``out``
    then holds only those, ``(U, V, len(rows), W)``; each view is filtered whole): a band's core
    rows written straight to their place, without a copy of the halo'd band."""
    if sigma_px <= 0:
        return gray
    U, V, H = gray.shape[:3]
    kept = range(H)[rows]
    if out is None:
        out = np.empty((U, V, len(kept)) + gray.shape[3:], dtype=np.float32)
    if out is gray and len(kept) != H:
        raise ValueError("soften_views writes a subset of the rows only into another array")

    def one(k: int) -> None:  # OpenCV releases the GIL: the views run on every core
        u, v = divmod(k, V)
        soften_view(gray[u, v], sigma_px=sigma_px, where=where[u, v], out=out[u, v], rows=rows)

    with ThreadPoolExecutor(max_workers=max(1, min(U * V, cv2.getNumThreads()))) as pool:
        list(pool.map(one, range(U * V)))
    return out


def soften_view(view: np.ndarray, *, sigma_px: float, where: np.ndarray, out: np.ndarray,
                rows: slice = slice(None)) -> None:
    """One view of :func:`soften_views` (``sigma_px > 0``) written into ``out``: the rows ``rows``
    of the ``(H, W)`` view filtered where ``where`` ``(H, W)``, or of the view itself when
    ``where`` is empty (``out`` may be ``view``)."""
    view = np.ascontiguousarray(view, dtype=np.float32)
    if where.any():
        if out.flags.c_contiguous and out.dtype == np.float32:
            _blend_filtered(view, where, sigma_px, out=out, rows=rows)
        else:
            out[...] = _blend_filtered(view, where, sigma_px, rows=rows)
    elif not np.may_share_memory(out, view):
        out[...] = view[rows]


def weak_texture_pixels(ratio: np.ndarray, *, texture_ratio: float) -> np.ndarray:
    """``(H, W)`` bool: pixels whose window-scale texture (:func:`texture_to_noise`, ``ratio``) is
    below ``texture_ratio`` times the noise's: textured enough to match unfiltered on average, but
    weak enough that the noise's sub-pixel pattern (see the module's text) still moves the cost
    minimum. No opening: the mild filter keeps the texture, so mixing filtered and unfiltered
    values in one window costs little."""
    return np.asarray(ratio) < texture_ratio


def _gradient_kernels(sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    # The Gaussian of sigma_px (cut at TRUNCATE sigmas) followed by the central difference
    # (f[x+1] - f[x-1]) / 2, as 1-D kernels: derivative along the axis, smoothing across it.
    radius = int(np.ceil(TRUNCATE * sigma_px))
    g = cv2.getGaussianKernel(2 * radius + 1, sigma_px).ravel()
    dg = np.convolve(g, [0.5, 0.0, -0.5])
    return dg, np.pad(g, 1)


def gradient_noise_energy(sigma_px: float) -> float:
    """Expected squared gradient magnitude (``gx^2 + gy^2``, central differences) of white noise of
    unit sigma after a Gaussian filter of ``sigma_px``: the sum of the squared weights of the two
    derivative kernels."""
    dg, g = _gradient_kernels(sigma_px)
    return float(2.0 * np.sum(dg ** 2) * np.sum(g ** 2))


def texture_to_noise(image: np.ndarray, *, noise_sigma: float, sigma_px: float,
                     radius_px: int) -> np.ndarray:
    """``(H, W)`` float32: the squared gradient magnitude of ``image`` after a Gaussian filter of
    ``sigma_px``, averaged over the ``(2 radius_px + 1)^2`` square around each pixel, in units of
    the same quantity for white noise of ``noise_sigma`` (:func:`gradient_noise_energy`).

    About 1 where the window holds nothing but noise (a plain wall under render noise, whatever its
    texture below the noise), ``1 + (texture / noise)^2`` in the filter's band where it holds faint
    texture, and tens to thousands where it holds an edge, a mortar line, a reflection or the
    border of a thin structure. A window-scale measure: unlike Eq. 12's 5x5 count it does not flip
    from pixel to pixel on a noisy wall, and a flat pixel next to texture (the inside of a brick,
    a textureless pole before a textured background) is not noise-limited at the window scale.
    ``noise_sigma`` and ``image`` in the same grey units; ``sigma_px > 0``.
    """
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0 pixels, got {sigma_px}")
    dg, g = _gradient_kernels(sigma_px)
    img = np.ascontiguousarray(image, dtype=np.float32)
    gx = cv2.sepFilter2D(img, cv2.CV_32F, dg[::-1].copy(), g, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.sepFilter2D(img, cv2.CV_32F, g, dg[::-1].copy(), borderType=cv2.BORDER_REPLICATE)
    side = 2 * int(radius_px) + 1
    energy = cv2.boxFilter(gx * gx + gy * gy, cv2.CV_32F, (side, side), normalize=True,
                           borderType=cv2.BORDER_REPLICATE)
    noise = max(float(noise_sigma), 1e-12) ** 2 * gradient_noise_energy(sigma_px)
    return (energy / np.float32(noise)).astype(np.float32)


def texture_reach_px(sigma_px: float, *, radius_px: int) -> int:
    """How far (pixels) :func:`texture_to_noise` at a pixel depends on the image."""
    return int(np.ceil(TRUNCATE * sigma_px)) + 1 + int(radius_px)  # filter + central difference + box


def noise_limited_windows(mask: np.ndarray, *, radius_px: int) -> np.ndarray:
    """``(H, W)`` bool: the pixels of ``mask`` that lie in a ``(2 radius_px + 1)^2`` square wholly
    inside ``mask`` (a morphological opening; outside the image, the edge pixels repeated).

    A patch of noise-limited texture smaller than the largest window (a weak spot on a textured
    slant) is left out: its pixels' windows, and their neighbours' windows, reach texture that
    matches well unfiltered, and filtering the views there only mixes filtered and unfiltered
    values in those windows (blender-dev slanted-v1: 0.2 points of BadPix lost without it)."""
    side = 2 * int(radius_px) + 1
    kernel = np.ones((side, side), np.uint8)
    return cv2.morphologyEx(np.asarray(mask, bool).view(np.uint8), cv2.MORPH_OPEN, kernel,
                            borderType=cv2.BORDER_REPLICATE).view(bool)

