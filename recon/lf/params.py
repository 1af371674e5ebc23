"""``parameters.cfg``: the 4D Light Field Benchmark's scene description, read and written.

The file is INI-style with the sections ``[intrinsics]`` (``focal_length_mm``, ``sensor_size_mm``,
``image_resolution_x_px``, ``image_resolution_y_px``, ...), ``[extrinsics]`` (``num_cams_x``,
``num_cams_y``, ``baseline_mm``, ``focus_distance_m``, ...) and ``[meta]`` (``disp_min``,
``disp_max``, ...). lfrig writes the same sections for its own captures, so that other tools can
read them, plus an ``[lfrig]`` section with what the benchmark has no key for (``focal_px``,
``disparity_offset_px``, ``principal_x_px``, ``principal_y_px``). :func:`parameters_for` writes the
sections for a light field and :func:`camera_from_parameters` reads them back: one inverse pair.
"""

from __future__ import annotations

import configparser
import math
import os
from pathlib import Path
from typing import Any

from recon.errors import LightFieldFormatError

Parameters = dict[str, dict[str, Any]]


def _value(text: str) -> Any:
    text = text.strip()
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def read_parameters(path: str | os.PathLike) -> Parameters:
    """Read a ``parameters.cfg`` into ``{section: {key: value}}`` with numbers converted.

    Raises
    ------
    LightFieldFormatError
        When the file cannot be parsed, naming the file and the line.
    """
    path = Path(path)
    parser = configparser.ConfigParser(interpolation=None)
    from recon.lf.imageio import read_bytes

    data = read_bytes(path, max_bytes=1 << 20)  # a scene description is a few hundred bytes
    try:
        parser.read_string(data.decode("utf-8"), source=str(path))
    except (configparser.Error, UnicodeDecodeError) as error:
        detail = str(error).splitlines()[0]
        raise LightFieldFormatError(f"{path}: not a valid parameters.cfg ({detail})") from None
    return {section: {k: _value(v) for k, v in parser[section].items()} for section in parser.sections()}


def write_parameters(path: str | os.PathLike, parameters: Parameters) -> None:
    """Write ``{section: {key: value}}`` as a ``parameters.cfg`` (atomically)."""
    path = Path(path)
    lines: list[str] = []
    for section, values in parameters.items():
        lines.append(f"[{section}]")
        lines.extend(f"{key} = {value}" for key, value in values.items())
        lines.append("")
    from recon.lf.imageio import write_bytes_atomic

    write_bytes_atomic(path, "\n".join(lines).encode("utf-8"))


#: The most views per grid side a light field may declare (``num_cams_x``, ``num_cams_y``, a capture's
#: grid): far beyond any rig, small enough that a typo cannot make lfrig allocate for millions of views.
MAX_GRID_SIDE = 1024


def is_finite(value: int | float) -> bool:
    """``math.isfinite`` that says False for an integer too large for a float (instead of raising)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _number(parameters: Parameters, section: str, key: str, path: Path, *, positive: bool = False) -> float | None:
    value = parameters.get(section, {}).get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not is_finite(value):
        raise LightFieldFormatError(f"{path}: [{section}] {key} = {value!r} is not a finite number")
    if positive and not value > 0:
        raise LightFieldFormatError(f"{path}: [{section}] {key} = {value!r} must be positive; fix or remove the line")
    return float(value)


def benchmark_focal_px(*, focal_length_mm: float, sensor_size_mm: float, width_px: float, height_px: float) -> float:
    """The benchmark's focal length in pixels: ``focal_length_mm / sensor_size_mm * max(W, H)``."""
    return focal_length_mm / sensor_size_mm * max(width_px, height_px)


def focus_disparity_px(*, focal_px: float, pitch_mm: float, focus_distance_m: float) -> float:
    """``d0``: the disparity (pixels per view step) of the focus plane, which the benchmark's refocused
    views map to 0: ``focal_px * pitch_mm / (1000 * focus_distance_m)``."""
    return focal_px * pitch_mm / (1000.0 * focus_distance_m)


def camera_from_parameters(parameters: Parameters, *, path: Path) -> tuple[tuple[int, int] | None, dict[str, Any]]:
    """What lfrig needs from a ``parameters.cfg``: grid, pitch, focal length, disparity range.

    Returns ``(num_cams, camera)``: the grid ``(rows, cols)`` or ``None``, and the keyword arguments
    of :class:`recon.lf.lightfield.LightField` that the file fixes: ``pitch_mm``, ``focal_px``,
    ``disparity_offset`` (pixels per view step, 0 when unknown), ``disparity_range`` and
    ``principal_point_px`` (each may be ``None``).
    The benchmark's focal length in pixels is :func:`benchmark_focal_px` and its views are refocused
    at ``focus_distance_m``, so ``d0`` is :func:`focus_disparity_px`.
    """
    pitch_mm = _number(parameters, "extrinsics", "baseline_mm", path, positive=True)
    focal_px = _number(parameters, "lfrig", "focal_px", path, positive=True)
    if focal_px is None:
        focal_mm = _number(parameters, "intrinsics", "focal_length_mm", path, positive=True)
        sensor_mm = _number(parameters, "intrinsics", "sensor_size_mm", path, positive=True)
        res_x = _number(parameters, "intrinsics", "image_resolution_x_px", path, positive=True)
        res_y = _number(parameters, "intrinsics", "image_resolution_y_px", path, positive=True)
        if None not in (focal_mm, sensor_mm, res_x, res_y) and sensor_mm > 0:
            focal_px = benchmark_focal_px(focal_length_mm=focal_mm, sensor_size_mm=sensor_mm, width_px=res_x, height_px=res_y)
    offset = _number(parameters, "lfrig", "disparity_offset_px", path)
    focus_m = _number(parameters, "extrinsics", "focus_distance_m", path, positive=True)
    if offset is None:
        offset = 0.0
        if focus_m and focal_px and pitch_mm and "lfrig" not in parameters:
            offset = focus_disparity_px(focal_px=focal_px, pitch_mm=pitch_mm, focus_distance_m=focus_m)
    cx = _number(parameters, "lfrig", "principal_x_px", path)
    cy = _number(parameters, "lfrig", "principal_y_px", path)
    d_min = _number(parameters, "meta", "disp_min", path)
    d_max = _number(parameters, "meta", "disp_max", path)
    if d_min is not None and d_max is not None and not d_min < d_max:
        raise LightFieldFormatError(f"{path}: [meta] disp_min = {d_min} must be less than disp_max = {d_max}")
    rows = parameters.get("extrinsics", {}).get("num_cams_y")
    cols = parameters.get("extrinsics", {}).get("num_cams_x")
    num_cams = None
    if rows is not None or cols is not None:
        if not (isinstance(rows, int) and isinstance(cols, int) and 0 < rows <= MAX_GRID_SIDE
                and 0 < cols <= MAX_GRID_SIDE):
            raise LightFieldFormatError(
                f"{path}: [extrinsics] num_cams_x = {cols!r}, num_cams_y = {rows!r} must be integers "
                f"from 1 to {MAX_GRID_SIDE}"
            )
        num_cams = (rows, cols)
    return num_cams, {
        "pitch_mm": pitch_mm,
        "focal_px": focal_px,
        "disparity_offset": offset,
        "disparity_range": (d_min, d_max) if d_min is not None and d_max is not None else None,
        "principal_point_px": (cx, cy) if cx is not None and cy is not None else None,
    }


#: Bounds of a camera that lfrig accepts anywhere (``parameters.cfg``, flags, ``result.json``,
#: :class:`recon.camera.Camera`): anything outside is a typo or a damaged file, and would put points
#: at absurd distances (a pitch of 1e-320 mm, a focal length of 1e300 px).
FOCAL_PX_RANGE = (1.0, 1e7)
PITCH_MM_RANGE = (1e-6, 1e6)
#: The largest refocusing shift ``d0`` (pixels per view step) and principal point coordinate (pixels).
MAX_DISPARITY_OFFSET_PX = 1e6
MAX_PRINCIPAL_POINT_PX = 1e7


def camera_problem(*, focal_px: float | None = None, pitch_mm: float | None = None,
                   disparity_offset: float | None = None,
                   principal_point_px: tuple[float, float] | None = None) -> str | None:
    """What is wrong with these camera values (non-finite, or outside the bounds above), or ``None``.

    ``None`` values are not checked. The message names the value and the range it must lie in.
    """
    def bad(value: Any) -> bool:
        return isinstance(value, bool) or not isinstance(value, (int, float)) or not is_finite(value)

    for name, value, (low, high), unit in (("focal_px", focal_px, FOCAL_PX_RANGE, "px"),
                                           ("pitch_mm", pitch_mm, PITCH_MM_RANGE, "mm")):
        if value is not None and (bad(value) or not low <= value <= high):
            return f"{name} = {value!r} must be a number from {low:g} to {high:g} {unit}"
    if disparity_offset is not None and (bad(disparity_offset) or abs(disparity_offset) > MAX_DISPARITY_OFFSET_PX):
        return (f"disparity_offset (d0) = {disparity_offset!r} must be a number from {-MAX_DISPARITY_OFFSET_PX:g} to "
                f"{MAX_DISPARITY_OFFSET_PX:g} pixels per view step")
    if principal_point_px is not None:
        if (not isinstance(principal_point_px, (tuple, list)) or len(principal_point_px) != 2
                or any(bad(c) or abs(c) > MAX_PRINCIPAL_POINT_PX for c in principal_point_px)):
            return (f"principal_point_px {principal_point_px!r} must be two numbers (cx, cy) within "
                    f"+-{MAX_PRINCIPAL_POINT_PX:g} px")
    return None


def max_disparity_px(grid: tuple[int, int], image_shape: tuple[int, int]) -> float:
    """The largest ``|d|`` (pixels per view step) a light field can show: the farthest view from the
    centre, ``k`` steps away along an axis, sees a point shifted by ``k * |d|`` pixels, which must stay
    within the image's size along that axis. ``inf`` for a single view."""
    rows, cols = grid
    height, width = image_shape
    limits = []
    for count, size in ((rows, height), (cols, width)):
        steps = max(count // 2, count - 1 - count // 2)
        if steps > 0:
            limits.append(size / steps)
    return min(limits) if limits else math.inf


def disparity_range_problem(disparity_range: Any, *, grid: tuple[int, int],
                            image_shape: tuple[int, int]) -> str | None:
    """What is wrong with a disparity range ``(min, max)`` for this light field, or ``None``: not two
    finite numbers with ``min < max``, or beyond :func:`max_disparity_px` (a range that wide would
    ask for more candidates than the image can tell apart, and memory for all of them)."""
    try:
        low, high = disparity_range
    except (TypeError, ValueError):
        return f"disparity range {disparity_range!r} must be two numbers, MIN and MAX"
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not is_finite(v) for v in (low, high)):
        return f"disparity range ({low!r}, {high!r}) must be two finite numbers"
    if not low < high:
        return f"disparity range ({low:g}, {high:g}): MIN must be less than MAX"
    limit = max_disparity_px(grid, image_shape)
    if max(abs(low), abs(high)) > limit:
        return (f"disparity range ({low:g}, {high:g}) goes beyond +-{limit:.4g} pixels per view step, where the "
                f"outer views of the {grid[0]}x{grid[1]} grid would be shifted out of the "
                f"{image_shape[1]}x{image_shape[0]} image; give a range within it")
    return None


def check_camera_fits(camera: dict[str, Any], parameters: Parameters, *, grid: tuple[int, int],
                      image_shape: tuple[int, int], path: Path) -> None:
    """Check what :func:`camera_from_parameters` found against the views it describes: the
    resolution keys equal the views' size, the camera's values lie within lfrig's bounds, and the
    disparity range stays within the image (:func:`disparity_range_problem`).

    Raises
    ------
    LightFieldFormatError
        Naming ``path`` and the value.
    """
    height, width = image_shape
    intrinsics = parameters.get("intrinsics", {})
    for key, size in (("image_resolution_x_px", width), ("image_resolution_y_px", height)):
        value = intrinsics.get(key)
        if value is not None and value != size:
            raise LightFieldFormatError(f"{path}: [intrinsics] {key} = {value!r}, but the views are {width}x{height} "
                                        "pixels; fix the line or remove it")
    problem = camera_problem(focal_px=camera.get("focal_px"), pitch_mm=camera.get("pitch_mm"),
                             disparity_offset=camera.get("disparity_offset"),
                             principal_point_px=camera.get("principal_point_px"))
    if problem is None and camera.get("disparity_range") is not None:
        problem = disparity_range_problem(camera["disparity_range"], grid=grid, image_shape=image_shape)
    if problem is not None:
        raise LightFieldFormatError(f"{path}: {problem}; fix parameters.cfg")


def parameters_for(
    *,
    grid: tuple[int, int],
    image_shape: tuple[int, int],
    pitch_mm: float | None,
    focal_px: float | None = None,
    focal_length_mm: float | None = None,
    sensor_size_mm: float | None = None,
    disparity_range: tuple[float, float] | None = None,
    disparity_offset: float = 0.0,
    principal_point_px: tuple[float, float] | None = None,
) -> dict[str, dict[str, Any]]:
    """The ``parameters.cfg`` sections describing a light field: the inverse of :func:`camera_from_parameters`.

    ``camera_from_parameters(parameters_for(grid=g, image_shape=s, **camera))`` gives back ``g`` and
    ``camera`` (a test checks the round trip).
    """
    height, width = image_shape
    intrinsics: dict[str, Any] = {"image_resolution_x_px": width, "image_resolution_y_px": height}
    if focal_px is not None:
        # The benchmark derives focal_px = focal_length_mm / sensor_size_mm * max(W, H); pick a
        # consistent pair when only focal_px is known.
        if focal_length_mm is None or sensor_size_mm is None:
            focal_length_mm, sensor_size_mm = focal_px / max(width, height), 1.0
    if focal_length_mm is not None and sensor_size_mm is not None:
        intrinsics.update(focal_length_mm=focal_length_mm, sensor_size_mm=sensor_size_mm)
    sections: dict[str, dict[str, Any]] = {
        "intrinsics": intrinsics,
        "extrinsics": {"num_cams_x": grid[1], "num_cams_y": grid[0]},
    }
    if pitch_mm is not None:  # unknown pitch: no line, rather than a baseline of 0
        sections["extrinsics"]["baseline_mm"] = pitch_mm
    if disparity_range is not None:
        sections["meta"] = {"disp_min": disparity_range[0], "disp_max": disparity_range[1]}
    lfrig: dict[str, Any] = {"disparity_offset_px": disparity_offset}
    if focal_px is not None:
        lfrig["focal_px"] = focal_px
    if principal_point_px is not None:
        lfrig["principal_x_px"], lfrig["principal_y_px"] = (float(c) for c in principal_point_px)
    sections["lfrig"] = lfrig
    return sections
