"""One HTML page per reconstruction, with PNG figures, that shows at a glance how good it is.

:func:`write_report` takes arrays (what the simulated session and ``lfrig reconstruct`` have in
memory); :func:`report_for_result` reads them from a reconstruction folder (``lfrig export
--report``). The page ``index.html`` and its figures are written into one folder that can be
copied or zipped as a whole; the page refers to the figures by relative name and needs no network.

Figures (all PNG, drawn with OpenCV; matplotlib is not a dependency):

- ``centre_view.png``: the centre view, with the rows of the profiles marked;
- ``disparity.png``: disparity with a colour bar (turbo, near = red);
- ``depth.png``: depth in mm with a colour bar (when the camera is known);
- ``shaded.png``: the depth map as a lit surface, so bumps and false steps are easy to see;
- ``error.png``: signed disparity error against the truth (blue = estimate too small, i.e. too
  far; red = too large, too near), clipped at ``error_range_px``;
- ``badpix.png``: the centre view in grey with pixels off by more than 0.07 px in red;
- ``regions.png``: the region map in the paper's colours (occluding red, occluded blue, texture
  yellow, smooth green);
- ``window_size.png``: the chosen window side per pixel with a colour bar;
- ``profile_row<N>.png``: disparity and depth along row ``N`` against the truth (cf. the paper's
  Figs. 13-14).

Headline colours (green / amber / red) use fixed thresholds, documented in
``docs/depth-and-export.md``: BadPix 0.07 below 10 % / 25 %; median depth error below 0.5 % / 2 %
of the distance; coverage above 95 % / 80 %.
"""

from __future__ import annotations

import datetime as _dt
import html
import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from recon.depth import depth_error_scores, depth_to_disparity, disparity_to_depth
from recon.colour import LUTS, NO_VALUE, colour_map, robust_range
from recon.lf.imageio import write_png
from recon.lf.lightfield import to_float

#: Region labels as ``recon.entropy.regions`` numbers them (0..3) and the paper's colours (RGB).
REGION_NAMES = ("occluding", "occluded", "texture", "smooth")
REGION_COLOURS = {
    "occluding": (255, 0, 0),
    "occluded": (0, 0, 255),
    "texture": (255, 255, 0),
    "smooth": (0, 160, 0),
}
UNLABELLED = (128, 128, 128)

BADPIX_THRESHOLD = 0.07
_SS = 2  # supersampling factor for drawing text and lines
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_INK = (40, 40, 40)
_GRID = (225, 225, 225)
_ESTIMATE = (31, 119, 180)
_TRUTH = (20, 20, 20)


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


def _display_scale(width: int, *, target: int = 420, limit: int = 760) -> float:
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
    factor = _display_scale(width) if scale is None else scale
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
    factor = _display_scale(width) if scale is None else scale
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
# the page
# --------------------------------------------------------------------------------------------------


def _as_rgb8(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    rgb = np.clip(to_float(image) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.repeat(rgb[..., None], 3, axis=-1) if rgb.ndim == 2 else rgb


def _default_rows(height: int, truth: np.ndarray | None, border: int) -> list[int]:
    """Three rows: by default at 1/4, 1/2, 3/4 of the height, moved to the nearby row with the most
    structure in the truth (largest spread) when there is a truth."""
    rows = []
    for fraction in (0.25, 0.5, 0.75):
        row = int(round(fraction * (height - 1)))
        if truth is not None:
            lo, hi = max(border, row - height // 10), min(height - border, row + height // 10 + 1)
            if hi > lo:
                window = np.where(np.isfinite(truth[lo:hi]), truth[lo:hi], np.nan)
                with warnings.catch_warnings():  # rows without any truth are all-NaN slices
                    warnings.simplefilter("ignore", RuntimeWarning)
                    spread = np.nanpercentile(window, 95, axis=1) - np.nanpercentile(window, 5, axis=1)
                if np.isfinite(spread).any():
                    row = lo + int(np.nanargmax(spread))
        rows.append(row)
    return sorted(set(rows))


def _badge(label: str, value: str, level: str | None, note: str = "") -> str:
    cls = f"badge {level}" if level else "badge"
    tip = f' title="{html.escape(note)}"' if note else ""
    return f'<div class="{cls}"{tip}><div class="value">{html.escape(value)}</div><div class="label">{html.escape(label)}</div></div>'


def _level(value: float, good: float, fair: float, *, lower_is_better: bool = True) -> str | None:
    if not math.isfinite(value):
        return None
    if lower_is_better:
        return "good" if value <= good else "fair" if value <= fair else "poor"
    return "good" if value >= good else "fair" if value >= fair else "poor"


def _format(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return html.escape(str(value))
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "–"
        return f"{value:.4g}" if abs(value) < 1e5 else f"{value:.6g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_format(v) for v in value)
    return html.escape(str(value))


def _table(rows: Sequence[Mapping[str, Any]], columns: Sequence[tuple[str, str]], *, first: str) -> str:
    head = "".join(f"<th>{html.escape(title)}</th>" for _, title in columns)
    body = []
    for row in rows:
        cells = "".join(
            f'<td class="{"text" if key == first else "num"}">{_format(row.get(key))}</td>' for key, _ in columns
        )
        body.append(f"<tr>{cells}</tr>")
    return f'<table><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>'


def _key_values(values: Mapping[str, Any]) -> str:
    rows = []
    for key, value in values.items():
        if isinstance(value, Mapping):
            value = ", ".join(f"{k} = {_format(v)}" for k, v in value.items())
            rows.append(f'<tr><th>{html.escape(str(key))}</th><td class="text">{value}</td></tr>')
        else:
            rows.append(f'<tr><th>{html.escape(str(key))}</th><td class="text">{_format(value)}</td></tr>')
    return f'<table class="kv"><tbody>{"".join(rows)}</tbody></table>'


_CSS = """
:root { --ink: #222; --muted: #667; --line: #e3e5ea; --card: #fff; --bg: #f4f5f7; }
* { box-sizing: border-box; }
body { margin: 0; background: var(--bg); color: var(--ink);
       font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; }
main { max-width: 1180px; margin: 0 auto; padding: 24px 20px 40px; }
header h1 { font-size: 24px; margin: 0 0 2px; font-weight: 650; }
header .sub { color: var(--muted); margin: 0 0 16px; word-break: break-all; }
.badges { display: flex; flex-wrap: wrap; gap: 10px; margin-bottom: 22px; }
.badge { background: var(--card); border: 1px solid var(--line); border-left: 6px solid #9aa3b2;
         border-radius: 8px; padding: 8px 14px; min-width: 150px; }
.badge.good { border-left-color: #2e9d4f; } .badge.fair { border-left-color: #e0a100; }
.badge.poor { border-left-color: #d1342f; }
.badge .value { font-size: 22px; font-weight: 650; font-variant-numeric: tabular-nums; }
.badge .label { color: var(--muted); font-size: 13px; }
h2 { font-size: 17px; margin: 26px 0 10px; font-weight: 650; }
.grid { display: grid; grid-template-columns: repeat(auto-fit, minmax(420px, 1fr)); gap: 16px; }
figure { margin: 0; background: var(--card); border: 1px solid var(--line); border-radius: 8px;
         padding: 12px; display: flex; flex-direction: column; }
figure img { max-width: 100%; height: auto; align-self: center; image-rendering: auto; }
figure.wide { grid-column: 1 / -1; }
figcaption { color: var(--muted); font-size: 13px; margin-top: 8px; }
figcaption b { color: var(--ink); font-weight: 600; }
.legend { display: flex; flex-wrap: wrap; gap: 4px 14px; margin-top: 8px; font-size: 13px; }
.legend span.swatch { display: inline-block; width: 12px; height: 12px; border-radius: 2px;
                      margin-right: 5px; vertical-align: -1px; border: 1px solid rgba(0,0,0,.25); }
.profiles { display: grid; grid-template-columns: 1fr; gap: 6px; justify-items: center; }
.profiles img { max-width: 100%; height: auto; }
table { border-collapse: collapse; background: var(--card); border: 1px solid var(--line);
        border-radius: 8px; overflow: hidden; font-variant-numeric: tabular-nums; }
th, td { padding: 6px 12px; border-bottom: 1px solid var(--line); text-align: right; font-size: 14px; }
thead th { background: #eef0f4; font-weight: 600; }
td.text, table.kv th { text-align: left; }
table.kv th { color: var(--muted); font-weight: 500; }
footer { color: var(--muted); font-size: 12.5px; margin-top: 30px; }
"""


def write_report(
    out_dir,
    *,
    centre_view: np.ndarray,
    disparity_px: np.ndarray,
    title: str = "lfrig reconstruction",
    subtitle: str = "",
    truth_disparity_px: np.ndarray | None = None,
    truth_depth_mm: np.ndarray | None = None,
    camera: Mapping[str, float] | None = None,
    region_map: np.ndarray | None = None,
    region_names: Sequence[str] = REGION_NAMES,
    window_size_px: np.ndarray | None = None,
    rows: Sequence[int] | None = None,
    disparity_range: tuple[float, float] | None = None,
    error_range_px: float = 0.2,
    border_px: int = 15,
    scores: Mapping[str, Any] | None = None,
    info: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``out_dir/index.html`` and its PNG figures; returns the path of the page.

    Parameters
    ----------
    out_dir
        Folder for the page and figures (created if missing; files of the same names are replaced).
    centre_view
        ``(H, W, 3)`` RGB or ``(H, W)`` grey, ``uint8``/``uint16``/float in ``[0, 1]``.
    disparity_px
        ``(H, W)`` estimated disparity, pixels per view step; ``NaN`` where there is none.
    title, subtitle
        Page heading and the line under it (e.g. the light-field path).
    truth_disparity_px
        ``(H, W)`` true disparity, or ``None``: enables the error map, BadPix map, scores and the
        truth curves of the profiles.
    truth_depth_mm
        ``(H, W)`` true depth in mm instead (e.g. a simulated scene's); needs ``camera``.
    camera
        ``{"focal_px", "pitch_mm", "disparity_offset"}`` for metric depth (depth figure, depth
        profiles and depth-error scores), or ``None``.
    region_map
        ``(H, W)`` integer labels (``region_names[k]`` names label ``k``), or an ``(H, W, 3)`` RGB
        picture already in the paper's colours, or ``None``.
    window_size_px
        ``(H, W)`` chosen window side in pixels, or ``None``.
    rows
        Image rows for the profiles; default three rows near 1/4, 1/2, 3/4 of the height, moved to
        where the truth has most structure.
    disparity_range
        ``(low, high)`` of the disparity colour bar; default the 1st..99th percentile.
    error_range_px
        The error map is clipped at ``±error_range_px``.
    border_px
        Pixels left out on every side when scoring (the benchmark's 15; 0 for images too small).
    scores, info
        Extra numbers ("Reported by the run") and facts about the run (method, options, times) to
        list on the page; values may be numbers, strings or one level of nested mappings.
    """
    from recon.evaluate import score

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    disparity = np.asarray(disparity_px, dtype=np.float64)
    if disparity.ndim != 2:
        raise ValueError(f"disparity_px must be an (H, W) map; got shape {disparity.shape}")
    shape = disparity.shape
    height, width = shape
    view = _as_rgb8(centre_view)
    if view.shape[:2] != shape:
        raise ValueError(f"centre_view is {view.shape[:2]} but disparity_px is {shape}; they must match")
    if truth_depth_mm is not None:
        if truth_disparity_px is not None or camera is None:
            raise ValueError("truth_depth_mm needs camera= and replaces truth_disparity_px; give one truth")
        truth_disparity_px = depth_to_disparity(np.asarray(truth_depth_mm, dtype=np.float64), **camera)
    truth = None if truth_disparity_px is None else np.asarray(truth_disparity_px, dtype=np.float64)
    if truth is not None and truth.shape != shape:
        raise ValueError(f"truth_disparity_px is {truth.shape} but disparity_px is {shape}")
    if 2 * border_px >= min(shape):
        border_px = 0
    figures: list[str] = []
    factor = _display_scale(width)

    # ---- numbers first: they go in the headline
    finite = np.isfinite(disparity)
    coverage = 100.0 * finite.mean()
    depth = truth_depth = None
    if camera is not None:
        depth = disparity_to_depth(disparity, **camera)
        if truth is not None:
            truth_depth = disparity_to_depth(truth, **camera)
    general: dict[str, Any] | None = None
    region_rows: list[dict[str, Any]] = []
    labels = None if region_map is None or np.asarray(region_map).ndim != 2 else np.asarray(region_map)
    if truth is not None:
        general = {"region": "all pixels", **score(disparity.astype(np.float32), truth.astype(np.float32), border=border_px)}
        if truth_depth is not None:
            general["depth_median_pct"] = depth_error_scores(depth, truth_depth, border_px=border_px)["median_abs_rel_pct"]
        if labels is not None:
            for label, name in enumerate(region_names):
                mask = labels == label
                row = {"region": name, **score(disparity.astype(np.float32), truth.astype(np.float32),
                                               border=border_px, mask=mask)}
                if truth_depth is not None:
                    row["depth_median_pct"] = depth_error_scores(depth, truth_depth, mask=mask, border_px=border_px)[
                        "median_abs_rel_pct"]
                region_rows.append(row)

    badges = [_badge("pixels with a disparity", f"{coverage:.1f} %", _level(coverage, 95, 80, lower_is_better=False))]
    if general is not None:
        badges.append(_badge("BadPix 0.07 (|error| > 0.07 px)", f"{general['badpix_0.07']:.2f} %",
                             _level(general["badpix_0.07"], 10, 25)))
        badges.append(_badge("MSE × 100", f"{general['mse_x100']:.3f}", None))
        if "depth_median_pct" in general:
            badges.append(_badge("median depth error (of distance)", f"{general['depth_median_pct']:.3f} %",
                                 _level(general["depth_median_pct"], 0.5, 2.0)))
        texture = next((r for r in region_rows if r["region"] == "texture"), None)
        if texture is not None and "depth_median_pct" in texture:
            badges.append(_badge("… on textured surfaces", f"{texture['depth_median_pct']:.3f} %",
                                 _level(texture["depth_median_pct"], 0.5, 2.0)))
    if depth is not None and np.isfinite(depth).any():
        near, far = np.nanpercentile(depth, [1, 99])
        badges.append(_badge("depth (1st–99th percentile)", f"{near:.0f}–{far:.0f} mm", None))

    # ---- figures
    if rows is None:
        rows = _default_rows(height, truth, border_px)
    rows = [int(r) for r in rows if 0 <= int(r) < height]
    write_png(out / "centre_view.png", image_figure(view, rows=rows, scale=factor))
    figures.append(_figure("centre_view.png", "Centre view",
                           "the rows of the depth profiles below are marked" if rows else ""))

    low, high = robust_range(disparity if truth is None else np.concatenate([disparity.ravel(), truth.ravel()]),
                              disparity_range)
    picture = colour_map(disparity, low=low, high=high, lut="turbo")
    write_png(out / "disparity.png", colourbar_figure(picture, low=low, high=high, lut="turbo",
                                                       label="disparity (px per view step)", scale=factor))
    figures.append(_figure("disparity.png", "Disparity",
                           f"near is red, far is blue; dark grey: no value ({100 - coverage:.1f} % of pixels)"))

    if depth is not None:
        d_low, d_high = robust_range(depth)
        picture = colour_map(depth, low=d_low, high=d_high, lut="turbo_r")
        write_png(out / "depth.png", colourbar_figure(picture, low=d_low, high=d_high, lut="turbo_r",
                                                       label="depth (mm)", scale=factor))
        figures.append(_figure("depth.png", "Depth",
                               f"Z = focal_px · pitch_mm / (d + d0), focal {camera['focal_px']:.6g} px, "
                               f"pitch {camera['pitch_mm']:.4g} mm, d0 {camera.get('disparity_offset', 0.0):.4g}"))

    if depth is not None:
        write_png(out / "shaded.png", image_figure(shaded_relief(depth, focal_px=camera["focal_px"]), scale=factor))
        figures.append(_figure("shaded.png", "Shaded surface",
                               "the depth map (smoothed over 1.5 px) lit from the upper left: bumps and false steps show as "
                               "light and shade"))

    if truth is not None:
        error = disparity - truth
        picture = colour_map(error, low=-error_range_px, high=error_range_px, lut="diverging")
        write_png(out / "error.png", colourbar_figure(picture, low=-error_range_px, high=error_range_px,
                                                       lut="diverging", label="estimate - truth (px)", scale=factor))
        figures.append(_figure("error.png", "Disparity error",
                               f"red: estimate too near, blue: too far; clipped at ±{error_range_px:g} px"))
        grey = cv2.cvtColor(view, cv2.COLOR_RGB2GRAY)
        bad = (np.abs(error) > BADPIX_THRESHOLD) | (np.isfinite(truth) & ~finite)
        pale = (155 + 0.35 * grey).astype(np.uint8)
        badpix = np.repeat(pale[..., None], 3, axis=-1)
        badpix[bad] = (215, 25, 28)
        if border_px:
            outside = np.ones(shape, bool)
            outside[border_px:-border_px, border_px:-border_px] = False
            badpix[outside] = (badpix[outside] * 0.6).astype(np.uint8)
        write_png(out / "badpix.png", image_figure(badpix, scale=factor))
        caption = f"red: |error| > {BADPIX_THRESHOLD} px or no value"
        if border_px:
            caption += f"; the darker {border_px}-pixel border is not scored"
        figures.append(_figure("badpix.png", f"BadPix {BADPIX_THRESHOLD}", caption))

    if region_map is not None:
        region = np.asarray(region_map)
        picture = region_picture(region, names=region_names) if region.ndim == 2 else _as_rgb8(region)
        write_png(out / "regions.png", image_figure(picture, scale=factor))
        legend = []
        for label, name in enumerate(region_names):
            share = f" {100.0 * np.mean(region == label):.1f} %" if region.ndim == 2 else ""
            colour = "#%02x%02x%02x" % REGION_COLOURS.get(name, UNLABELLED)
            legend.append(f'<span><span class="swatch" style="background:{colour}"></span>{html.escape(name)}{share}</span>')
        figures.append(_figure("regions.png", "Region types", "", extra=f'<div class="legend">{"".join(legend)}</div>'))

    if window_size_px is not None:
        sizes = np.asarray(window_size_px, dtype=np.float64)
        if sizes.shape != shape:
            raise ValueError(f"window_size_px is {sizes.shape} but disparity_px is {shape}")
        present = np.unique(sizes[np.isfinite(sizes)])
        w_low, w_high = (float(present.min()), float(present.max())) if present.size else (0.0, 1.0)
        if w_high <= w_low:
            w_low, w_high = w_low - 1, w_high + 1
        ticks = present if 0 < present.size <= 8 else None
        picture = colour_map(sizes, low=w_low, high=w_high, lut="viridis")
        write_png(out / "window_size.png", colourbar_figure(picture, low=w_low, high=w_high, lut="viridis",
                                                             label="window side (px)", ticks=ticks, scale=factor))
        figures.append(_figure("window_size.png", "Window size", "side of the square window chosen per pixel"))

    profiles = []
    columns = np.arange(width)
    for row in rows:
        plots = []
        series = [("estimate", disparity[row], _ESTIMATE, 2.0)]
        if truth is not None:
            series.append(("truth", truth[row], _TRUTH, 1.0))
        plots.append(line_plot(columns, series, xlabel=f"column x (px), row {row}", ylabel="disparity (px)"))
        if depth is not None:
            series = [("estimate", depth[row], _ESTIMATE, 2.0)]
            if truth_depth is not None:
                series.append(("truth", truth_depth[row], _TRUTH, 1.0))
            plots.append(line_plot(columns, series, xlabel=f"column x (px), row {row}", ylabel="depth (mm)"))
        name = f"profile_row{row}.png"
        write_png(out / name, np.concatenate(plots, axis=1) if len(plots) > 1 else plots[0])
        profiles.append(f'<img src="{name}" alt="profile along row {row}">')

    # ---- the page
    parts = [f"<header><h1>{html.escape(title)}</h1>"]
    parts.append(f'<p class="sub">{html.escape(subtitle)}</p>' if subtitle else '<p class="sub"></p>')
    parts.append(f'<div class="badges">{"".join(badges)}</div></header>')
    parts.append(f'<div class="grid">{"".join(figures)}</div>')
    if profiles:
        what = "Depth and disparity" if depth is not None else "Disparity"
        against = " against the truth (black)" if truth is not None else ""
        parts.append(f"<h2>{what} along rows{against}</h2>")
        parts.append(f'<figure class="wide"><div class="profiles">{"".join(profiles)}</div>'
                     "<figcaption>blue: estimate; gaps: no value. Compare the paper's Figs. 13–14."
                     "</figcaption></figure>")
    if general is not None:
        columns_spec = [("region", "pixels scored"), ("pixels", "count"), ("mse_x100", "MSE ×100"),
                        ("badpix_0.07", "BadPix 0.07 %"), ("badpix_0.03", "BadPix 0.03 %"),
                        ("badpix_0.01", "BadPix 0.01 %")]
        if "depth_median_pct" in general:
            columns_spec.append(("depth_median_pct", "median |ΔZ|/Z %"))
        parts.append("<h2>Scores against the truth</h2>")
        parts.append(_table([general, *region_rows], columns_spec, first="region"))
        parts.append(f'<p class="sub">The 4D Light Field Benchmark\'s scores: a border of {border_px} px is left '
                     "out; BadPix t is the share of pixels with |estimate − truth| &gt; t px.</p>")
    if scores:
        parts.append("<h2>Reported by the run</h2>" + _key_values(scores))
    if info:
        parts.append("<h2>Run</h2>" + _key_values(info))
    stamp = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    parts.append(
        f"<footer>Written by lfrig on {html.escape(stamp)}. Disparity in pixels per view step, positive for points "
        "in front of the plane of zero disparity; depth in mm along the centre camera's optical axis "
        "(docs/conventions.md).</footer>"
    )
    page = (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head>\n<body><main>\n"
        + "\n".join(parts)
        + "\n</main></body></html>\n"
    )
    path = out / "index.html"
    path.write_text(page, encoding="utf-8")
    return path


def _figure(name: str, title: str, caption: str, *, extra: str = "") -> str:
    text = f"<b>{html.escape(title)}</b>" + (f" — {html.escape(caption)}" if caption else "")
    return f'<figure><img src="{name}" alt="{html.escape(title)}"><figcaption>{text}</figcaption>{extra}</figure>'


# --------------------------------------------------------------------------------------------------
# from a reconstruction folder
# --------------------------------------------------------------------------------------------------


def report_for_result(result, out_dir, *, camera: Mapping[str, float] | None = None) -> Path:
    """:func:`write_report` for a :class:`recon.export.ResultFolder` (``lfrig export --report``).

    Reads, when present: the truth ``gt_disp_lowres.pfm`` in the ``source`` light-field folder;
    ``regions.npy`` (``(H, W)`` labels 0..3) or ``regions.png`` (labels, or the coloured picture) and
    ``window_size.npy`` / ``window_size.pfm`` in the result folder; ``scores``, ``method``,
    ``options`` and ``seconds`` from ``result.json``. ``camera`` defaults to the folder's own.
    """
    from recon.lf.pfm import read_pfm

    folder = Path(result.path)
    record = dict(result.record)
    if camera is None and result.focal_px is not None and result.pitch_mm is not None:
        camera = {"focal_px": result.focal_px, "pitch_mm": result.pitch_mm,
                  "disparity_offset": result.disparity_offset}
    truth = None
    source = record.get("source")
    if source:
        source_path = Path(source) if Path(source).is_absolute() else folder / source
        gt = source_path / "gt_disp_lowres.pfm"
        if gt.is_file():
            truth = read_pfm(gt)
            if truth.shape != result.disparity_px.shape:
                truth = None
    regions = None
    if (folder / "regions.npy").is_file():
        regions = np.load(folder / "regions.npy")
    elif (folder / "regions.png").is_file():
        from recon.lf.imageio import read_image

        regions = read_image(folder / "regions.png")
    window = None
    if (folder / "window_size.npy").is_file():
        window = np.load(folder / "window_size.npy")
    elif (folder / "window_size.pfm").is_file():
        window = read_pfm(folder / "window_size.pfm")
    view = result.image
    if view is None:
        view = np.zeros(result.disparity_px.shape, np.uint8)
    info = {key: record[key] for key in ("method", "options", "seconds", "source") if key in record}
    # the run's own scores only when the page cannot score against the truth itself
    extra = None if truth is not None else ({k: v for k, v in (record.get("scores") or {}).items()
                                             if not isinstance(v, Mapping)} or None)
    return write_report(
        out_dir,
        centre_view=view,
        disparity_px=result.disparity_px,
        title=f"lfrig reconstruction: {Path(str(source)).name if source else folder.name}",
        subtitle=str(folder.resolve()),
        truth_disparity_px=truth,
        camera=camera,
        region_map=regions if regions is not None and regions.shape[:2] == result.disparity_px.shape else None,
        window_size_px=window if window is not None and window.shape == result.disparity_px.shape else None,
        scores=extra,
        info=info or None,
    )
