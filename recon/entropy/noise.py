"""Noise-limited matching: the views low-pass filtered where they carry no texture above the noise.

Where a view is flat in the sense of Eq. 12 (fewer than half of the 5x5 neighbours differ from the
pixel by more than ``smooth_tolerance`` noise sigmas), whatever texture it has is weaker than the
camera noise, and the matching cost there is dominated by the noise, in two ways that have nothing to
do with disparity:

- its level: the mean absolute difference of two noisy samples is ``~1.13 sigma`` whatever the
  candidate, so the faint texture's contribution (a fraction of a grey level) is buried, and
- its *shape*: a view sampled at a sub-pixel position is a bilinear mix of four pixels, which averages
  their noise, the more so the closer the position is to a half pixel (the noise variance of the
  sample is ``((1 - fy)^2 + fy^2) ((1 - fx)^2 + fx^2)``, 1 at whole pixels, 1/4 at half pixels). The
  cost of a flat window is therefore lowest at the candidates whose shifts in most views fall near
  half pixels: on a plain wall the arg-min follows this pattern, not the wall (blender-dev
  weaktexture-v1: every estimate of the wall off by about 0.17 px/view, the cost curve with bumps at
  every whole and half pixel of the outer views' shifts).

The estimator calls a pixel *noise-limited* when it is flat and the initial nine-view search found
no valley in its cost (a black hole of ``d0``): on a clean render (backgammon) flat pixels with a
faint but real texture still match with small windows, and are left alone. A Gaussian filter of
``sigma_px`` (1.5 px) on the views where the noise-limited pixels land (and the view is flat)
removes both effects: the noise
falls by the filter's gain ``1 / (2 sqrt(pi) sigma_px)`` (0.19), and the noise that remains is
correlated over a few pixels, so a bilinear sample averages it hardly more at half pixels than at
whole pixels. Textured pixels keep their unfiltered values (the filter would blur away the texture
the matching uses there). The flat mask of each view is blended with a 1-px Gaussian so that the
filtered and unfiltered parts join without a seam.
"""

from __future__ import annotations

import cv2
import numpy as np

from recon.entropy.regions import flat_pixels


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


def filter_reach_px(sigma_px: float, *, size: int) -> int:
    """How far (pixels) a filtered value depends on the unfiltered view: the flat test's
    neighbourhood, the mask's blur and the filter itself (0 when off)."""
    if sigma_px <= 0:
        return 0
    return int(np.ceil(TRUNCATE * sigma_px)) + int(np.ceil(TRUNCATE * MASK_SIGMA_PX)) + size // 2 + 1


def warp_mask_to_views(mask: np.ndarray, disparity: np.ndarray, grid_shape: tuple[int, int]) -> np.ndarray:
    """``(U, V, H, W)`` bool: where the centre-view pixels of ``mask`` land in each view with
    ``disparity`` (``docs/conventions.md``: ``p - (u - u0, v - v0) d``, rounded), grown by one pixel
    to close the gaps of the forward warp."""
    U, V = grid_shape
    H, W = mask.shape
    ys, xs = np.nonzero(mask)
    d = np.asarray(disparity, np.float64)[ys, xs]
    out = np.zeros((U, V, H, W), bool)
    for u in range(U):
        for v in range(V):
            ly = np.floor(ys - (u - U // 2) * d + 0.5).astype(np.int64)
            lx = np.floor(xs - (v - V // 2) * d + 0.5).astype(np.int64)
            ok = (ly >= 0) & (ly < H) & (lx >= 0) & (lx < W)
            out[u, v, ly[ok], lx[ok]] = True
            out[u, v] = cv2.dilate(out[u, v].view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    return out


def _gaussian(image: np.ndarray, sigma_px: float) -> np.ndarray:
    # Edge pixels repeated (scipy's "nearest"), the kernel cut at TRUNCATE sigmas.
    radius = int(np.ceil(TRUNCATE * sigma_px))
    return cv2.GaussianBlur(image, (2 * radius + 1, 2 * radius + 1), sigma_px, borderType=cv2.BORDER_REPLICATE)


def filter_flat_views(gray: np.ndarray, *, sigma_px: float, noise_sigma: float, size: int,
                      tolerance: float, where: np.ndarray | None = None) -> np.ndarray:
    """``(U, V, H, W)`` float32 views with their Eq. 12-flat parts Gaussian filtered.

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
    """
    if sigma_px <= 0:
        return gray
    out = np.empty_like(gray, dtype=np.float32)
    U, V = gray.shape[:2]
    for u in range(U):
        for v in range(V):
            view = np.ascontiguousarray(gray[u, v], dtype=np.float32)
            if where is not None and not where[u, v].any():
                out[u, v] = view
                continue
            flat, _ = flat_pixels(view, size=size, tolerance=tolerance, sigma=noise_sigma)
            if where is not None:
                flat &= where[u, v]
            if not flat.any():
                out[u, v] = view
                continue
            weight = _gaussian(flat.astype(np.float32), MASK_SIGMA_PX)
            smooth = _gaussian(view, sigma_px)
            out[u, v] = view + weight * (smooth - view)
    return out
