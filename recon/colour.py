"""Colour-mapped pictures of disparity maps."""

from __future__ import annotations

import cv2
import numpy as np


def colourise(values: np.ndarray, *, value_range: tuple[float, float] | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    """Map ``(H, W)`` values to an RGB ``uint8`` image (OpenCV's TURBO map; non-finite pixels black).

    Returns the image and the ``(low, high)`` that were mapped to the ends of the colour map: the
    given ``value_range``, or the 1st and 99th percentiles of the finite values.
    """
    finite = np.isfinite(values)
    if value_range is None:
        if finite.any():
            low, high = (float(x) for x in np.percentile(values[finite], [1, 99]))
        else:
            low, high = 0.0, 1.0
    else:
        low, high = value_range
    if not high > low:
        high = low + 1e-6
    scaled = np.clip((np.where(finite, values, low) - low) / (high - low), 0, 1)
    rgb = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[:, :, ::-1].copy()
    rgb[~finite] = 0
    return rgb, (low, high)
