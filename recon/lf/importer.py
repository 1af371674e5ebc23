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
- the **4D Light Field Benchmark** layout (``input_CamNNN.png`` row-major, ``parameters.cfg``).

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
from typing import Any, Sequence

import numpy as np

from recon.errors import LightFieldFormatError
from recon.lf.capture import CaptureWriter, is_capture
from recon.lf.imageio import check_total_size, read_image, sha256_file
from recon.lf.lock import FolderLock, FolderLockedError
from recon.lf.params import MAX_GRID_SIDE, camera_problem, disparity_range_problem
from recon.progress import ProgressCallback, report

#: File suffixes taken as images when no pattern names the files (any case).
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".pnm")
ORDERS = ("serpentine", "raster")
_FIELD_ALIASES = {"u": "u", "row": "u", "v": "v", "col": "v", "i": "i"}
_SPEC = re.compile(r"^(0?\d{0,2})d?$")  # a width of at most 99 digits


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
        values = {written: int(m.group(k)) for k, written in enumerate(self.names, start=1)}
        if self.text.format(**values) != name:  # e.g. "img_1.png" against "img_{i:03d}.png"
            return None
        return {_FIELD_ALIASES[k]: v for k, v in values.items()}


def parse_pattern(text: str) -> ViewPattern:
    """Parse ``view_{u}_{v}.png``-style patterns; fields ``u``/``row``, ``v``/``col`` or ``i``, each
    optionally with an integer format such as ``:02d``.

    Raises
    ------
    ViewImportError
        A field other than those, a non-integer format, a field given twice, a folder in the pattern,
        or neither ``u`` and ``v`` nor ``i``.
    """
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
                f"pattern {text!r}: unknown field {{{name}}}; use {{u}} (or {{row}}) and {{v}} (or {{col}}), or {{i}} for a running index"
            )
        if conversion or not _SPEC.match(spec or ""):
            raise ViewImportError(f"pattern {text!r}: field {{{name}:{spec}}} must be a whole number of at most 99 "
                                  f"digits, e.g. {{{name}:02d}}")
        canonical = _FIELD_ALIASES[name]
        if canonical in fields:
            raise ViewImportError(f"pattern {text!r}: field {{{name}}} appears twice")
        fields.append(canonical)
        names.append(name)
        regex += r"(\d+)"
    if sorted(fields) not in (["u", "v"], ["i"]):
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
    _require_all(src, rows, cols, found, lambda u, v: pattern.text.format(
        **{name: (u if _FIELD_ALIASES[name] == "u" else v) + index_base for name in pattern.names}))
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
            names = ", ".join(pattern.text.format(**{pattern.names[0]: i + index_base}) for i in missing[:3])
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
        report(progress, 0.5 * (k + 1) / total, path.name)
    return images


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
    if not src.is_dir():
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
    parsed = parse_pattern(pattern) if pattern is not None else None
    benchmark = parsed is None and order is None and (src / "input_Cam000.png").is_file()
    if pitch_mm is None and not benchmark:
        raise ViewImportError("give the grid pitch with --pitch-mm: the distance between neighbouring views in mm")
    if parsed is not None and "u" in parsed.fields:
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
    _write(src, target, plan, images, camera, progress)
    return target


def _write(src: Path, target: Path, plan: ImportPlan, images: dict[tuple[int, int], np.ndarray],
           camera: dict[str, Any], progress: ProgressCallback | None) -> None:
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
    try:
        # Held until the capture is renamed into place: another import into the same target takes
        # this folder for a dead run's only when nobody holds its lock (remove_abandoned_imports).
        lock = FolderLock(tmp, what="import")
        with CaptureWriter(tmp, header=header, lock=lock) as writer:
            total = plan.rows * plan.cols
            for k, (u, v) in enumerate((u, v) for u in range(plan.rows) for v in range(plan.cols)):
                path = plan.files[(u, v)]
                writer.write_view(u, v, images[(u, v)], {"source": path.name, "source_sha256": _sha256(path)})
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
