"""lfrig's capture layout on disk: write a capture view by view, resume it, read it back.

A capture folder holds::

    manifest.jsonl      append-only journal: a header line, then one line per written view
    views/uUU_vVV.png   one image per grid position, named by position (never by capture order)
    parameters.cfg      the scene description in the 4D Light Field Benchmark's format
    session.log         a human-readable log (written by the capture session)

Each view is written atomically (temporary file, fsync, rename) and only then journalled, so the
journal never names a view that is not completely on disk. A view file that is on disk but not in
the journal (the process died between the two steps) is taken again on resume. See
``docs/capture-format.md`` for the full description.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from recon.lf.imageio import read_images, write_png
from recon.lf.lightfield import LightField
from recon.errors import CaptureLayoutError
from recon.lf.params import MAX_GRID_SIDE, camera_from_parameters, is_finite, parameters_for, read_parameters, write_parameters

FORMAT = "lfrig-capture"
VERSION = 1
MANIFEST = "manifest.jsonl"
VIEWS = "views"
PARAMETERS = "parameters.cfg"
_VIEW_NAME = re.compile(r"^u(\d+)_v(\d+)\.png$")


def view_name(u: int, v: int) -> str:
    """File name of the view at grid row ``u``, column ``v`` (relative to the capture folder)."""
    return f"{VIEWS}/u{u:02d}_v{v:02d}.png"


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def is_capture(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder in lfrig's capture layout (it has a manifest)."""
    return (Path(path) / MANIFEST).is_file()


def _read_journal(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The header and the remaining records of a manifest. A torn last line (a crash mid-append) is
    ignored; any other unreadable line is an error."""
    manifest = path / MANIFEST
    try:
        lines = manifest.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise CaptureLayoutError(f"{manifest}: no such file; {path} is not an lfrig capture") from None
    except UnicodeDecodeError as error:
        line = manifest.read_bytes()[: error.start].count(b"\n") + 1
        raise CaptureLayoutError(f"{manifest}: line {line} is not UTF-8 text; the journal is damaged") from None
    except OSError as error:
        raise CaptureLayoutError(f"{manifest}: cannot read ({error.strerror})") from None
    records: list[dict[str, Any]] = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            if number == len(lines):
                break  # torn final append: the view it named is taken again
            raise CaptureLayoutError(f"{manifest}: line {number} is not valid JSON; the journal is damaged") from None
        if not isinstance(record, dict):
            raise CaptureLayoutError(f"{manifest}: line {number} is not a JSON object")
        if record.get("kind") == "view":
            _check_view_record(record, where=f"{manifest}: line {number}")
        records.append(record)
    if not records or records[0].get("kind") != "header" or records[0].get("format") != FORMAT:
        raise CaptureLayoutError(f"{manifest}: the first line is not an {FORMAT} header")
    header = records[0]
    if header.get("version") != VERSION:
        raise CaptureLayoutError(
            f"{manifest}: capture format version {header.get('version')!r}; this lfrig reads version {VERSION}"
        )
    grid = header.get("grid")
    if not (isinstance(grid, dict) and _is_int(grid.get("rows")) and _is_int(grid.get("cols"))
            and 0 < grid["rows"] <= MAX_GRID_SIDE and 0 < grid["cols"] <= MAX_GRID_SIDE):
        raise CaptureLayoutError(
            f"{manifest}: header has no valid grid (rows and cols must be integers from 1 to {MAX_GRID_SIDE})")
    pitch = grid.get("pitch_mm")
    if pitch is not None and not (isinstance(pitch, (int, float)) and not isinstance(pitch, bool)
                                  and is_finite(pitch) and pitch > 0):
        raise CaptureLayoutError(f"{manifest}: header grid pitch_mm = {pitch!r} must be a positive number of mm")
    if not isinstance(header.get("settings", {}), dict):
        raise CaptureLayoutError(f"{manifest}: header settings must be a JSON object")
    return header, records[1:]


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_view_record(record: dict[str, Any], *, where: str) -> None:
    """A view record's fields have their types: ``u``, ``v`` integers >= 0, ``file`` and ``sha256``
    strings. (Whether ``u``, ``v`` lie in the grid and the file matches is checked by the callers.)"""
    for key in ("u", "v"):
        if not (_is_int(record.get(key)) and record[key] >= 0):
            raise CaptureLayoutError(f"{where}: view record has {key} = {record.get(key)!r}; expected an integer >= 0")
    for key in ("file", "sha256"):
        if not isinstance(record.get(key), str):
            raise CaptureLayoutError(f"{where}: view record has {key} = {record.get(key)!r}; expected a string")


class CaptureWriter:
    """Writes a capture folder view by view; opening an existing one resumes it.

    Parameters
    ----------
    path
        The capture folder (created if missing).
    header
        The header record: must contain ``grid`` (``rows``, ``cols``, ``pitch_mm``) and ``settings``,
        the dict that must be equal for a run to resume this folder (grid, pitch, origin, order,
        requested camera settings...). ``kind``, ``format``, ``version`` and ``created`` are filled in.

    Raises
    ------
    CaptureLayoutError
        When the folder holds a capture taken with other settings, or is not a capture but not empty.
    """

    def __init__(self, path: str | os.PathLike, *, header: dict[str, Any]) -> None:
        self.path = Path(path)
        if "settings" not in header or "grid" not in header:
            raise ValueError("the capture header needs 'grid' and 'settings'")
        self.completed: dict[tuple[int, int], dict[str, Any]] = {}
        #: Whether the journal ends with the "complete" record (no view was retaken after it).
        self.marked_complete = False
        if is_capture(self.path):
            self.header, records = _read_journal(self.path)
            self._check_settings(header["settings"])
            self._load_completed(records)
        else:
            if self.path.exists() and any(p.name != "session.log" for p in self.path.iterdir()):
                raise CaptureLayoutError(
                    f"{self.path}: folder exists, is not empty and is not an lfrig capture; choose a new folder"
                )
            (self.path / VIEWS).mkdir(parents=True, exist_ok=True)
            self.header = {"kind": "header", "format": FORMAT, "version": VERSION, "created": now_iso(), **header}
            with open(self.path / MANIFEST, "w", encoding="utf-8") as f:
                f.write(json.dumps(self.header, sort_keys=True) + "\n")
                f.flush()
                os.fsync(f.fileno())
        self.rows = int(self.header["grid"]["rows"])
        self.cols = int(self.header["grid"]["cols"])
        self._journal = open(self.path / MANIFEST, "a", encoding="utf-8")

    def _check_settings(self, settings: dict[str, Any]) -> None:
        stored = self.header.get("settings", {})
        # Compare through JSON so that tuples and lists, ints and floats compare as they are stored.
        wanted = json.loads(json.dumps(settings))
        if stored != wanted:
            keys = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
            diffs = "; ".join(f"{k}: capture has {stored.get(k)!r}, now {wanted.get(k)!r}" for k in keys)
            raise CaptureLayoutError(
                f"{self.path} was captured with other settings ({diffs}); "
                "run with the same settings to resume it, or capture into a new folder"
            )

    def _load_completed(self, records: list[dict[str, Any]]) -> None:
        self.marked_complete = bool(records) and records[-1].get("kind") == "complete"
        for record in records:
            if record.get("kind") != "view":
                continue
            key = (int(record["u"]), int(record["v"]))
            file = self.path / record["file"]
            try:
                digest = hashlib.sha256(file.read_bytes()).hexdigest()
            except FileNotFoundError:
                continue
            if digest == record.get("sha256"):
                self.completed[key] = record
            else:
                self.completed.pop(key, None)

    def write_view(self, u: int, v: int, image: np.ndarray, record: dict[str, Any] | None = None) -> dict[str, Any]:
        """Write the view at grid position ``(u, v)`` atomically, then journal it. Returns the record."""
        if not (0 <= u < self.rows and 0 <= v < self.cols):
            raise ValueError(f"grid position ({u}, {v}) is outside the {self.rows}x{self.cols} grid")
        name = view_name(u, v)
        digest = write_png(self.path / name, image)
        entry = {**(record or {}), "kind": "view", "u": u, "v": v, "file": name, "sha256": digest}
        entry.setdefault("time", now_iso())
        self._append(entry)
        self.completed[(u, v)] = entry
        self.marked_complete = False
        return entry

    def _append(self, record: dict[str, Any]) -> None:
        self._journal.write(json.dumps(record, sort_keys=True) + "\n")
        self._journal.flush()
        os.fsync(self._journal.fileno())

    @property
    def is_complete(self) -> bool:
        return len(self.completed) == self.rows * self.cols

    def write_parameters(self, **camera: Any) -> None:
        """Write ``parameters.cfg`` in the benchmark's format (plus an ``[lfrig]`` section).

        ``camera`` are the keyword arguments of :func:`parameters_for` other than ``grid``.
        """
        write_parameters(self.path / PARAMETERS, parameters_for(grid=(self.rows, self.cols), **camera))

    def mark_complete(self) -> None:
        """Journal that every view is present (once). Raises when some are missing."""
        if self.marked_complete:
            return
        if not self.is_complete:
            raise CaptureLayoutError(
                f"{self.path}: {len(self.completed)} of {self.rows * self.cols} views written; cannot mark complete"
            )
        self._append({"kind": "complete", "time": now_iso()})
        self.marked_complete = True

    def close(self) -> None:
        self._journal.close()

    def __enter__(self) -> "CaptureWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_capture(path: str | os.PathLike) -> LightField:
    """Read a complete capture folder into a :class:`LightField`.

    Raises
    ------
    CaptureLayoutError
        When views are missing (the capture is incomplete: resume it), a view file lies outside the
        grid, or a file does not match its journalled checksum.
    """
    path = Path(path)
    header, records = _read_journal(path)
    rows, cols = header["grid"]["rows"], header["grid"]["cols"]
    entries: dict[tuple[int, int], dict[str, Any]] = {}
    for record in records:
        if record.get("kind") == "view":
            entries[(int(record["u"]), int(record["v"]))] = record
    view_dir = path / VIEWS
    for file in sorted(view_dir.iterdir()) if view_dir.is_dir() else []:
        if file.name.startswith("."):
            continue  # a temporary file of an interrupted write
        match = _VIEW_NAME.match(file.name)
        if not match or not (int(match[1]) < rows and int(match[2]) < cols):
            raise CaptureLayoutError(
                f"{file}: not a view of the {rows}x{cols} grid (expected uUU_vVV.png with UU < {rows}, VV < {cols}); remove it"
            )
    missing = [(u, v) for u in range(rows) for v in range(cols) if (u, v) not in entries]
    if missing:
        shown = ", ".join(view_name(u, v) for u, v in missing[:3]) + (" ..." if len(missing) > 3 else "")
        raise CaptureLayoutError(
            f"{path}: capture is incomplete, {len(missing)} of {rows * cols} views missing ({shown}); "
            "run the same `lfrig capture` command again to resume it"
        )
    paths = [path / entries[(u, v)]["file"] for u in range(rows) for v in range(cols)]
    for p in paths:
        if not p.is_file():
            raise CaptureLayoutError(f"{p}: journalled view is missing on disk; resume the capture to take it again")
    images = read_images(paths)
    views = images.reshape((rows, cols) + images.shape[1:])
    camera: dict[str, Any] = {"pitch_mm": header["grid"].get("pitch_mm")}
    metadata: dict[str, Any] = {"layout": "lfrig-capture", "header": header,
                                "views": [entries[(u, v)] for u in range(rows) for v in range(cols)]}
    if (path / PARAMETERS).is_file():
        parameters = read_parameters(path / PARAMETERS)
        metadata["parameters"] = parameters
        _, found = camera_from_parameters(parameters, path=path / PARAMETERS)
        camera.update({k: v for k, v in found.items() if v is not None})
    return LightField(views=views, metadata=metadata, source=path, **camera)


def write_lightfield(path: str | os.PathLike, lf: LightField, *, header_extra: dict[str, Any] | None = None) -> None:
    """Write a whole light field (e.g. a rectified one) as a complete capture folder.

    ``lf.views`` must be ``uint8`` or ``uint16``. The folder must not exist or be empty.
    """
    path = Path(path)
    if is_capture(path) or (path.exists() and any(path.iterdir())):
        raise CaptureLayoutError(f"{path}: folder exists and is not empty; choose a new output folder")
    rows, cols = lf.grid_shape
    grid = {"rows": rows, "cols": cols, "pitch_mm": lf.pitch_mm}
    header = {"grid": grid, "settings": {"grid": grid, "source": str(lf.source) if lf.source else None},
              **(header_extra or {})}
    with CaptureWriter(path, header=header) as writer:
        for u in range(rows):
            for v in range(cols):
                writer.write_view(u, v, lf.views[u, v])
        writer.write_parameters(
            image_shape=lf.image_shape,
            pitch_mm=lf.pitch_mm,
            focal_px=lf.focal_px,
            disparity_range=lf.disparity_range,
            disparity_offset=lf.disparity_offset,
            principal_point_px=lf.principal_point_px,
        )
        writer.mark_complete()
