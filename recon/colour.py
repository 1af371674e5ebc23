"""Colour maps for pictures of disparity, depth, errors and window sizes."""

from __future__ import annotations

import cv2
import numpy as np

NO_VALUE = (60, 60, 60)  # pixels without a value in colour-mapped figures


def _opencv_lut(code: int) -> np.ndarray:
    ramp = np.arange(256, dtype=np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(ramp, code)[:, 0, ::-1].copy()  # (256, 3) RGB


def _diverging_lut() -> np.ndarray:
    # blue - near white - red (the ends of ColorBrewer's RdBu)
    stops = np.array([(33, 102, 172), (146, 197, 222), (247, 247, 247), (244, 165, 130), (178, 24, 43)], float)
    positions = np.linspace(0, 1, len(stops))
    t = np.linspace(0, 1, 256)
    return np.stack([np.interp(t, positions, stops[:, k]) for k in range(3)], axis=-1).round().astype(np.uint8)


LUTS = {
    "turbo": lambda: _opencv_lut(cv2.COLORMAP_TURBO),
    "turbo_r": lambda: _opencv_lut(cv2.COLORMAP_TURBO)[::-1].copy(),
    "viridis": lambda: _opencv_lut(cv2.COLORMAP_VIRIDIS),
    "diverging": _diverging_lut,
}


def colour_map(values: np.ndarray, *, low: float, high: float, lut: str = "turbo",
               no_value: tuple[int, int, int] = NO_VALUE) -> np.ndarray:
    """``(H, W)`` values -> ``(H, W, 3)`` RGB ``uint8`` through a 256-entry colour map.

    ``low`` maps to the first colour, ``high`` to the last; values outside are clipped. Non-finite
    pixels get ``no_value`` (default :data:`NO_VALUE`).
    """
    table = LUTS[lut]()
    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    span = high - low if high > low else 1.0
    index = np.clip((np.where(finite, values, low) - low) / span, 0.0, 1.0)
    rgb = table[np.round(index * 255).astype(np.int64)]
    rgb[~finite] = no_value
    return rgb


def robust_range(values: np.ndarray, given: tuple[float, float] | None = None) -> tuple[float, float]:
    """``given``, or the 1st and 99th percentiles of the finite values (widened when they coincide)."""
    if given is not None:
        return float(given[0]), float(given[1])
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    low, high = (float(v) for v in np.percentile(finite, [1, 99]))
    return (low, high) if high > low else (low - 0.5, high + 0.5)


def colourise(values: np.ndarray, *, value_range: tuple[float, float] | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    """Map ``(H, W)`` values to an RGB ``uint8`` image (TURBO; non-finite pixels black).

    Returns the image and the ``(low, high)`` mapped to the ends of the colour map: the given
    ``value_range``, or the 1st and 99th percentiles of the finite values (:func:`robust_range`).
    """
    low, high = robust_range(values, value_range)
    return colour_map(values, low=low, high=high, lut="turbo", no_value=(0, 0, 0)), (low, high)
