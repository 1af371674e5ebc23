"""The aperture test of the strip windows (lfrig's, not the paper's; ``docs/entropy-method.md``,
"Confidence and thin textureless structures").

A strip window (shapes 9 and 10, :mod:`recon.entropy.windows`) is one pixel thick and is matched
over the views in line with it only: the horizontal strip over the views of the centre row (parallax
along x), the vertical strip over the centre column (parallax along y). Its cost can then tell
disparities apart only through the grey values' variation **along** the strip. Where the scene does
not vary along it (a vertical strip on a vertical pole, edge or stripe), every disparity matches:
the cost curve is the noise, its least value lies anywhere, and being lower than any informative
window's least cost, it wins the joint search (Eq. 7) with a wrong disparity. This is the aperture
problem of one-dimensional matching.

:func:`informative_strips` tells, per pixel and strip size, whether the centre view varies along the
strip by more than noise: the mean absolute difference of neighbouring pixels along the strip must
exceed ``factor`` times what noise alone gives it (``2 sigma / sqrt(pi)`` for white noise of
standard deviation ``sigma``). Elsewhere the strip is not offered. The variation is measured over
``length`` pixels (at least the strip's own size): a strip is fooled by a structure that stays the
same along it over the parallax shifts of the search, longer than the window, and a long test
decides far more surely than a 3- or 5-pixel one (pure noise passes a factor of 1.5 at about 13 % of
5-pixel strips, hardly ever over 31 pixels), so the factor can be low enough to keep the strips on
faint textures, which the matching, summing over the strip and its views, still resolves.
"""

from __future__ import annotations

import numpy as np

#: Mean absolute difference of two independent samples of white noise, in units of its sigma.
NOISE_ABS_DIFF = 2.0 / np.sqrt(np.pi)


def along_strip_variation(centre: np.ndarray, *, size: int, axis: int) -> np.ndarray:
    """``(H, W)`` mean absolute difference of neighbouring pixels of ``centre`` along ``axis``
    (1: the horizontal strip of ``size`` pixels centred on each pixel; 0: the vertical one), in the
    units of ``centre``. The strip is cut at the image edge like the matching windows."""
    if size < 3 or size % 2 == 0:
        raise ValueError(f"strip size must be odd and at least 3, got {size}")
    image = np.asarray(centre, np.float64)
    if axis == 0:
        return along_strip_variation(image.T, size=size, axis=1).T
    H, W = image.shape
    r = (size - 1) // 2
    diff = np.abs(np.diff(image, axis=1))  # (H, W - 1): diff[:, j] between columns j and j + 1
    table = np.zeros((H, W), np.float64)
    np.cumsum(diff, axis=1, out=table[:, 1:])
    x = np.arange(W)
    a = np.clip(x - r, 0, W - 1)  # first and last column of the strip inside the image
    b = np.clip(x + r, 0, W - 1)
    count = np.maximum(b - a, 1)
    return (table[:, b] - table[:, a]) / count


def informative_strips(centre: np.ndarray, *, sizes: tuple[int, ...], noise_sigma: float,
                       factor: float, floor: float = 0.0, length: int = 0) -> np.ndarray:
    """``(H, W, 2, len(sizes))`` bool: ``[..., 0, j]`` the horizontal and ``[..., 1, j]`` the
    vertical strip of ``sizes[j]`` pixels can measure disparity at the pixel (see the module
    docstring): the variation along it, measured over ``max(sizes[j], length)`` pixels, exceeds
    ``max(factor * 2 sigma / sqrt(pi), floor)``. ``noise_sigma`` and ``floor`` are in the units of
    ``centre``; ``factor`` 0 offers every strip."""
    if factor < 0 or not np.isfinite(factor):
        raise ValueError(f"factor must be a finite number >= 0, got {factor}")
    centre = np.asarray(centre, np.float64)
    H, W = centre.shape
    out = np.ones((H, W, 2, len(sizes)), bool)
    if factor == 0:
        return out
    threshold = max(factor * NOISE_ABS_DIFF * max(float(noise_sigma), 0.0), float(floor))
    measured: dict[tuple[int, int], np.ndarray] = {}
    for j, size in enumerate(sizes):
        span = max(int(size), int(length) | 1)
        if span < 3:
            continue  # a 1-pixel strip is the pixel itself: nothing to vary
        for k, axis in enumerate((1, 0)):
            if (span, axis) not in measured:
                measured[span, axis] = along_strip_variation(centre, size=span, axis=axis) > threshold
            out[..., k, j] = measured[span, axis]
    return out
