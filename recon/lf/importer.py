"""Bring a folder of views written by another tool into lfrig's capture layout (``lfrig import``).

Three ways to say which file is which view (``docs/capture-format.md``, "Importing"):

- a **pattern** with row and column fields and the grid size, Python format syntax: ``view_{u}_{v}.png``,
  ``img_{v:02d}-{u:02d}.tif`` (``u``/``row`` is the grid row, ``v``/``col`` the column; see
  ``docs/conventions.md``). A file name matches when formatting the pattern with its numbers gives the
  name back exactly;
- files in **capture order** with ``order="serpentine"`` or ``"raster"`` and the grid size: the files
  of the folder sorted naturally (``img2`` before ``img10``), or those matching a pattern with an
  index field ``{i}`` sorted by it. Serpentine is lfrig's own scan: row by row, every other row
  right to left (:func:`capture_order`, the same as ``rig.grid.scan_order``);
- the **4D Light Field Benchmark** layout (``input_CamNNN.png`` row-major, ``parameters.cfg``); its
  ground truth (``gt_disp_lowres.pfm``, ``gt_depth_lowres.pfm``) is copied into the capture;
- one **mosaic** image holding every view in a ``rows x cols`` tiling (``mosaic=(rows, cols)``);
- an **HDF5** light field in the old HCI ``lf.h5`` layout (:func:`read_hdf5_lightfield`).

The Stanford archive's names (``out_RR_CC_<y>_<x>_.png``) are the preset pattern ``stanford``
(:data:`PATTERN_PRESETS`); the float fields ``{y}`` and ``{x}`` of a pattern match a position that is
not used for placing the view. The grid can then be transposed and flipped (``transpose``, ``flip_u``,
``flip_v``: in that order), and :func:`order_warnings` warns when the views' order looks mirrored.

Indices in names start at ``index_base`` (0 unless told). Pitch, focal length and principal point come
from the caller (the benchmark's ``parameters.cfg`` supplies them for that layout; the caller's
values override).

Nothing is written on bad input: every view is found, read and checked (present exactly once, same
size, colour and bit depth, 8- or 16-bit integers) before anything is written, and the first problem
is one :class:`ViewImportError` naming the file. The capture is then built in a temporary folder beside
the target and renamed into place at the end, so the target is either absent or complete. Its
journal records, for every view, the source file and its SHA-256 beside the written view's.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import string
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from recon.errors import LightFieldFormatError
from recon.lf.capture import CaptureWriter, is_capture
from recon.lf.benchmark import GROUND_TRUTH
from recon.lf.imageio import check_total_size, read_image, sha256_file
from recon.lf.lock import FolderLock, FolderLockedError
from recon.lf.params import MAX_GRID_SIDE, camera_problem, disparity_range_problem
from recon.lf.pfm import write_pfm
from recon.progress import ProgressCallback, report

#: File suffixes taken as images when no pattern names the files (any case).
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".pnm")
ORDERS = ("serpentine", "raster")
#: The benchmark's depth ground truth, copied with the disparity's when present.
GROUND_TRUTH_DEPTH = "gt_depth_lowres.pfm"
_FIELD_ALIASES = {"u": "u", "row": "u", "v": "v", "col": "v", "i": "i", "y": "y", "x": "x"}
_SPEC = re.compile(r"^(0?\d{0,2})d?$")  # a width of at most 99 digits
#: Position fields: a signed decimal number in the name that does not place the view.
_FLOAT_FIELDS = ("y", "x")
_FLOAT = r"([-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?)"
#: Named patterns accepted by ``--pattern``.
PATTERN_PRESETS = {"stanford": "out_{u:02d}_{v:02d}_{y}_{x}_.png"}


class ViewImportError(LightFieldFormatError):
    """The source folder cannot be imported as it is (the message names the file and what to do)."""


# --------------------------------------------------------------------------------------------------
# Which file is which view (pure)


@dataclass(frozen=True)
class ViewPattern:
    """A parsed file-name pattern: ``text`` in format syntax, the fields it holds (``u``, ``v`` or ``i``)."""

    text: str
    regex: re.Pattern[str]
    fields: tuple[str, ...]
    names: tuple[str, ...]  # the field names as written (``row``, ``u``...), in order

    def match(self, name: str) -> dict[str, int] | None:
        """``{"u": 3, "v": 5}`` (or ``{"i": 12}``) when ``name`` is this pattern's, else ``None``."""
        m = self.regex.fullmatch(name)
        if m is None:
            return None
        values = {written: (m.group(k) if written in _FLOAT_FIELDS else int(m.group(k)))
                  for k, written in enumerate(self.names, start=1)}
        if self.text.format(**values) != name:  # e.g. "img_1.png" against "img_{i:03d}.png"
            return None
        return {_FIELD_ALIASES[k]: v for k, v in values.items() if k not in _FLOAT_FIELDS}

    def name_of(self, **fields: int) -> str:
        """The name of the view with these ``u``/``v`` (or ``i``) numbers (float fields shown as ``*``)."""
        return self.text.format(**{name: ("*" if name in _FLOAT_FIELDS else fields[_FIELD_ALIASES[name]])
                                   for name in self.names})


def parse_pattern(text: str) -> ViewPattern:
    """Parse ``view_{u}_{v}.png``-style patterns; fields ``u``/``row``, ``v``/``col`` or ``i``, each
    optionally with an integer format such as ``:02d``, and the position fields ``{y}``, ``{x}`` (a
    signed decimal number, not used for placing). A name in :data:`PATTERN_PRESETS` stands for its pattern.

    Raises
    ------
    ViewImportError
        A field other than those, a non-integer format, a field given twice, a folder in the pattern,
        or neither ``u`` and ``v`` nor ``i``.
    """
    text = PATTERN_PRESETS.get(text, text)
    if "/" in text or os.sep in text:
        raise ViewImportError(f"pattern {text!r}: give a file name pattern without folders (the folder is SRC)")
    regex = ""
    fields: list[str] = []
    names: list[str] = []
    try:
        parsed = list(string.Formatter().parse(text))
    except ValueError as error:
        raise ViewImportError(f"pattern {text!r}: {error}; write fields as {{u}}, {{v:02d}} ...") from None
    for literal, name, spec, conversion in parsed:
        regex += re.escape(literal)
        if name is None:
            continue
        if name not in _FIELD_ALIASES:
            raise ViewImportError(
                f"pattern {text!r}: unknown field {{{name}}}; use {{u}} (or {{row}}) and {{v}} (or {{col}}), or {{i}} for a "
                f"running index ({{y}}, {{x}}: a position that is not used; presets: {', '.join(PATTERN_PRESETS)})"
            )
        if name in _FLOAT_FIELDS:
            if conversion or spec:
                raise ViewImportError(f"pattern {text!r}: the position field {{{name}}} takes no format; write {{{name}}}")
            if name in names:
                raise ViewImportError(f"pattern {text!r}: field {{{name}}} appears twice")
            names.append(name)
            regex += _FLOAT
            continue
        if conversion or not _SPEC.match(spec or ""):
            raise ViewImportError(f"pattern {text!r}: field {{{name}:{spec}}} must be a whole number of at most 99 "
                                  f"digits, e.g. {{{name}:02d}}")
        canonical = _FIELD_ALIASES[name]
        if canonical in fields:
            raise ViewImportError(f"pattern {text!r}: field {{{name}}} appears twice")
        fields.append(canonical)
        names.append(name)
        regex += r"(\d+)"
    if sorted(f for f in fields if f not in _FLOAT_FIELDS) not in (["u", "v"], ["i"]):
        raise ViewImportError(
            f"pattern {text!r}: needs both {{u}} and {{v}} (the view's row and column), or {{i}} (its place in "
            "capture order, with --order and the grid size)"
        )
    return ViewPattern(text, re.compile(regex), tuple(fields), tuple(names))


def capture_order(rows: int, cols: int, *, order: str = "serpentine") -> list[tuple[int, int]]:
    """Grid positions ``(u, v)`` in visiting order: row by row; ``serpentine`` reverses every other row
    (row 0 left to right, row 1 right to left, ...), as lfrig's own capture does."""
    if order not in ORDERS:
        raise ViewImportError(f"order {order!r}: choose one of {', '.join(ORDERS)}")
    views = []
    for u in range(rows):
        columns = range(cols) if order == "raster" or u % 2 == 0 else range(cols - 1, -1, -1)
        views.extend((u, v) for v in columns)
    return views


def _source_files(src: Path) -> list[Path]:
    """The files of ``src`` (not below it). A symbolic link is followed only to a file inside ``src``;
    one that leads out of it (``view.png -> /home/x/secret``) is an error naming it."""
    root = src.resolve()
    files = []
    for path in src.iterdir():
        if path.is_symlink():
            target = path.resolve()
            if not target.is_relative_to(root):
                raise ViewImportError(f"{path}: is a link to {target}, outside {src}; lfrig imports only files "
                                      "inside SRC: copy the file in, or remove the link")
        if path.is_file():
            files.append(path)
    return files


def _number_key(name: str) -> list[Any]:
    """:func:`natural_key` without the digits as written: ``img01`` and ``img1`` have the same."""
    return [(kind, number) if kind == 0 else (kind, text) for kind, number, text in natural_key(name)]


def natural_key(name: str) -> list[Any]:
    """Sort key that orders digit runs by value: ``img2.png`` before ``img10.png``."""
    return [(0, int(part), part) if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name)]


@dataclass
class ImportPlan:
    """The grid and which source file goes to each position, before anything is read."""

    rows: int
    cols: int
    files: dict[tuple[int, int], Path]
    how: dict[str, Any] = field(default_factory=dict)


def _require_grid(rows: int | None, cols: int | None) -> None:
    if rows is None or cols is None:
        raise ViewImportError(
            "give the grid size with --rows and --cols (file names alone cannot show a missing last row or column)"
        )
    for name, value in (("rows", rows), ("cols", cols)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)
                                  or not 1 <= value <= MAX_GRID_SIDE):
            raise ViewImportError(f"grid {name} must be a whole number from 1 to {MAX_GRID_SIDE}; got {value!r}")


def plan_by_position(src: Path, pattern: ViewPattern, *, rows: int, cols: int, index_base: int = 0) -> ImportPlan:
    """Place every file matching a ``{u}``/``{v}`` pattern by the numbers in its name."""
    _require_grid(rows, cols)
    found: dict[tuple[int, int], Path] = {}
    for path in sorted(_source_files(src), key=lambda p: natural_key(p.name)):
        values = pattern.match(path.name)
        if values is None:
            continue
        u, v = values["u"] - index_base, values["v"] - index_base
        if u < 0 or v < 0:
            raise ViewImportError(
                f"{path}: row {values['u']}, column {values['v']} is below the first index {index_base}; "
                "pass the index your names start at (--index-base)"
            )
        if (u, v) in found:
            raise ViewImportError(f"{path}: same grid position (u={u}, v={v}) as {found[(u, v)].name}; keep one of them")
        found[(u, v)] = path
    if not found:
        raise ViewImportError(f"{src}: no file matches the pattern {pattern.text!r}; check it against the names in the folder")
    outside = sorted((uv, p) for uv, p in found.items() if uv[0] >= rows or uv[1] >= cols)
    if outside:
        (u, v), path = outside[0]
        raise ViewImportError(
            f"{path}: grid position (u={u}, v={v}) is outside the {rows}x{cols} grid; remove it or give the grid size"
        )
    _require_all(src, rows, cols, found, lambda u, v: pattern.name_of(u=u + index_base, v=v + index_base))
    return ImportPlan(rows, cols, found, {"mode": "pattern", "pattern": pattern.text, "index_base": index_base})


def plan_by_order(
    src: Path, *, rows: int, cols: int, order: str, pattern: ViewPattern | None = None, index_base: int = 0
) -> ImportPlan:
    """Place the files in capture order: a ``{i}`` pattern's files by index, else every image file of
    the folder in natural name order."""
    _require_grid(rows, cols)
    positions = capture_order(rows, cols, order=order)
    if pattern is not None:
        indexed: dict[int, Path] = {}
        for path in _source_files(src):
            values = pattern.match(path.name)
            if values is None:
                continue
            i = values["i"] - index_base
            if i < 0:
                raise ViewImportError(f"{path}: index {values['i']} is below the first index {index_base}; pass --index-base")
            if i in indexed:
                raise ViewImportError(f"{path}: same index {values['i']} as {indexed[i].name}; keep one of them")
            indexed[i] = path
        if not indexed:
            raise ViewImportError(f"{src}: no file matches the pattern {pattern.text!r}; check it against the names in the folder")
        beyond = sorted(i for i in indexed if i >= len(positions))
        if beyond:
            raise ViewImportError(
                f"{indexed[beyond[0]]}: index {beyond[0] + index_base} is beyond the {rows}x{cols} grid "
                f"({len(positions)} views, indices {index_base} .. {len(positions) - 1 + index_base})"
            )
        missing = [i for i in range(len(positions)) if i not in indexed]
        if missing:
            names = ", ".join(pattern.name_of(i=i + index_base) for i in missing[:3])
            raise ViewImportError(f"{src}: {len(missing)} of {len(positions)} views missing ({names}{' ...' if len(missing) > 3 else ''})")
        files = [indexed[i] for i in range(len(positions))]
    else:
        files = sorted((p for p in _source_files(src) if p.suffix.lower() in IMAGE_SUFFIXES
                        and not p.name.startswith(".")), key=lambda p: natural_key(p.name))
        for before, after in zip(files, files[1:]):
            if _number_key(before.name) == _number_key(after.name):
                raise ViewImportError(
                    f"{after}: has the same numbers as {before.name} (written with other zero padding), so the "
                    "capture order is ambiguous; remove one of them, or name the files with --pattern"
                )
        if len(files) != len(positions):
            raise ViewImportError(
                f"{src}: {len(files)} image files, but a {rows}x{cols} grid has {len(positions)} views; "
                "remove the extra files or fix the grid size (or name the files with --pattern)"
            )
    how = {"mode": "order", "order": order, "index_base": index_base,
           "pattern": pattern.text if pattern is not None else None}
    return ImportPlan(rows, cols, dict(zip(positions, files)), how)


def _require_all(src: Path, rows: int, cols: int, found: dict[tuple[int, int], Path], name_of) -> None:
    missing = [(u, v) for u in range(rows) for v in range(cols) if (u, v) not in found]
    if missing:
        names = ", ".join(name_of(u, v) for u, v in missing[:3]) + (" ..." if len(missing) > 3 else "")
        raise ViewImportError(f"{src}: {len(missing)} of {rows * cols} views missing ({names})")


def reorient(plan: ImportPlan, images: dict[tuple[int, int], np.ndarray], *, transpose: bool = False,
             flip_u: bool = False, flip_v: bool = False) -> tuple[ImportPlan, dict[tuple[int, int], np.ndarray]]:
    """Move the views to other grid positions: ``transpose`` swaps rows and columns (a source row
    becomes a column), then ``flip_u`` reverses the rows and ``flip_v`` the columns. The views' pixels
    are not touched. Returns the new plan (its ``how`` records the three switches) and images."""
    rows, cols = (plan.cols, plan.rows) if transpose else (plan.rows, plan.cols)

    def place(u: int, v: int) -> tuple[int, int]:
        if transpose:
            u, v = v, u
        return (rows - 1 - u if flip_u else u, cols - 1 - v if flip_v else v)

    files = {place(*uv): path for uv, path in plan.files.items()}
    moved = {place(*uv): image for uv, image in images.items()}
    how = {**plan.how, "transpose": transpose, "flip_u": flip_u, "flip_v": flip_v}
    return ImportPlan(rows, cols, files, how), moved


def _grey(image: np.ndarray) -> np.ndarray:
    return (image.mean(axis=2) if image.ndim == 3 else image).astype(np.float32)


def order_warnings(views: dict[tuple[int, int], np.ndarray], *, rows: int, cols: int,
                   min_shift_px: float = 0.3) -> list[str]:
    """Warnings when the grid's order looks mirrored; empty when it looks consistent or cannot tell.

    In every row the last view is matched against the first by phase correlation (their dominant
    image shift along x, px), and in every column the last against the first (along y); divided by
    the number of view steps between them, each gives a coarse disparity per view step. In a
    consistent grid all rows agree in sign, all columns agree, and rows agree with columns (the grid
    pitch is the same along both). Rows that disagree mean the column order is reversed in some rows
    (serpentine files read as raster, or back); rows against columns mean one axis is mirrored. A
    shift below ``min_shift_px`` (a scene near the focus plane) says nothing and is not compared.

    ``views``: ``(u, v) -> (H, W[, C])`` images of a ``rows x cols`` grid.
    """
    import cv2

    greys: dict[tuple[int, int], np.ndarray] = {}

    def grey(uv: tuple[int, int]) -> np.ndarray:
        if uv not in greys:
            greys[uv] = _grey(views[uv])
        return greys[uv]

    window = cv2.createHanningWindow((grey((0, 0)).shape[1], grey((0, 0)).shape[0]), cv2.CV_32F)

    def slope(a: tuple[int, int], b: tuple[int, int], axis: int, steps: int) -> float | None:
        (dx, dy), _ = cv2.phaseCorrelate(grey(a), grey(b), window)
        shift = dx if axis == 1 else dy
        return shift / steps if abs(shift) >= min_shift_px else None

    by_row = {u: slope((u, 0), (u, cols - 1), 1, cols - 1) for u in range(rows)} if cols > 1 else {}
    by_col = {v: slope((0, v), (rows - 1, v), 0, rows - 1) for v in range(cols)} if rows > 1 else {}
    by_row = {k: x for k, x in by_row.items() if x is not None}
    by_col = {k: x for k, x in by_col.items() if x is not None}
    warnings = []
    for name, slopes, what in (("rows", by_row, "column order is reversed in some rows (files in serpentine "
                                 "order read as raster, or back?); check --order"),
                               ("columns", by_col, "row order is reversed in some columns")):
        signs = {k: x > 0 for k, x in slopes.items()}
        if len(set(signs.values())) > 1:
            minority = [k for k, sign in signs.items() if list(signs.values()).count(sign) <= len(signs) / 2]
            warnings.append(f"the {name} of the grid disagree in the sign of their disparity ({name} "
                            f"{', '.join(map(str, sorted(minority)[:5]))} against the others): the {what}")
    if not warnings and by_row and by_col:
        across, down = float(np.median(list(by_row.values()))), float(np.median(list(by_col.values())))
        if (across > 0) != (down > 0):
            warnings.append(f"the rows and the columns of the grid give disparities of opposite sign ({across:+.2f} "
                            f"and {down:+.2f} px per view step): one axis looks mirrored; import again with "
                            "--flip-v (or --flip-u)")
    return warnings


# --------------------------------------------------------------------------------------------------
# Reading and writing


def _read_checked(plan: ImportPlan, progress: ProgressCallback | None) -> dict[tuple[int, int], np.ndarray]:
    """Read every view, checking dtype and that all match the first (in grid order)."""
    images: dict[tuple[int, int], np.ndarray] = {}
    first: tuple[Path, np.ndarray] | None = None
    total = plan.rows * plan.cols
    for k, (u, v) in enumerate((u, v) for u in range(plan.rows) for v in range(plan.cols)):
        path = plan.files[(u, v)]
        image = read_image(path)
        if image.dtype not in (np.uint8, np.uint16):
            raise ViewImportError(
                f"{path}: {image.dtype} pixels; lfrig views are 8- or 16-bit integers: convert the file "
                "(e.g. scale float data to 16 bit)"
            )
        if first is None:
            first = (path, image)
            check_total_size(path.parent, total * image.nbytes)
        elif image.shape != first[1].shape or image.dtype != first[1].dtype:
            raise ViewImportError(
                f"{path}: image is {_describe(image)} but {first[0].name} is {_describe(first[1])}; "
                "all views must have the same size, colour and bit depth"
            )
        images[(u, v)] = image
        report(progress, 0.4 * (k + 1) / total, path.name)
    return images


def read_mosaic(path: Path, *, rows: int, cols: int) -> tuple[ImportPlan, dict[tuple[int, int], np.ndarray]]:
    """Cut one image holding every view, tiled ``rows x cols`` (view ``(u, v)`` at tile row ``u``,
    column ``v``), into its views. The image's size must be a whole multiple of the grid."""
    _require_grid(rows, cols)
    image = read_image(path)
    h, w = image.shape[:2]
    if h % rows or w % cols:
        raise ViewImportError(
            f"{path}: a {w}x{h} image cannot be cut into {rows}x{cols} equal views ({w}/{cols} or {h}/{rows} is not "
            "whole); check --mosaic ROWSxCOLS (rows first)"
        )
    th, tw = h // rows, w // cols
    views = {(u, v): np.ascontiguousarray(image[u * th:(u + 1) * th, v * tw:(v + 1) * tw])
             for u in range(rows) for v in range(cols)}
    plan = ImportPlan(rows, cols, {uv: path for uv in views}, {"mode": "mosaic", "mosaic": [rows, cols]})
    return plan, views


#: Names of the old HCI ``lf.h5`` layout: the views, and the ground truth when present.
H5_VIEWS, H5_DISPARITY, H5_DEPTH = "LF", "GT_DISP", "GT_DEPTH"


def read_hdf5_lightfield(path: Path) -> tuple[ImportPlan, dict[tuple[int, int], np.ndarray], dict[str, Any], np.ndarray | None]:
    """Read a light field in the old HCI ``lf.h5`` layout.

    Dataset ``LF`` of shape ``(U, V, H, W, 3)`` or ``(U, V, H, W)`` (8- or 16-bit integers, or floats in
    0..1, which are scaled to 16 bit); root attributes ``dH`` (distance between neighbouring views,
    taken as ``pitch_mm``), ``focalLength`` (px) and ``shift`` (px, the disparity offset ``d0`` of
    ``disparity = focal * dH / Z - shift``), each optional. Ground truth of the centre view from
    ``GT_DISP`` (disparity px) or else ``GT_DEPTH`` (depth in the units of ``dH``, converted with the
    formula), each ``(H, W)`` or ``(U, V, H, W)``.

    Returns the plan, the views, the camera values found and the ground-truth disparity (or ``None``).
    """
    import h5py

    try:
        file = h5py.File(path, "r")
    except OSError as error:
        raise ViewImportError(f"{path}: not a readable HDF5 file ({error}); pass an lf.h5 file or a folder of views") from None
    with file:
        data = file.get(H5_VIEWS)
        if not isinstance(data, h5py.Dataset) or data.ndim not in (4, 5) or (data.ndim == 5 and data.shape[4] != 3):
            raise ViewImportError(
                f"{path}: no dataset {H5_VIEWS!r} of shape (U, V, H, W, 3) or (U, V, H, W); "
                f"found {', '.join(f'{k} {getattr(v, "shape", "")}' for k, v in file.items()) or 'nothing'}"
            )
        lf = np.asarray(data[()])
        if lf.dtype.kind == "f":
            if not np.all(np.isfinite(lf)) or lf.min() < 0 or lf.max() > 1:
                raise ViewImportError(f"{path}: {H5_VIEWS} holds floats outside 0..1; scale them to 0..1 or to 8/16-bit integers")
            lf = np.round(lf * 65535).astype(np.uint16)
        elif lf.dtype not in (np.uint8, np.uint16):
            raise ViewImportError(f"{path}: {H5_VIEWS} holds {lf.dtype}; lfrig views are 8- or 16-bit integers")
        attrs = {k: file.attrs[k] for k in ("dH", "focalLength", "shift") if k in file.attrs}
        camera: dict[str, Any] = {}
        for key, name in (("dH", "pitch_mm"), ("focalLength", "focal_px"), ("shift", "disparity_offset")):
            if key in attrs:
                value = float(np.asarray(attrs[key]).ravel()[0])
                if not np.isfinite(value):
                    raise ViewImportError(f"{path}: attribute {key} is {value}; it must be a finite number")
                camera[name] = value
        rows, cols = lf.shape[:2]
        truth = None
        for name in (H5_DISPARITY, H5_DEPTH):
            if name in file:
                gt = np.asarray(file[name][()], dtype=np.float64)
                if gt.ndim == 4 and gt.shape[:2] == (rows, cols):
                    gt = gt[rows // 2, cols // 2]
                if gt.shape != lf.shape[2:4]:
                    raise ViewImportError(f"{path}: {name} has shape {gt.shape}; expected (H, W) = {lf.shape[2:4]} "
                                          "or (U, V, H, W)")
                if name == H5_DEPTH:
                    if "focal_px" not in camera or "pitch_mm" not in camera:
                        raise ViewImportError(f"{path}: {H5_DEPTH} needs the attributes dH and focalLength to become disparity")
                    with np.errstate(divide="ignore", invalid="ignore"):
                        gt = camera["focal_px"] * camera["pitch_mm"] / gt - camera.get("disparity_offset", 0.0)
                truth = gt.astype(np.float32)
                break
    views = {(u, v): np.ascontiguousarray(lf[u, v]) for u in range(rows) for v in range(cols)}
    plan = ImportPlan(rows, cols, {uv: path for uv in views}, {"mode": "hdf5"})
    return plan, views, camera, truth


def _describe(image: np.ndarray) -> str:
    h, w = image.shape[:2]
    return f"{w}x{h} {'RGB' if image.ndim == 3 else 'grey'} {image.dtype.itemsize * 8}-bit"


def _sha256(path: Path) -> str:
    return sha256_file(path, error=ViewImportError)


def _check_target(target: Path) -> None:
    if target.is_symlink():
        raise ViewImportError(f"{target}: is a symbolic link; give the new capture folder itself (lfrig does not "
                              "write through links)")
    if is_capture(target) or (target.exists() and (not target.is_dir() or any(target.iterdir()))):
        raise ViewImportError(f"{target}: exists and is not empty; choose a new folder for the imported capture")
    if not target.parent.is_dir():
        raise ViewImportError(f"{target.parent}: no such folder; create it first")


def import_views(
    src: str | os.PathLike,
    target: str | os.PathLike,
    *,
    pattern: str | None = None,
    order: str | None = None,
    rows: int | None = None,
    cols: int | None = None,
    index_base: int = 0,
    pitch_mm: float | None = None,
    focal_px: float | None = None,
    principal_point_px: tuple[float, float] | None = None,
    disparity_range: tuple[float, float] | None = None,
    mosaic: tuple[int, int] | None = None,
    transpose: bool = False,
    flip_u: bool = False,
    flip_v: bool = False,
    check_order: bool = True,
    warn: Callable[[str], None] | None = None,
    progress: ProgressCallback | None = None,
) -> Path:
    """Import the views in folder ``src`` as a complete lfrig capture at ``target`` (see the module docstring).

    Parameters
    ----------
    pattern
        File-name pattern with ``{u}``/``{v}`` (position by name) or ``{i}`` (with ``order``).
    order
        ``"serpentine"`` or ``"raster"``: the files are in capture order (needs ``rows`` and ``cols``).
    rows, cols
        Grid size (required, except for a benchmark folder, where it is checked when given).
    index_base
        The number the names' indices start at (0 or 1, usually).
    pitch_mm
        Distance between neighbouring views in mm (required, except for a benchmark folder whose
        ``parameters.cfg`` has ``baseline_mm``).
    focal_px, principal_point_px
        Focal length in pixels and ``(cx, cy)`` of the views, when known.
    disparity_range
        ``(min, max)`` disparity in pixels per view step the scene spans, when known.
    mosaic
        ``(rows, cols)``: ``src`` is one image holding every view (:func:`read_mosaic`).
    transpose, flip_u, flip_v
        Swap the grid's rows and columns, then reverse its rows, its columns (:func:`reorient`).
    check_order, warn
        Run :func:`order_warnings` on the placed views and pass each warning to ``warn``.

    An ``src`` ending in ``.h5``/``.hdf5`` is read by :func:`read_hdf5_lightfield`.

    Returns
    -------
    Path
        ``target``, now a complete capture folder.

    Raises
    ------
    ViewImportError, LightFieldFormatError
        Bad input, naming the file; nothing is written.
    """
    src, target = Path(src), Path(target)
    hdf5 = src.suffix.lower() in (".h5", ".hdf5")
    if mosaic is not None or hdf5:
        if not src.is_file():
            raise ViewImportError(f"{src}: no such file")
        if pattern is not None or order is not None:
            raise ViewImportError(f"{src}: one file holds every view; --pattern and --order are for folders of views")
    elif not src.is_dir():
        raise ViewImportError(f"{src}: no such folder")
    _check_target(target)
    if isinstance(index_base, bool) or not isinstance(index_base, int) or index_base < 0:
        raise ViewImportError(f"--index-base must be a whole number >= 0; got {index_base!r}")
    _require_grid(rows if rows is not None else 1, cols if cols is not None else 1)
    problem = camera_problem(focal_px=focal_px, pitch_mm=pitch_mm, principal_point_px=principal_point_px)
    if problem is not None:
        raise ViewImportError(f"{problem}; give the view's real camera")
    if disparity_range is not None:
        problem = disparity_range_problem(disparity_range, grid=(1, 1), image_shape=(1, 1))  # the numbers alone
        if problem is not None:
            raise ViewImportError(f"{problem} (pixels per view step)")
    camera: dict[str, Any] = {}
    truth: dict[str, Path | np.ndarray] = {}
    parsed = parse_pattern(pattern) if pattern is not None else None
    benchmark = not hdf5 and mosaic is None and parsed is None and order is None and (src / "input_Cam000.png").is_file()
    if pitch_mm is None and not benchmark and not hdf5:
        raise ViewImportError("give the grid pitch with --pitch-mm: the distance between neighbouring views in mm")
    if hdf5:
        plan, images, camera, gt = read_hdf5_lightfield(src)
        if (rows is not None or cols is not None) and (rows, cols) != (plan.rows, plan.cols):
            raise ViewImportError(f"{src}: the file holds a {plan.rows}x{plan.cols} grid, not {rows}x{cols}")
        if gt is not None:
            truth[GROUND_TRUTH] = gt
        report(progress, 0.3, src.name)
    elif mosaic is not None:
        if (rows is not None and rows != mosaic[0]) or (cols is not None and cols != mosaic[1]):
            raise ViewImportError(f"--mosaic {mosaic[0]}x{mosaic[1]} and --rows/--cols {rows}x{cols} disagree; give one of them")
        plan, images = read_mosaic(src, rows=mosaic[0], cols=mosaic[1])
        report(progress, 0.3, src.name)
    elif parsed is not None and "u" in parsed.fields:
        if order is not None:
            raise ViewImportError(
                f"pattern {pattern!r} places each view by its row and column; --order is for files in capture order"
            )
        plan = plan_by_position(src, parsed, rows=rows, cols=cols, index_base=index_base)
        images = _read_checked(plan, progress)
    elif order is not None:
        plan = plan_by_order(src, rows=rows, cols=cols, order=order, pattern=parsed, index_base=index_base)  # type: ignore[arg-type]
        images = _read_checked(plan, progress)
    elif parsed is not None:
        raise ViewImportError(f"pattern {pattern!r} numbers the views in capture order: give --order serpentine|raster and the grid size")
    elif benchmark:
        from recon.lf.benchmark import read_benchmark

        _source_files(src)  # a view, truth or parameters file linked from outside SRC is refused, as in the other layouts
        lf = read_benchmark(src)
        if rows is not None or cols is not None:
            if (rows, cols) != lf.grid_shape:
                raise ViewImportError(
                    f"{src}: the benchmark folder holds a {lf.grid_shape[0]}x{lf.grid_shape[1]} grid, not {rows}x{cols}"
                )
        plan = ImportPlan(*lf.grid_shape, {(u, v): src / f"input_Cam{u * lf.grid_shape[1] + v:03d}.png"
                                           for u in range(lf.grid_shape[0]) for v in range(lf.grid_shape[1])},
                          {"mode": "benchmark"})
        images = {(u, v): lf.views[u, v] for u in range(plan.rows) for v in range(plan.cols)}
        if lf.views.dtype not in (np.uint8, np.uint16):
            raise ViewImportError(f"{src}: views are {lf.views.dtype}; lfrig views are 8- or 16-bit integers")
        camera = {"pitch_mm": lf.pitch_mm, "focal_px": lf.focal_px, "principal_point_px": lf.principal_point_px,
                  "disparity_range": lf.disparity_range, "disparity_offset": lf.disparity_offset}
        truth = {name: src / name for name in (GROUND_TRUTH, GROUND_TRUTH_DEPTH) if (src / name).is_file()}
    else:
        raise ViewImportError(
            f"{src}: say which file is which view: --pattern 'view_{{u}}_{{v}}.png' (row and column in the name), "
            "--order serpentine|raster with --rows and --cols (files in capture order), or a folder in the "
            "benchmark's layout (input_Cam000.png ...)"
        )
    overrides = {"pitch_mm": pitch_mm, "focal_px": focal_px, "principal_point_px": principal_point_px,
                 "disparity_range": disparity_range}
    camera.update({k: v for k, v in overrides.items() if v is not None})
    if camera.get("pitch_mm") is None:
        raise ViewImportError("give the grid pitch with --pitch-mm: the distance between neighbouring views in mm")
    shape = next(iter(images.values())).shape[:2]
    if camera.get("disparity_range") is not None:
        problem = disparity_range_problem(camera["disparity_range"], grid=(plan.rows, plan.cols), image_shape=shape)
        if problem is not None:
            raise ViewImportError(f"{problem} (pixels per view step)")
    if principal_point_px is not None:
        cx, cy = principal_point_px
        if not (0 <= cx <= shape[1] - 1 and 0 <= cy <= shape[0] - 1):
            raise ViewImportError(
                f"principal point ({cx}, {cy}) px lies outside the {shape[1]}x{shape[0]} views; give (cx, cy), x first"
            )
    if transpose or flip_u or flip_v:
        moves_centre = (flip_u and plan.rows % 2 == 0) or (flip_v and plan.cols % 2 == 0)
        if truth and (transpose or moves_centre):
            raise ViewImportError(f"{src}: the ground truth belongs to the centre view as the source orders the grid; "
                                  "--transpose, or a flip of an even grid side, would not keep it true: import without them")
        plan, images = reorient(plan, images, transpose=transpose, flip_u=flip_u, flip_v=flip_v)
    if check_order:
        report(progress, 0.4, "checking the order")
        for text in order_warnings(images, rows=plan.rows, cols=plan.cols):
            if warn is not None:
                warn(f"{src}: {text}")
        report(progress, 0.5, "order checked")
    _write(src, target, plan, images, camera, progress, truth)
    return target


def _write(src: Path, target: Path, plan: ImportPlan, images: dict[tuple[int, int], np.ndarray],
           camera: dict[str, Any], progress: ProgressCallback | None,
           truth: dict[str, Path | np.ndarray] | None = None) -> None:
    """Build the capture in a temporary folder beside ``target``, then rename it into place."""
    grid = {"rows": plan.rows, "cols": plan.cols, "pitch_mm": float(camera["pitch_mm"])}
    how = {**plan.how, "source": str(src.resolve())}
    header = {"grid": grid, "settings": {"grid": grid, "import": how}, "imported": how}
    remove_abandoned_imports(target)
    tmp = target.parent / f".{target.name}.import-{os.getpid()}.tmp"
    if tmp.is_symlink() or tmp.is_file():
        tmp.unlink()
    elif tmp.exists():
        shutil.rmtree(tmp)
    lock = None
    digests: dict[Path, str] = {}
    try:
        # Held until the capture is renamed into place: another import into the same target takes
        # this folder for a dead run's only when nobody holds its lock (remove_abandoned_imports).
        lock = FolderLock(tmp, what="import")
        with CaptureWriter(tmp, header=header, lock=lock) as writer:
            for name, gt in (truth or {}).items():
                if isinstance(gt, Path):
                    shutil.copyfile(gt, tmp / name)
                else:
                    write_pfm(tmp / name, gt)
            total = plan.rows * plan.cols
            for k, (u, v) in enumerate((u, v) for u in range(plan.rows) for v in range(plan.cols)):
                path = plan.files[(u, v)]
                if path not in digests:
                    digests[path] = _sha256(path)
                writer.write_view(u, v, images[(u, v)], {"source": path.name, "source_sha256": digests[path]})
                report(progress, 0.5 + 0.5 * (k + 1) / total, f"u{u:02d} v{v:02d}")
            writer.write_parameters(
                image_shape=next(iter(images.values())).shape[:2],
                pitch_mm=grid["pitch_mm"],
                focal_px=camera.get("focal_px"),
                principal_point_px=camera.get("principal_point_px"),
                disparity_range=camera.get("disparity_range"),
                disparity_offset=camera.get("disparity_offset") or 0.0,
            )
            writer.mark_complete()
        try:
            if target.is_dir() and not target.is_symlink():
                target.rmdir()  # checked empty above; an empty folder the user made for it
            os.rename(tmp, target)
        except OSError as error:
            if error.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR, errno.EISDIR):
                raise
            raise ViewImportError(
                f"{target}: was filled by another process while this import ran (another `lfrig import` into the "
                "same folder?); nothing of this import was kept: choose a new folder, or run it again"
            ) from None
        fd = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if lock is not None:
            lock.release()


_IMPORT_TMP = re.compile(r"\.(?P<name>.+)\.import-\d+\.tmp")


def remove_abandoned_imports(target: Path) -> list[Path]:
    """Remove the temporary folders (``.NAME.import-PID.tmp``) of imports into ``target`` that ended
    without finishing (killed, or stopped by a power cut): a folder whose lock (the capture writer's,
    :mod:`recon.lf.lock`) nobody holds. Returns what was removed."""
    removed: list[Path] = []
    parent = target.parent if str(target.parent) else Path(".")
    try:
        entries = list(os.scandir(parent))
    except OSError:
        return removed
    for entry in entries:
        match = _IMPORT_TMP.fullmatch(entry.name)
        if match is None or match["name"] != target.name or not entry.is_dir(follow_symlinks=False):
            continue
        try:
            with FolderLock(entry.path, what="import"):
                shutil.rmtree(entry.path)
        except (FolderLockedError, LightFieldFormatError, OSError):
            continue  # a running import's, or not ours to judge
        removed.append(Path(entry.path))
    return removed


__all__: Sequence[str] = ["ImportPlan", "ViewImportError", "capture_order", "import_views", "natural_key", "parse_pattern",
                          "remove_abandoned_imports"]
