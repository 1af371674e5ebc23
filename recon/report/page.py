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
- ``depth_error.png``: true minus estimated depth in mm (with a truth and the camera), red where
  the estimate is too near;
- ``badpix.png``: the centre view in grey with pixels off by more than 0.07 px in red;
- ``regions.png``: the region map in the paper's colours (occluding red, occluded blue, texture
  yellow, smooth green);
- ``window_size.png``: the chosen window side per pixel with a colour bar;
- ``profile_row<N>.png``: disparity and depth along row ``N`` against the truth (cf. the paper's
  Figs. 13-14).

Every colour bar's caption says what its colours span and how much is clipped. With a ``model``
the page also has an interactive 3D view (:mod:`recon.report.model`: ``model-data.js``,
``viewer.js`` and the vendored ``three.viewer.min.js`` with ``LICENSE-three.txt``, all classic
scripts so that the page works from ``file://``). The method's options are shown as grouped tables,
and the footer lists how the result was made (``provenance``) or says it was not recorded.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from recon.camera import Camera
from recon.colour import colour_map, robust_range
from recon.depth import depth_error_scores
from recon.lf.imageio import write_bytes_atomic, write_png
from recon.report.model import ViewerModel, decimate, write_viewer_files
from recon.report.figures import (ESTIMATE, REGION_COLOURS, REGION_NAMES, TRUTH, UNLABELLED, as_rgb8,
                                      colourbar_figure, display_scale, image_figure, line_plot, region_picture,
                                      reliability_figure, shaded_relief, sparsification_figure)
from recon.errors import ExportError
from recon.result import (REGIONS_NPY, REGIONS_PNG, WINDOW_SIZE_NPY, ResultFolder, source_folder)

BADPIX_THRESHOLD = 0.07


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
    if isinstance(value, dict):
        return ", ".join(f"{html.escape(str(k))} {_format(v)}" for k, v in value.items()) or "–"
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
footer table.kv { margin-top: 6px; } footer td, footer th { font-size: 12.5px; padding: 3px 10px; }
.settings { display: grid; grid-template-columns: repeat(auto-fit, minmax(340px, 1fr)); gap: 12px; align-items: start; }
.settings table { width: 100%; }
.settings caption { text-align: left; font-weight: 600; padding: 0 0 4px 2px; }
#lfrig-3d canvas { width: 100%; height: 520px; display: block; border-radius: 6px; background: #f4f5f7; cursor: grab; }
#lfrig-3d .toolbar { display: flex; flex-wrap: wrap; gap: 6px; margin-bottom: 8px; align-items: center; }
#lfrig-3d button { font: inherit; font-size: 13px; padding: 3px 10px; border: 1px solid #c4c8d0; border-radius: 5px;
                   background: #fff; cursor: pointer; }
#lfrig-3d button.on { background: #222; color: #fff; border-color: #222; }
#lfrig-3d button:disabled { opacity: .4; cursor: default; }
#lfrig-3d .status { color: #a33; margin: 6px 0 0; }
#lfrig-3d .legend3d { font-size: 13px; color: var(--muted); margin-top: 6px; }
#lfrig-3d .ramp { display: inline-block; width: 120px; height: 10px; margin-right: 8px; vertical-align: -1px;
                  border: 1px solid rgba(0,0,0,.25); }
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
    camera: Camera | None = None,
    region_map: np.ndarray | None = None,
    region_names: Sequence[str] = REGION_NAMES,
    window_size_px: np.ndarray | None = None,
    confidence: np.ndarray | None = None,
    min_confidence: float | None = None,
    rows: Sequence[int] | None = None,
    disparity_range: tuple[float, float] | None = None,
    error_range_px: float = 0.2,
    border_px: int = 15,
    scores: Mapping[str, Any] | None = None,
    info: Mapping[str, Any] | None = None,
    model: ViewerModel | None = None,
    provenance: Mapping[str, Any] | None = None,
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
        The rectified camera (:class:`recon.camera.Camera`) for metric depth (depth figure, depth
        profiles and depth-error scores), or ``None``.
    region_map
        ``(H, W)`` integer labels (``region_names[k]`` names label ``k``), or an ``(H, W, 3)`` RGB
        picture already in the paper's colours, or ``None``.
    window_size_px
        ``(H, W)`` chosen window side in pixels, or ``None``.
    confidence, min_confidence
        ``(H, W)`` per-pixel confidence in ``[0, 1]`` (``confidence.pfm``) and the export's threshold,
        or ``None``: a figure, the share of pixels the export keeps and, with the truth, the scores of
        the kept pixels.
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
        ``info["options"]`` (the method's settings) is shown as a table grouped by the stage of the
        method each option belongs to.
    model
        The exported mesh or point cloud (:class:`recon.report.model.ViewerModel`, e.g.
        :func:`recon.report.model.read_ply`) for the interactive 3D view, or ``None`` for no view.
        It is simplified to at most :data:`recon.report.model.MAX_TRIANGLES` triangles or
        ``MAX_POINTS`` points first (:func:`recon.report.model.decimate`); the page says so.
    provenance
        How the result was made (``result.json``'s ``provenance``: ``lfrig_version``, ``command``,
        ``started_utc``, ``input``, ``timings_s``, ``machine``), shown in the footer; ``None``: the
        footer says it was not recorded.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    maps = _Maps.of(centre_view=centre_view, disparity_px=disparity_px, truth_disparity_px=truth_disparity_px,
                    truth_depth_mm=truth_depth_mm, camera=camera, border_px=border_px)
    labels = None if region_map is None or np.asarray(region_map).ndim != 2 else np.asarray(region_map)
    general, region_rows = _score_rows(maps, labels, region_names)
    if rows is None:
        rows = _default_rows(maps.height, maps.truth, maps.border_px)
    rows = [int(r) for r in rows if 0 <= int(r) < maps.height]
    figures = _map_figures(out, maps, rows=rows, disparity_range=disparity_range, error_range_px=error_range_px)
    figures += _method_figures(out, maps, region_map=region_map, region_names=region_names,
                               window_size_px=window_size_px, confidence=confidence,
                               min_confidence=min_confidence)
    figures += _confidence_figures(out, maps, confidence)
    if confidence is not None and min_confidence is not None and general is not None:
        kept = np.asarray(confidence) >= min_confidence
        region_rows = region_rows + [_score_rows(maps, kept.astype(np.int64), ("dropped by the export", "kept by the export"))[1][1]]
    profiles = _profiles(out, maps, rows)
    viewer, viewer_scripts = _viewer_section(out, model) if model is not None else ("", [])

    parts = [f"<header><h1>{html.escape(title)}</h1>"]
    parts.append(f'<p class="sub">{html.escape(subtitle)}</p>' if subtitle else '<p class="sub"></p>')
    badges = _badges(maps, general, region_rows) + _kept_badge(confidence, min_confidence)
    parts.append(f'<div class="badges">{"".join(badges)}</div></header>')
    parts.append(f'<div class="grid">{"".join(figures)}</div>')
    if viewer:
        parts.append(viewer)
    if profiles:
        what = "Depth and disparity" if maps.depth is not None else "Disparity"
        against = " against the truth (black)" if maps.truth is not None else ""
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
        parts.append(f'<p class="sub">The 4D Light Field Benchmark\'s scores: a border of {maps.border_px} px is left '
                     "out; BadPix t is the share of pixels with |estimate − truth| &gt; t px.</p>")
    if scores:
        parts.append("<h2>Reported by the run</h2>" + _key_values(scores))
    if info:
        rest = {key: value for key, value in info.items() if key != "options"}
        if rest:
            parts.append("<h2>Run</h2>" + _key_values(rest))
        if isinstance(info.get("options"), Mapping) and info["options"]:
            parts.append("<h2>Settings</h2>" + _settings_tables(info["options"]))
    stamp = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    parts.append(
        f"<footer>Written by lfrig on {html.escape(stamp)}. Disparity in pixels per view step, positive for points "
        "in front of the plane of zero disparity; depth in mm along the centre camera's optical axis "
        f"(docs/conventions.md).{_provenance_footer(provenance)}</footer>"
    )
    scripts = "".join(f'<script src="{html.escape(name)}"></script>' for name in viewer_scripts)
    page = (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head>\n<body><main>\n"
        + "\n".join(parts)
        + f"\n</main>{scripts}</body></html>\n"
    )
    path = out / "index.html"
    write_bytes_atomic(path, page.encode("utf-8"))
    return path


#: The settings table's groups: (title, option names), in page order; a name also takes the options
#: that extend it (``hole`` takes ``hole_width``), the first group that matches wins, the rest go last.
SETTING_GROUPS = (
    ("disparity range and sampling", ("disparity_range", "initial_range", "discover_range", "initial_step",
                                      "initial_window", "initial_shiftable", "range", "step")),
    ("occlusion layers", ("layer", "occlusion")),
    ("windows and matching entropy", ("window", "grey_bins", "disparity_bin", "smooth", "strip_windows", "side",
                                      "single_layer", "crease", "visible_sets", "joint", "lambda", "alpha1", "alpha2",
                                      "intensity_scale", "centroid", "flat_windows")),
    ("refinement and holes", ("gamma", "tv", "fill_holes", "hole", "initial_hole")),
    ("noise and weak texture", ("noise", "weak_texture", "strip_aperture")),
    ("object boundaries", ("boundary",)),
)


def _settings_tables(options: Mapping[str, Any]) -> str:
    """The method's options as small tables, one per :data:`SETTING_GROUPS` group ("other" last)."""
    groups: dict[str, list[tuple[str, Any]]] = {title: [] for title, _ in SETTING_GROUPS}
    groups["other"] = []
    for key, value in options.items():
        title = next((t for t, prefixes in SETTING_GROUPS
                      if any(key == p or key.startswith(p + "_") for p in prefixes)), "other")
        groups[title].append((key, value))
    tables = []
    for title, items in groups.items():
        if not items:
            continue
        rows = "".join(f'<tr><th>{html.escape(str(k))}</th><td class="text">{_format(v)}</td></tr>' for k, v in items)
        tables.append(f'<table class="kv"><caption>{html.escape(title)}</caption><tbody>{rows}</tbody></table>')
    return f'<div class="settings">{"".join(tables)}</div>'


def _provenance_footer(provenance: Mapping[str, Any] | None) -> str:
    """The footer's record of how the result was made (``result.json`` → ``provenance``)."""
    if not isinstance(provenance, Mapping) or not provenance:
        return " <br>How the result was made (lfrig version, command, input, timings, machine): not recorded."
    rows: dict[str, Any] = {}
    if provenance.get("lfrig_version"):
        rows["lfrig version"] = provenance["lfrig_version"]
    command = provenance.get("command")
    if isinstance(command, (list, tuple)):
        import shlex

        rows["command"] = shlex.join(str(word) for word in command)
    elif command:
        rows["command"] = command
    if provenance.get("started_utc"):
        rows["started (UTC)"] = provenance["started_utc"]
    source = provenance.get("input")
    if isinstance(source, Mapping):
        digest = source.get("journal_sha256") or source.get("files_sha256")
        what = f"{source.get('kind', '')} {source.get('path', '')}".strip()
        if digest:
            what += f" (sha256 {str(digest)[:16]}…)"
        rows["input"] = what
    timings = provenance.get("timings_s")
    if isinstance(timings, Mapping) and timings:
        rows["timings"] = ", ".join(f"{k} {_format(v)} s" for k, v in timings.items())
    machine = provenance.get("machine")
    if isinstance(machine, Mapping) and machine:
        rows["machine"] = ", ".join(f"{k} {_format(v)}" for k, v in machine.items())
    if not rows:
        return " <br>How the result was made: not recorded."
    return " How the result was made:" + _key_values(rows)


def _viewer_section(out: Path, model: ViewerModel) -> tuple[str, list[str]]:
    """The interactive 3D view: writes its files into ``out``; returns its HTML and the scripts to load."""
    shown = decimate(model)
    scripts = write_viewer_files(out, shown)
    vertices, triangles = model.original
    if shown.kind == "mesh":
        what = f"{html.escape(model.name)}: a mesh of {vertices:,} vertices and {triangles:,} triangles"
        if len(shown.triangles) < triangles:
            what += (f", shown simplified to {len(shown.triangles):,} triangles by vertex clustering so that a browser "
                     "draws it smoothly (the PLY file has them all)")
    else:
        what = f"{html.escape(model.name)}: {vertices:,} points"
        if len(shown.vertices_mm) < vertices:
            what += f", of which a random {len(shown.vertices_mm):,} are shown so that a browser draws them smoothly"
    buttons = "".join(f'<button type="button" data-colour="{key}">{label}</button>'
                      for key, label in (("image", "centre view"), ("depth", "depth"), ("confidence", "confidence")))
    body = (
        '<h2>3D model</h2><figure class="wide" id="lfrig-3d">'
        f'<div class="toolbar">colour by {buttons}<button type="button" data-reset>reset view</button></div>'
        '<canvas aria-label="3D view of the model"></canvas>'
        '<p class="status">The 3D view needs JavaScript and WebGL.</p><div class="legend3d"></div>'
        f"<figcaption><b>3D model</b> — {what}. Drag to orbit, right-drag to pan, wheel to zoom; it starts "
        "on the centre camera's side, turned a little so that depth shows. Coordinates in mm, centre camera frame (docs/conventions.md). "
        'Drawn with three.js (MIT licence: <a href="LICENSE-three.txt">LICENSE-three.txt</a>).</figcaption></figure>'
    )
    return body, scripts


def _round_up(value: float) -> float:
    """The smallest of 1, 2 and 5 times a power of ten that is at least ``value`` (> 0; else 1)."""
    if not (math.isfinite(value) and value > 0):
        return 1.0
    power = 10.0 ** math.floor(math.log10(value))
    return next(m * power for m in (1, 2, 5, 10) if m * power >= value * (1 - 1e-12))


def _span_number(value: float) -> str:
    """A colour bar's end for a caption: whole numbers from 1000 up, four significant digits below."""
    return f"{value:.0f}" if abs(value) >= 1000 else f"{value:.4g}"


def _clip_note(values: np.ndarray, low: float, high: float, *, how: str, unit: str) -> tuple[str, bool]:
    """What a colour bar does with values outside ``[low, high]``: the caption's words and whether
    anything is clipped."""
    finite = np.asarray(values, np.float64)
    finite = finite[np.isfinite(finite)]
    outside = 100.0 * float(np.mean((finite < low) | (finite > high))) if finite.size else 0.0
    span = f"{_span_number(float(low))} … {_span_number(float(high))} {unit}".rstrip()
    if outside > 0:
        return f"colours clipped to {how}: {span} ({outside:.1f} % of pixels outside)", True
    return f"colours span {span}, nothing clipped", False


@dataclass
class _Maps:
    """The arrays the page shows, checked and converted once: disparity, truth, depth, the view."""

    view: np.ndarray
    disparity: np.ndarray
    truth: np.ndarray | None
    depth: np.ndarray | None
    truth_depth: np.ndarray | None
    camera: Camera | None
    border_px: int
    factor: float
    finite: np.ndarray = field(init=False)
    coverage: float = field(init=False)

    def __post_init__(self) -> None:
        self.finite = np.isfinite(self.disparity)
        self.coverage = 100.0 * float(self.finite.mean())

    @property
    def shape(self) -> tuple[int, int]:
        return self.disparity.shape

    @property
    def height(self) -> int:
        return self.disparity.shape[0]

    @classmethod
    def of(cls, *, centre_view, disparity_px, truth_disparity_px, truth_depth_mm, camera, border_px) -> "_Maps":
        disparity = np.asarray(disparity_px, dtype=np.float64)
        if disparity.ndim != 2:
            raise ValueError(f"disparity_px must be an (H, W) map; got shape {disparity.shape}")
        shape = disparity.shape
        view = as_rgb8(centre_view)
        if view.shape[:2] != shape:
            raise ValueError(f"centre_view is {view.shape[:2]} but disparity_px is {shape}; they must match")
        if truth_depth_mm is not None:
            if truth_disparity_px is not None or camera is None:
                raise ValueError("truth_depth_mm needs camera= and replaces truth_disparity_px; give one truth")
            truth_disparity_px = camera.disparity_px(np.asarray(truth_depth_mm, dtype=np.float64))
        truth = None if truth_disparity_px is None else np.asarray(truth_disparity_px, dtype=np.float64)
        if truth is not None and truth.shape != shape:
            raise ValueError(f"truth_disparity_px is {truth.shape} but disparity_px is {shape}")
        depth = truth_depth = None
        if camera is not None:
            depth = camera.depth_mm(disparity)
            if truth is not None:
                truth_depth = camera.depth_mm(truth)
        return cls(view=view, disparity=disparity, truth=truth, depth=depth, truth_depth=truth_depth, camera=camera,
                   border_px=0 if 2 * border_px >= min(shape) else border_px, factor=display_scale(shape[1]))


def _score_rows(maps: _Maps, labels: np.ndarray | None,
                region_names: Sequence[str]) -> tuple[dict[str, Any] | None, list[dict[str, Any]]]:
    """The scores against the truth: all pixels, then one row per region type (when labelled)."""
    from recon.evaluate import score

    if maps.truth is None:
        return None, []
    estimate, truth = maps.disparity.astype(np.float32), maps.truth.astype(np.float32)

    def row(name: str, mask: np.ndarray | None) -> dict[str, Any]:
        scores = {"region": name, **score(estimate, truth, border=maps.border_px, mask=mask)}
        if maps.truth_depth is not None:
            scores["depth_median_pct"] = depth_error_scores(maps.depth, maps.truth_depth, mask=mask,
                                                            border_px=maps.border_px)["median_abs_rel_pct"]
        return scores

    general = row("all pixels", None)
    regions = [] if labels is None else [row(name, labels == label) for label, name in enumerate(region_names)]
    return general, regions


def _badges(maps: _Maps, general: dict[str, Any] | None, region_rows: list[dict[str, Any]]) -> list[str]:
    """The headline numbers, coloured by the thresholds of ``docs/depth-and-export.md``."""
    badges = [_badge("pixels with a disparity", f"{maps.coverage:.1f} %",
                     _level(maps.coverage, 95, 80, lower_is_better=False))]
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
    if maps.depth is not None and np.isfinite(maps.depth).any():
        near, far = np.nanpercentile(maps.depth, [1, 99])
        badges.append(_badge("depth (1st–99th percentile)", f"{near:.0f}–{far:.0f} mm", None))
    return badges


def _map_figures(out: Path, maps: _Maps, *, rows: list[int], disparity_range, error_range_px: float) -> list[str]:
    """Centre view, disparity, depth, shaded surface, error and BadPix maps; returns their HTML."""
    figures = []
    factor, disparity, truth, depth = maps.factor, maps.disparity, maps.truth, maps.depth
    write_png(out / "centre_view.png", image_figure(maps.view, rows=rows, scale=factor))
    figures.append(_figure("centre_view.png", "Centre view",
                           "the rows of the depth profiles below are marked" if rows else ""))

    low, high = robust_range(disparity if truth is None else np.concatenate([disparity.ravel(), truth.ravel()]),
                              disparity_range)
    how = "the given range" if disparity_range is not None else "the 1st–99th percentile" + (
        " of estimate and truth" if truth is not None else "")
    note, clipped = _clip_note(disparity, low, high, how=how, unit="px")
    picture = colour_map(disparity, low=low, high=high, lut="turbo")
    write_png(out / "disparity.png", colourbar_figure(picture, low=low, high=high, lut="turbo",
                                                       label="disparity (px per view step)" + _CLIPPED * clipped,
                                                       scale=factor))
    figures.append(_figure("disparity.png", "Disparity",
                           f"near is red, far is blue; dark grey: no value ({100 - maps.coverage:.1f} % of pixels); {note}"))

    if depth is not None:
        camera = maps.camera
        d_low, d_high = robust_range(depth)
        note, clipped = _clip_note(depth, d_low, d_high, how="the 1st–99th percentile", unit="mm")
        picture = colour_map(depth, low=d_low, high=d_high, lut="turbo_r")
        write_png(out / "depth.png", colourbar_figure(picture, low=d_low, high=d_high, lut="turbo_r",
                                                       label="depth (mm)" + _CLIPPED * clipped, scale=factor))
        figures.append(_figure("depth.png", "Depth",
                               f"Z = focal_px · pitch_mm / (d + d0), focal {camera.focal_px:.6g} px, "
                               f"pitch {camera.pitch_mm:.4g} mm, d0 {camera.disparity_offset:.4g}; {note}"))
        write_png(out / "shaded.png", image_figure(shaded_relief(depth, focal_px=camera.focal_px), scale=factor))
        figures.append(_figure("shaded.png", "Shaded surface",
                               "the depth map (smoothed over 1.5 px) lit from the upper left: bumps and false steps show as "
                               "light and shade"))

    if truth is not None:
        error = disparity - truth
        note, clipped = _clip_note(error, -error_range_px, error_range_px, how=f"±{error_range_px:g} px", unit="px")
        picture = colour_map(error, low=-error_range_px, high=error_range_px, lut="diverging")
        write_png(out / "error.png", colourbar_figure(picture, low=-error_range_px, high=error_range_px,
                                                       lut="diverging", label="estimate - truth (px)" + _CLIPPED * clipped,
                                                       scale=factor))
        figures.append(_figure("error.png", "Disparity error", f"red: estimate too near, blue: too far; {note}"))
        if maps.truth_depth is not None:
            figures.append(_depth_error_figure(out, maps))
        grey = cv2.cvtColor(maps.view, cv2.COLOR_RGB2GRAY)
        bad = (np.abs(error) > BADPIX_THRESHOLD) | (np.isfinite(truth) & ~maps.finite)
        pale = (155 + 0.35 * grey).astype(np.uint8)
        badpix = np.repeat(pale[..., None], 3, axis=-1)
        badpix[bad] = (215, 25, 28)
        border_px = maps.border_px
        if border_px:
            outside = np.ones(maps.shape, bool)
            outside[border_px:-border_px, border_px:-border_px] = False
            badpix[outside] = (badpix[outside] * 0.6).astype(np.uint8)
        write_png(out / "badpix.png", image_figure(badpix, scale=factor))
        caption = f"red: |error| > {BADPIX_THRESHOLD} px or no value"
        if border_px:
            caption += f"; the darker {border_px}-pixel border is not scored"
        figures.append(_figure("badpix.png", f"BadPix {BADPIX_THRESHOLD}", caption))
    return figures


_CLIPPED = ", clipped"


def _depth_error_figure(out: Path, maps: _Maps) -> str:
    """``depth_error.png``: true minus estimated depth in mm, symmetric about 0 up to the 95th
    percentile of ``|error|`` rounded up to 1, 2 or 5 times a power of ten; red where the estimate
    is too near, blue too far (as on the disparity error map)."""
    error_mm = maps.depth - maps.truth_depth
    finite = np.abs(error_mm[np.isfinite(error_mm)])
    limit = _round_up(float(np.percentile(finite, 95)) if finite.size else 1.0)
    note, clipped = _clip_note(error_mm, -limit, limit, how=f"±{_format(limit)} mm (about the 95th percentile of |error|)",
                               unit="mm")
    # too near (negative error) is red, as on the disparity error map
    picture = colour_map(-error_mm, low=-limit, high=limit, lut="diverging")
    write_png(out / "depth_error.png", colourbar_figure(picture, low=-limit, high=limit, lut="diverging",
                                                         label="truth - estimate (mm)" + _CLIPPED * clipped,
                                                         scale=maps.factor))
    median = float(np.median(finite)) if finite.size else float("nan")
    return _figure("depth_error.png", "Depth error in mm",
                   f"red: estimate nearer than the truth, blue: farther; median |error| {_format(median)} mm; {note}")


def _method_figures(out: Path, maps: _Maps, *, region_map, region_names: Sequence[str], window_size_px,
                    confidence=None, min_confidence=None) -> list[str]:
    """What the method explains itself with: region types, window sizes, confidence; returns their HTML."""
    figures = []
    if confidence is not None:
        conf = np.asarray(confidence, dtype=np.float64)
        if conf.shape != maps.shape:
            raise ValueError(f"confidence is {conf.shape} but disparity_px is {maps.shape}")
        picture = colour_map(conf, low=0.0, high=1.0, lut="viridis")
        note, clipped = _clip_note(conf, 0.0, 1.0, how="0 … 1", unit="")
        write_png(out / "confidence.png", colourbar_figure(picture, low=0.0, high=1.0, lut="viridis",
                                                            label="confidence" + _CLIPPED * clipped, scale=maps.factor))
        caption = ("the probability that the disparity is within 0.07 px of the truth (recon.entropy.calibration); "
                   f"{note}")
        if min_confidence is not None:
            caption += (f"; the export keeps {100.0 * np.mean(conf >= min_confidence):.1f} % of pixels "
                        f"(confidence ≥ {min_confidence:g})")
        figures.append(_figure("confidence.png", "Confidence", caption))
    if region_map is not None:
        region = np.asarray(region_map)
        picture = region_picture(region, names=region_names) if region.ndim == 2 else as_rgb8(region)
        write_png(out / "regions.png", image_figure(picture, scale=maps.factor))
        legend = []
        for label, name in enumerate(region_names):
            share = f" {100.0 * np.mean(region == label):.1f} %" if region.ndim == 2 else ""
            colour = "#%02x%02x%02x" % REGION_COLOURS.get(name, UNLABELLED)
            legend.append(f'<span><span class="swatch" style="background:{colour}"></span>{html.escape(name)}{share}</span>')
        figures.append(_figure("regions.png", "Region types", "", extra=f'<div class="legend">{"".join(legend)}</div>'))

    if window_size_px is not None:
        sizes = np.asarray(window_size_px, dtype=np.float64)
        if sizes.shape != maps.shape:
            raise ValueError(f"window_size_px is {sizes.shape} but disparity_px is {maps.shape}")
        present = np.unique(sizes[np.isfinite(sizes)])
        w_low, w_high = (float(present.min()), float(present.max())) if present.size else (0.0, 1.0)
        if w_high <= w_low:
            w_low, w_high = w_low - 1, w_high + 1
        ticks = present if 0 < present.size <= 8 else None
        picture = colour_map(sizes, low=w_low, high=w_high, lut="viridis")
        write_png(out / "window_size.png", colourbar_figure(picture, low=w_low, high=w_high, lut="viridis",
                                                             label="window side (px)", ticks=ticks, scale=maps.factor))
        figures.append(_figure("window_size.png", "Window size", "side of the square window chosen per pixel; "
                               + _clip_note(sizes, w_low, w_high, how="", unit="px")[0]))
    return figures


def _kept_badge(confidence, min_confidence) -> list[str]:
    """The headline share of pixels the export keeps (confidence at least ``min_confidence``)."""
    if confidence is None or min_confidence is None:
        return []
    kept = 100.0 * float(np.mean(np.asarray(confidence) >= min_confidence))
    return [_badge(f"kept by the export (confidence ≥ {min_confidence:g})", f"{kept:.1f} %", None)]


def _confidence_figures(out: Path, maps: _Maps, confidence) -> list[str]:
    """With a truth: the confidence's reliability diagram and sparsification curve (inside the
    scoring border); returns their HTML."""
    if confidence is None or maps.truth is None:
        return []
    b = maps.border_px
    inner = (slice(b, maps.shape[0] - b or None), slice(b, maps.shape[1] - b or None))
    conf = np.asarray(confidence, np.float64)[inner]
    error = np.abs(maps.disparity - maps.truth)[inner]
    ok = np.isfinite(maps.truth[inner])
    right = error[ok] <= 0.07
    write_png(out / "reliability.png", reliability_figure(conf[ok], right))
    write_png(out / "sparsification.png", sparsification_figure(conf[ok], np.where(np.isfinite(error), error, np.inf)[ok]))
    return [_figure("reliability.png", "Reliability of the confidence",
                    "share of right pixels (|error| ≤ 0.07 px) per confidence bin; calibrated on the diagonal"),
            _figure("sparsification.png", "Sparsification",
                    "BadPix 0.07 of the pixels left as the least confident are removed, and the ideal")]


def _profiles(out: Path, maps: _Maps, rows: list[int]) -> list[str]:
    """Disparity (and depth) along each row against the truth; returns the ``<img>`` tags."""
    profiles = []
    columns = np.arange(maps.shape[1])
    for row in rows:
        plots = []
        series = [("estimate", maps.disparity[row], ESTIMATE, 2.0)]
        if maps.truth is not None:
            series.append(("truth", maps.truth[row], TRUTH, 1.0))
        plots.append(line_plot(columns, series, xlabel=f"column x (px), row {row}", ylabel="disparity (px)"))
        if maps.depth is not None:
            series = [("estimate", maps.depth[row], ESTIMATE, 2.0)]
            if maps.truth_depth is not None:
                series.append(("truth", maps.truth_depth[row], TRUTH, 1.0))
            plots.append(line_plot(columns, series, xlabel=f"column x (px), row {row}", ylabel="depth (mm)"))
        name = f"profile_row{row}.png"
        write_png(out / name, np.concatenate(plots, axis=1) if len(plots) > 1 else plots[0])
        profiles.append(f'<img src="{name}" alt="profile along row {row}">')
    return profiles


def _figure(name: str, title: str, caption: str, *, extra: str = "") -> str:
    text = f"<b>{html.escape(title)}</b>" + (f" — {html.escape(caption)}" if caption else "")
    return f'<figure><img src="{name}" alt="{html.escape(title)}"><figcaption>{text}</figcaption>{extra}</figure>'


# --------------------------------------------------------------------------------------------------
# from a reconstruction folder
# --------------------------------------------------------------------------------------------------


def report_for_result(result: ResultFolder, out_dir, *, camera: Camera | None = None, ply=None) -> Path:
    """:func:`write_report` for a reconstruction folder (:func:`recon.result.read_result`; ``lfrig
    export --report``).

    Reads, when present: the truth ``gt_disp_lowres.pfm`` in the ``source`` light-field folder;
    ``regions.npy`` (``(H, W)`` labels 0..3) or ``regions.png`` (labels, or the coloured picture) and
    ``window_size.npy`` in the result folder; ``scores``, ``method``, ``options``, ``seconds`` and
    ``provenance`` from ``result.json``. ``camera`` defaults to the folder's own (none: no metric
    depth). The 3D view shows ``ply`` (an exported PLY file) when given, else, with a camera, the
    points the export would keep (:func:`recon.export.trusted_pixels`).
    """
    from recon.lf.benchmark import GROUND_TRUTH
    from recon.lf.pfm import read_pfm

    folder = Path(result.path)
    record = result.record
    if camera is None:
        camera = record.camera
    shape = result.disparity_px.shape
    truth = None
    source = source_folder(folder, record)
    if source is not None and (source / GROUND_TRUTH).is_file():
        truth = read_pfm(source / GROUND_TRUTH)
        if truth.shape != shape:
            truth = None
    from recon.lf.imageio import read_npy

    regions = None
    if (folder / REGIONS_NPY).is_file():
        regions = read_npy(folder / REGIONS_NPY, error=ExportError)
        if regions.ndim != 2 or regions.dtype.kind not in "biu":
            raise ExportError(f"{folder / REGIONS_NPY}: holds {regions.dtype} values of shape {regions.shape}, "
                              "not (H, W) region labels; remove it or run lfrig reconstruct again")
    elif (folder / REGIONS_PNG).is_file():
        from recon.lf.imageio import read_image

        regions = read_image(folder / REGIONS_PNG)
    window = read_npy(folder / WINDOW_SIZE_NPY, error=ExportError) if (folder / WINDOW_SIZE_NPY).is_file() else None
    from recon.export import MIN_CONFIDENCE, trusted_pixels
    from recon.report.model import cloud_model, read_ply

    view = result.image
    if view is None:
        view = np.zeros(shape, np.uint8)
    info = {key: value for key, value in (("method", record.method), ("options", record.options),
                                          ("seconds", record.seconds), ("source", record.source)) if value}
    # the run's own scores only when the page cannot score against the truth itself
    extra = None if truth is not None else ({k: v for k, v in (record.scores or {}).items()
                                             if not isinstance(v, Mapping)} or None)
    model = None
    if ply is not None:
        model = read_ply(ply)
    elif camera is not None:
        keep = trusted_pixels(result.disparity_px, confidence=result.confidence, search_range=result.search_range)
        if result.mask is not None:
            keep &= result.mask
        model = cloud_model(camera.depth_mm(result.disparity_px.astype(np.float64)), focal_px=camera.focal_px,
                            principal_point_px=camera.principal_point_px, image=None if result.image is None else
                            as_rgb8(result.image), keep=keep, confidence=result.confidence,
                            name="the points lfrig export keeps (no PLY was exported with this report)")
    provenance = getattr(record, "provenance", None) or record.extra.get("provenance")
    return write_report(
        out_dir,
        centre_view=view,
        disparity_px=result.disparity_px,
        title=f"lfrig reconstruction: {source.name if source is not None else folder.name}",
        subtitle=str(folder.resolve()),
        truth_disparity_px=truth,
        camera=camera,
        region_map=regions if regions is not None and regions.shape[:2] == shape else None,
        window_size_px=window if window is not None and window.shape == shape else None,
        confidence=result.confidence,
        min_confidence=MIN_CONFIDENCE if result.confidence is not None else None,
        scores=extra,
        info=info or None,
        model=model,
        provenance=provenance if isinstance(provenance, Mapping) else None,
    )
