"""The report's pictures as ``(H, W, 3)`` uint8 RGB arrays, drawn with OpenCV (matplotlib is not a
dependency): region maps in the paper's colours, a shaded relief of depth, images with a colour bar,
line plots. :mod:`recon.report.page` writes them and lays out the page.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from recon.colour import LUTS, NO_VALUE
from recon.entropy.labels import REGION_COLOURS as _LABEL_COLOURS
from recon.entropy.labels import REGION_NAMES
from recon.lf.lightfield import to_float

#: Region type -> the paper's colour (RGB), from the one table in :mod:`recon.entropy.labels`.
REGION_COLOURS = {name: tuple(int(c) for c in rgb) for name, rgb in zip(REGION_NAMES, _LABEL_COLOURS)}
UNLABELLED = (128, 128, 128)

_SS = 2  # supersampling factor for drawing text and lines
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_INK = (40, 40, 40)
_GRID = (225, 225, 225)
#: Line colours of the profiles (RGB): the estimate blue, the truth black.
ESTIMATE = (31, 119, 180)
TRUTH = (20, 20, 20)


# --------------------------------------------------------------------------------------------------
# colour maps
# --------------------------------------------------------------------------------------------------


def region_picture(labels: np.ndarray, *, names: Sequence[str] = REGION_NAMES) -> np.ndarray:
    """``(H, W)`` integer region labels -> ``(H, W, 3)`` RGB in the paper's colours.

    ``names[k]`` is the region type of label ``k`` (default ``recon.entropy.regions``' numbering:
    0 occluding, 1 occluded, 2 texture, 3 smooth); other labels are grey.
    """
    labels = np.asarray(labels)
    rgb = np.empty(labels.shape + (3,), np.uint8)
    rgb[...] = UNLABELLED
    for label, name in enumerate(names):
        if name in REGION_COLOURS:
            rgb[labels == label] = REGION_COLOURS[name]
    return rgb


def shaded_relief(depth_mm: np.ndarray, *, focal_px: float, smooth_px: float = 1.5,
                  light=(-0.45, -0.55, -1.0)) -> np.ndarray:
    """``(H, W)`` depth in mm -> ``(H, W, 3)`` grey RGB of the surface lit by a distant light.

    The depth is first smoothed with a Gaussian of ``smooth_px`` pixels (missing pixels do not
    count; 0 for none) so that single-pixel noise does not drown the shape; normals come from
    :func:`recon.cloud.grid_normals` (never across depth jumps). ``light`` points from the surface
    towards the light in the camera frame (default: up, left, towards the camera). Brightness is
    ``0.15 + 0.85 * max(n . l, 0)``; pixels without depth are :data:`NO_VALUE`.
    """
    from recon.cloud import depth_to_points, grid_normals, neighbour_links

    depth = np.asarray(depth_mm, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    if smooth_px > 0:
        weights = cv2.GaussianBlur(valid.astype(np.float64), (0, 0), smooth_px)
        summed = cv2.GaussianBlur(np.where(valid, depth, 0.0), (0, 0), smooth_px)
        with np.errstate(invalid="ignore", divide="ignore"):
            depth = np.where(valid, summed / weights, np.nan)
    points = depth_to_points(depth, focal_px=focal_px)
    right, down = neighbour_links(depth)
    normals = grid_normals(points, right, down)
    direction = np.asarray(light, dtype=np.float64)
    direction /= np.linalg.norm(direction)
    with np.errstate(invalid="ignore"):
        brightness = 0.15 + 0.85 * np.clip(normals @ direction, 0.0, 1.0)
    grey = np.round(np.nan_to_num(brightness) * 255).astype(np.uint8)
    rgb = np.repeat(grey[..., None], 3, axis=-1)
    rgb[~np.isfinite(brightness)] = NO_VALUE
    return rgb


# --------------------------------------------------------------------------------------------------
# drawing with OpenCV
# --------------------------------------------------------------------------------------------------


def nice_ticks(low: float, high: float, *, count: int = 5) -> np.ndarray:
    """About ``count`` round tick values (steps of 1, 2 or 5 times a power of ten) within ``[low, high]``."""
    if not (math.isfinite(low) and math.isfinite(high)) or high <= low:
        return np.array([low])
    raw = (high - low) / max(count - 1, 1)
    power = 10.0 ** math.floor(math.log10(raw))
    candidates = sorted(m * power * scale for scale in (0.1, 1.0, 10.0) for m in (1, 2, 2.5, 5))
    # the finest round step that does not give more than count + 1 ticks
    for step in candidates:
        first = math.ceil(low / step - 1e-9) * step
        ticks = np.arange(first, high + step * 1e-9, step)
        if len(ticks) <= count + 1:
            break
    return np.round(ticks / step) * step  # no 0.30000000000000004


def _tick_text(value: float, ticks: np.ndarray) -> str:
    step = float(np.min(np.diff(ticks))) if len(ticks) > 1 else abs(value) or 1.0
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
    if step * 10**decimals % 1 > 1e-6:  # steps like 2.5
        decimals += 1
    text = f"{value:.{decimals}f}"
    return "0" if text.strip("-0.") == "" else text


def _text_size(text: str, scale: float) -> tuple[int, int, int]:
    (width, height), baseline = cv2.getTextSize(text, _FONT, scale * _SS, 1)
    return width, height, baseline


def _put(canvas: np.ndarray, text: str, x: float, y: float, *, scale: float = 0.46,
         colour=_INK, align: str = "left", valign: str = "baseline") -> None:
    """Draw text at supersampled coordinates ``(x, y)``."""
    width, height, _ = _text_size(text, scale)
    if align == "center":
        x -= width / 2
    elif align == "right":
        x -= width
    if valign == "middle":
        y += height / 2
    elif valign == "top":
        y += height
    cv2.putText(canvas, text, (int(round(x)), int(round(y))), _FONT, scale * _SS, colour, 1, cv2.LINE_AA)


def _finish(canvas: np.ndarray) -> np.ndarray:
    height, width = canvas.shape[:2]
    return cv2.resize(canvas, (width // _SS, height // _SS), interpolation=cv2.INTER_AREA)


def display_scale(width: int, *, target: int = 420, limit: int = 760) -> float:
    """How much a figure of ``width`` pixels is scaled for the page."""
    if width < target:
        return float(math.ceil(target / width))
    if width > limit:
        return limit / width
    return 1.0


def _resize(image: np.ndarray, factor: float) -> np.ndarray:
    if factor == 1:
        return image
    height, width = image.shape[:2]
    size = (max(1, round(width * factor)), max(1, round(height * factor)))
    return cv2.resize(image, size, interpolation=cv2.INTER_NEAREST if factor > 1 else cv2.INTER_AREA)


def image_figure(image_rgb: np.ndarray, *, rows: Sequence[int] = (), scale: float | None = None) -> np.ndarray:
    """An RGB picture at display size, with thin marks and labels at the given image rows."""
    height, width = image_rgb.shape[:2]
    factor = display_scale(width) if scale is None else scale
    shown = _resize(image_rgb, factor)
    canvas = _resize(shown, _SS).copy()
    for row in rows:
        y = int(round((row + 0.5) * factor * _SS))
        overlay = canvas.copy()
        cv2.line(overlay, (0, y), (canvas.shape[1] - 1, y), (255, 255, 255), _SS * 3, cv2.LINE_AA)
        canvas = cv2.addWeighted(overlay, 0.45, canvas, 0.55, 0)
        cv2.line(canvas, (0, y), (canvas.shape[1] - 1, y), (255, 40, 200), _SS, cv2.LINE_AA)
        label = f"row {row}"
        w, h, _ = _text_size(label, 0.46)
        top = y - h - 10 * _SS if y - h - 10 * _SS > 0 else y + 4 * _SS
        cv2.rectangle(canvas, (4 * _SS, top), (4 * _SS + w + 8 * _SS, top + h + 6 * _SS), (255, 255, 255), -1)
        _put(canvas, label, 8 * _SS, top + 3 * _SS, valign="top", colour=(150, 0, 110))
    return _finish(canvas)


def colourbar_figure(image_rgb: np.ndarray, *, low: float, high: float, lut: str, label: str,
                     ticks: Sequence[float] | None = None, scale: float | None = None) -> np.ndarray:
    """A colour-mapped picture at display size with a labelled vertical colour bar on its right."""
    height, width = image_rgb.shape[:2]
    factor = display_scale(width) if scale is None else scale
    shown = _resize(_resize(image_rgb, factor), _SS)
    img_h, img_w = shown.shape[:2]
    pad = 14 * _SS
    bar_w = 16 * _SS
    tick_values = np.asarray(nice_ticks(low, high) if ticks is None else ticks, dtype=float)
    tick_values = tick_values[(tick_values >= low - 1e-9) & (tick_values <= high + 1e-9)]
    labels = [_tick_text(v, tick_values if len(tick_values) > 1 else np.array([low, high])) for v in tick_values]
    text_w = max([_text_size(t, 0.46)[0] for t in labels] + [0])
    label_h = _text_size(label, 0.46)[1]
    total_w = img_w + pad + bar_w + 6 * _SS + text_w + 10 * _SS + label_h + 8 * _SS
    total_h = img_h + 2 * 8 * _SS
    canvas = np.full((total_h, total_w, 3), 255, np.uint8)
    top = 8 * _SS
    canvas[top : top + img_h, :img_w] = shown
    bar_x = img_w + pad
    bar_top, bar_bottom = top + 6 * _SS, top + img_h - 6 * _SS
    table = LUTS[lut]()
    ramp = np.linspace(1, 0, bar_bottom - bar_top)  # top of the bar is ``high``
    canvas[bar_top:bar_bottom, bar_x : bar_x + bar_w] = table[np.round(ramp * 255).astype(int)][:, None, :]
    cv2.rectangle(canvas, (bar_x, bar_top), (bar_x + bar_w - 1, bar_bottom - 1), (120, 120, 120), max(1, _SS // 2))
    span = high - low if high > low else 1.0
    for value, text in zip(tick_values, labels):
        y = bar_bottom - (value - low) / span * (bar_bottom - bar_top)
        cv2.line(canvas, (bar_x + bar_w, int(y)), (bar_x + bar_w + 4 * _SS, int(y)), (90, 90, 90), max(1, _SS // 2))
        _put(canvas, text, bar_x + bar_w + 6 * _SS, y, valign="middle")
    # the quantity's name, written upwards along the right edge
    title = np.full((label_h + 8 * _SS, bar_bottom - bar_top, 3), 255, np.uint8)
    _put(title, label, title.shape[1] / 2, title.shape[0] - 4 * _SS, align="center")
    title = cv2.rotate(title, cv2.ROTATE_90_COUNTERCLOCKWISE)
    x0 = total_w - title.shape[1] - 2 * _SS
    canvas[bar_top:bar_bottom, x0 : x0 + title.shape[1]] = np.minimum(canvas[bar_top:bar_bottom, x0 : x0 + title.shape[1]], title)
    return _finish(canvas)


def line_plot(x: np.ndarray, series: Sequence[tuple], *,
              xlabel: str, ylabel: str, size: tuple[int, int] = (560, 240),
              y_range: tuple[float, float] | None = None) -> np.ndarray:
    """A line plot: ``series`` is ``[(legend label, y, RGB colour[, line width px]), ...]`` over ``x``,
    drawn in order (later on top); NaN breaks lines.

    Returns an ``(height, width, 3)`` RGB image of ``size = (width, height)`` pixels.
    """
    width, height = size[0] * _SS, size[1] * _SS
    canvas = np.full((height, width, 3), 255, np.uint8)
    x = np.asarray(x, dtype=float)
    ys = [np.asarray(item[1], dtype=float) for item in series]
    widths = [float(item[3]) if len(item) > 3 else 1.6 for item in series]
    if y_range is None:
        finite = np.concatenate([y[np.isfinite(y)] for y in ys] + [np.zeros(0)])
        if finite.size:
            low, high = np.percentile(finite, [0.5, 99.5])
        else:
            low, high = 0.0, 1.0
        margin = 0.06 * (high - low) if high > low else max(abs(low) * 0.05, 1e-3)
        low, high = low - margin, high + margin
    else:
        low, high = y_range
    x_low, x_high = float(x.min()), float(x.max()) if x.max() > x.min() else float(x.min()) + 1
    x_ticks, y_ticks = nice_ticks(x_low, x_high, count=7), nice_ticks(low, high, count=5)
    label_w = max(_text_size(_tick_text(v, y_ticks), 0.46)[0] for v in y_ticks)
    left, right, top, bottom = label_w + 30 * _SS, 14 * _SS, 26 * _SS, 40 * _SS
    plot_w, plot_h = width - left - right, height - top - bottom

    def px(xv, yv):
        return (left + (xv - x_low) / (x_high - x_low) * plot_w, top + (high - yv) / (high - low) * plot_h)

    for value in y_ticks:
        _, y = px(x_low, value)
        cv2.line(canvas, (left, int(y)), (left + plot_w, int(y)), _GRID, _SS)
        _put(canvas, _tick_text(value, y_ticks), left - 6 * _SS, y, align="right", valign="middle")
    for value in x_ticks:
        xp, _ = px(value, low)
        cv2.line(canvas, (int(xp), top), (int(xp), top + plot_h), _GRID, _SS)
        _put(canvas, _tick_text(value, x_ticks), xp, top + plot_h + 6 * _SS, align="center", valign="top")
    cv2.rectangle(canvas, (left, top), (left + plot_w, top + plot_h), (150, 150, 150), _SS // 2 or 1)
    clip = canvas[top : top + plot_h + 1, left : left + plot_w + 1]
    for item, y, line_width in zip(series, ys, widths):
        colour = item[2]
        ok = np.isfinite(y) & np.isfinite(x)
        runs = np.split(np.arange(len(x)), np.flatnonzero(np.diff(ok.astype(int)) != 0) + 1)
        for run in runs:
            if not ok[run[0]]:
                continue
            xp, yp = px(x[run], np.clip(y[run], low - (high - low), high + (high - low)))
            points = np.stack([xp - left, yp - top], axis=-1)
            points = np.round(points * 16).astype(np.int32).reshape(-1, 1, 2)  # 4 fractional bits
            if len(run) == 1:
                cv2.circle(clip, tuple(points[0, 0] // 16), 2 * _SS, colour, -1, cv2.LINE_AA)
            else:
                cv2.polylines(clip, [points], False, colour, max(1, round(line_width * _SS)), cv2.LINE_AA, shift=4)
    _put(canvas, xlabel, left + plot_w / 2, height - 6 * _SS, align="center")
    ylab = np.full((18 * _SS, plot_h, 3), 255, np.uint8)
    _put(ylab, ylabel, plot_h / 2, 13 * _SS, align="center")
    canvas[top : top + plot_h, 2 * _SS : 2 * _SS + 18 * _SS] = cv2.rotate(ylab, cv2.ROTATE_90_COUNTERCLOCKWISE)
    # legend, top right above the plot
    x_cursor = left + plot_w
    for label, _, colour, *_ in reversed(series):
        w, _, _ = _text_size(label, 0.46)
        x_cursor -= w
        _put(canvas, label, x_cursor, top - 8 * _SS)
        x_cursor -= 26 * _SS
        cv2.line(canvas, (x_cursor, top - 12 * _SS), (x_cursor + 20 * _SS, top - 12 * _SS), colour, 2 * _SS, cv2.LINE_AA)
        x_cursor -= 16 * _SS
    return _finish(canvas)



# --------------------------------------------------------------------------------------------------
# the confidence against the truth
# --------------------------------------------------------------------------------------------------

#: Line colour of the ideal in the confidence plots (RGB).
IDEAL = (150, 150, 150)


def reliability_figure(confidence: np.ndarray, right: np.ndarray, *, bins: int = 10) -> np.ndarray:
    """Reliability diagram: per equal-width confidence bin, the share of pixels that are right
    (``right``: ``|error| <= 0.07`` px) against the bin's mean confidence; a calibrated confidence
    lies on the diagonal. ``confidence``, ``right``: same-shaped arrays. RGB image."""
    from recon.entropy.calibration import reliability

    mean_c, share, n = reliability(confidence, right, bins=bins)
    used = n > 0  # empty bins have no point
    diagonal = np.linspace(0.0, 1.0, 11)
    k = int(used.sum())
    return line_plot(np.concatenate([diagonal, mean_c[used]]),
                     [("calibrated", np.concatenate([diagonal, np.full(k, np.nan)]), IDEAL, 1.0),
                      ("observed", np.concatenate([np.full(11, np.nan), share[used]]), ESTIMATE, 2.0)],
                     xlabel="confidence (mean of the bin)", ylabel="share right", y_range=(0.0, 1.0))


def sparsification_figure(confidence: np.ndarray, error: np.ndarray, *, steps: int = 20) -> np.ndarray:
    """Sparsification curve: BadPix 0.07 (%) of the pixels left when the least confident share is
    removed, against that share; and the ideal (removing the largest errors first). RGB image."""
    from recon.entropy.calibration import sparsification

    error = np.abs(np.asarray(error, np.float64))
    fractions, by_confidence = sparsification(confidence, error, steps=steps)
    _, ideal = sparsification(-np.nan_to_num(error, nan=np.inf), error, steps=steps)
    return line_plot(fractions, [("ideal (by the true error)", ideal, IDEAL, 1.0),
                                 ("by confidence", by_confidence, ESTIMATE, 2.0)],
                     xlabel="share of pixels removed (least confident first)", ylabel="BadPix 0.07 %")




# --------------------------------------------------------------------------------------------------
# the page
# --------------------------------------------------------------------------------------------------


def as_rgb8(image: np.ndarray) -> np.ndarray:
    """Any ``(H, W)`` or ``(H, W, 3)`` image as ``uint8`` RGB (grey repeated)."""
    image = np.asarray(image)
    rgb = np.clip(to_float(image) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.repeat(rgb[..., None], 3, axis=-1) if rgb.ndim == 2 else rgb
