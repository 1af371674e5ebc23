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

import errno
import json
import os
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np

from recon.lf.imageio import (fault_point, read_bytes, read_view_grid, remove_stale_temporaries, sha256_file,
                             write_bytes_atomic, write_error, write_png)
from recon.lf.benchmark import GROUND_TRUTH
from recon.lf.lock import LOCK_NAME, FolderLock
from recon.lf.lightfield import LightField
from recon.errors import CaptureLayoutError
from recon.lf.params import MAX_GRID_SIDE, camera_from_parameters, check_camera_fits, is_finite, parameters_for, read_parameters, write_parameters

FORMAT = "lfrig-capture"
VERSION = 1
MANIFEST = "manifest.jsonl"
VIEWS = "views"
PARAMETERS = "parameters.cfg"
_VIEW_NAME = re.compile(r"^u(\d+)_v(\d+)\.png$")
#: Files a folder may hold before the capture starts (the lock is taken first, the log opened early).
_IGNORED = {"session.log", LOCK_NAME}
_TEMPORARY = re.compile(r"\..+\.\d+\.tmp(\.[^.]*)?")  # recon.lf.imageio.temporary_name


def view_name(u: int, v: int) -> str:
    """File name of the view at grid row ``u``, column ``v`` (relative to the capture folder)."""
    return f"{VIEWS}/u{u:02d}_v{v:02d}.png"


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def is_capture(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder in lfrig's capture layout (it has a manifest)."""
    return (Path(path) / MANIFEST).is_file()


def _journal_lines(manifest: Path) -> tuple[list[tuple[int, str]], int]:
    """The lines of a journal with their line numbers, and the byte offset where the last complete
    line ends. A torn tail (a crash or a full disk mid-append: bytes without a final newline, or a
    last line that is not JSON, e.g. the zeros a crash can leave) is left out of both."""
    data = read_bytes(manifest, error=CaptureLayoutError,
                      missing=f"no such file; {manifest.parent} is not an lfrig capture")
    end = data.rfind(b"\n") + 1  # bytes after the last newline are a torn append
    raw = data[:end].split(b"\n")[:-1] if end else []
    if raw:
        try:
            json.loads(raw[-1].decode("utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            end -= len(raw[-1]) + 1  # a complete-looking last line that is not JSON: torn as well
            raw = raw[:-1]
    lines = []
    for number, line in enumerate(raw, start=1):
        try:
            lines.append((number, line.decode("utf-8")))
        except UnicodeDecodeError:
            raise CaptureLayoutError(f"{manifest}: line {number} is not UTF-8 text; the journal is damaged") from None
    return lines, end


def _read_journal(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The header and the remaining records of a manifest. A torn last line (a crash mid-append) is
    ignored (:func:`_journal_lines`); any other unreadable line is an error."""
    manifest = path / MANIFEST
    lines, _ = _journal_lines(manifest)
    records: list[dict[str, Any]] = []
    for number, line in lines:
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            raise CaptureLayoutError(f"{manifest}: line {number} is not valid JSON; the journal is damaged") from None
        if not isinstance(record, dict):
            raise CaptureLayoutError(f"{manifest}: line {number} is not a JSON object")
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


def _view_key(record: dict[str, Any], *, rows: int, cols: int) -> tuple[tuple[int, int] | None, bool]:
    """The grid position a view record is about, and whether it names that position's own file.

    Returns ``(None, False)`` for a record whose ``u``, ``v`` are not integers inside the grid (it
    names nothing lfrig reads, and is ignored: such a line cannot make a capture unfinishable), and
    ``((u, v), ok)`` otherwise, ``ok`` when ``file`` is exactly ``views/uUU_vVV.png``.
    """
    u, v = record.get("u"), record.get("v")
    if not (isinstance(u, int) and isinstance(v, int) and not isinstance(u, bool) and not isinstance(v, bool)):
        return None, False
    if not (0 <= u < rows and 0 <= v < cols):
        return None, False
    return (u, v), record.get("file") == view_name(u, v)


def _unused(path: Path) -> bool:
    """Whether a folder that is not a capture may become one: it is missing, empty, or holds only
    what a capture that died before its header was in place leaves (the lock, the log, an empty
    ``views/``, temporary files)."""
    if not path.exists():
        return True

    def leftover(p: Path) -> bool:
        return p.name in _IGNORED or _TEMPORARY.fullmatch(p.name) is not None

    for entry in path.iterdir():
        if entry.name == VIEWS and entry.is_dir() and not entry.is_symlink():
            if all(leftover(v) for v in entry.iterdir()):
                continue
            return False
        if not leftover(entry):
            return False
    return True


def _check_views_folder(path: Path) -> None:
    """A capture writes its views only into its own ``views/``: a ``views`` that is a link (to a folder
    elsewhere, whose files a resume would overwrite or delete) or not a folder is refused."""
    views = path / VIEWS
    if views.is_symlink():
        raise CaptureLayoutError(
            f"{views}: is a symbolic link; a capture keeps its views in a folder of its own (lfrig does not "
            "write through the link): replace the link with the folder itself, or capture into a new folder"
        )
    if views.exists() and not views.is_dir():
        raise CaptureLayoutError(f"{views}: is not a folder; remove it, or capture into a new folder")


def _open_journal(manifest: Path, *, append: bool = True):
    """The journal opened for appending (or for cutting a torn tail), never through a symbolic link."""
    flags = (os.O_WRONLY | os.O_APPEND if append else os.O_RDWR) | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(manifest, flags)
    except OSError as error:
        if error.errno == errno.ELOOP:
            raise CaptureLayoutError(f"{manifest}: is a symbolic link; lfrig does not write through it "
                                     "(replace it with the journal itself)") from None
        raise
    return os.fdopen(fd, "ab" if append else "r+b")


def _inside(path: Path, file: Path) -> bool:
    """Whether ``file`` (resolved, symlinks followed) lies inside the folder ``path``."""
    try:
        file.resolve().relative_to(path.resolve())
    except ValueError:
        return False
    return True


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

    def __init__(self, path: str | os.PathLike, *, header: dict[str, Any], lock: FolderLock | None = None) -> None:
        self.path = Path(path)
        if "settings" not in header or "grid" not in header:
            raise ValueError("the capture header needs 'grid' and 'settings'")
        self.completed: dict[tuple[int, int], dict[str, Any]] = {}
        #: The journal's records other than views and ``complete`` (e.g. a capture session's notes
        #: about its machine frame), in order.
        self.events: list[dict[str, Any]] = []
        #: Whether this writer wrote the header (the folder was not a capture before).
        self.created = False
        self._discarded = False
        #: Whether the journal ends with the "complete" record (no view was retaken after it).
        self.marked_complete = False
        # One writer per folder: the caller may have taken the lock earlier (before opening devices).
        self._own_lock = lock is None
        self.lock = lock if lock is not None else FolderLock(self.path, what="capture")
        try:
            self._open(header)
        except BaseException:
            self.close()
            raise

    def _open(self, header: dict[str, Any]) -> None:
        self._journal = None
        manifest = self.path / MANIFEST
        if is_capture(self.path):
            self.header, records = _read_journal(self.path)
            self._check_settings(header["settings"])
            self.rows = int(self.header["grid"]["rows"])
            self.cols = int(self.header["grid"]["cols"])
            self._load_completed(records)
            _check_views_folder(self.path)
            remove_stale_temporaries(self.path)  # we hold the lock: these are a dead writer's
            remove_stale_temporaries(self.path / VIEWS)
            _, end = _journal_lines(manifest)
            if end != manifest.stat().st_size:
                # A torn last line (crash or full disk mid-append): cut it, or the next append would
                # land after it and turn it into a damaged line in the middle of the journal.
                try:
                    with _open_journal(manifest, append=False) as f:
                        f.truncate(end)
                        os.fsync(f.fileno())
                except OSError as error:
                    raise write_error(manifest, error) from None
        else:
            if not _unused(self.path):
                raise CaptureLayoutError(
                    f"{self.path}: folder exists, is not empty and is not an lfrig capture; choose a new folder"
                )
            _check_views_folder(self.path)
            remove_stale_temporaries(self.path)  # a run that died before its header was in place
            if (self.path / VIEWS).is_dir():
                remove_stale_temporaries(self.path / VIEWS)
            try:
                (self.path / VIEWS).mkdir(parents=True, exist_ok=True)
            except OSError as error:
                raise write_error(self.path / VIEWS, error) from None
            self.header = {"kind": "header", "format": FORMAT, "version": VERSION, "created": now_iso(), **header}
            # Atomic: a crash leaves no manifest (a folder to start afresh) or the whole header line.
            write_bytes_atomic(manifest, (json.dumps(self.header, sort_keys=True) + "\n").encode("utf-8"))
            self.rows = int(self.header["grid"]["rows"])
            self.cols = int(self.header["grid"]["cols"])
            self.created = True
        try:
            self._journal = _open_journal(manifest)
        except OSError as error:
            raise write_error(manifest, error) from None

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
        self.marked_complete = _ends_complete(records)
        for record in records:
            if record.get("kind") == "frame":
                self.completed.clear()  # views before a new frame no longer count: all are taken again
            if record.get("kind") not in ("view", "complete"):
                self.events.append(record)
            if record.get("kind") != "view":
                continue
            # A record outside the grid, or naming another file, counts for nothing (the grid's
            # own views are what completes a capture); the view it claims is taken again.
            key, named_right = _view_key(record, rows=self.rows, cols=self.cols)
            if key is None:
                continue
            file = self.path / view_name(*key)
            if not named_right or file.is_symlink() or not file.is_file():
                self.completed.pop(key, None)
                continue
            try:
                digest = sha256_file(file, error=CaptureLayoutError)
            except CaptureLayoutError:  # unreadable or not a regular file: taken again
                self.completed.pop(key, None)
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
        """Append one line and sync it; on failure cut what was written, so no torn line stays."""
        line = (json.dumps(record, sort_keys=True) + "\n").encode("utf-8")
        manifest = self.path / MANIFEST
        if self._journal is None:
            raise CaptureLayoutError(f"{manifest}: the journal could not be reopened after a failed write; run again to resume")
        start = self._journal.tell()
        try:
            half = len(line) // 2
            self._journal.write(line[:half])
            self._journal.flush()
            fault_point(manifest)
            self._journal.write(line[half:])
            self._journal.flush()
            os.fsync(self._journal.fileno())
        except OSError as error:
            try:
                self._journal.close()  # drops what is still buffered
            except OSError:
                pass
            try:
                with _open_journal(manifest, append=False) as f:
                    f.truncate(start)
                    os.fsync(f.fileno())
            except OSError:
                pass  # the next open cuts the torn line (_journal_lines)
            try:
                self._journal = _open_journal(manifest)
            except OSError:
                self._journal = None  # nothing more can be journalled; the views so far are kept
            raise write_error(manifest, error) from None

    @property
    def frame(self) -> Any:
        """The frame the views stand in: the last ``frame`` record's, else the header's ``frame``."""
        for event in reversed(self.events):
            if event.get("kind") == "frame":
                return event.get("frame")
        return self.header.get("frame")

    def note(self, kind: str, **fields: Any) -> dict[str, Any]:
        """Journal a record that is not a view (``kind`` other than ``view``, ``frame``, ``complete``)."""
        if kind in ("view", "frame", "complete", "header"):
            raise ValueError(f"note() does not journal {kind!r} records")
        record = {**fields, "kind": kind, "time": now_iso()}
        self._append(record)
        self.events.append(record)
        return record

    def new_frame(self, frame: Any) -> None:
        """Journal a new ``frame``: the views journalled before it no longer count (they are taken again)."""
        record = {"kind": "frame", "frame": frame, "time": now_iso()}
        self._append(record)
        self.events.append(record)
        self.completed.clear()
        self.marked_complete = False

    def discard(self) -> bool:
        """Remove the header this writer wrote and the empty ``views/`` folder, when no view was
        written (not even one the journal missed): a capture refused before its first view leaves no
        journal behind. Closes the journal; returns whether it removed them."""
        if not self.created or self.completed or any(e.get("kind") == "frame" for e in self.events):
            return False
        views = self.path / VIEWS
        try:
            remove_stale_temporaries(views)
            if any(views.iterdir()):  # a view written but not journalled: keep the capture, a resume takes it again
                return False
            if getattr(self, "_journal", None) is not None:
                self._journal.close()
                self._journal = None
            (self.path / MANIFEST).unlink(missing_ok=True)
            views.rmdir()
        except OSError:
            return False
        self.created = False
        self._discarded = True
        return True

    @property
    def is_complete(self) -> bool:
        return all((u, v) in self.completed for u in range(self.rows) for v in range(self.cols))

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
        if getattr(self, "_journal", None) is not None:
            self._journal.close()
            self._journal = None
        if self._own_lock:
            self.lock.release(discard=self._discarded)

    def __enter__(self) -> "CaptureWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_capture(path: str | os.PathLike, *, verify: bool = True, grey: bool = False,
                 decode: bool = True) -> LightField:
    """Read a complete capture folder into a :class:`LightField` (``grey``: the views as ``float32``
    luminance; ``decode=False``: no pixels, :func:`recon.lf.read_lightfield`).

    Every view must be journalled as ``views/uUU_vVV.png`` of its own grid position, a regular file
    inside the folder (not a symlink out of it). With ``verify`` (the default), each file's SHA-256
    is checked against the journal (from the bytes read for decoding, before they are decoded), so
    a swapped, edited or damaged view is an error rather than silently used; ``verify=False``
    (``--no-verify``) skips that check (the hashing: ``bench/verify_capture.py``), never the path
    checks.

    Raises
    ------
    CaptureLayoutError
        When views are missing (the capture is incomplete: resume it), a view file lies outside the
        grid or the folder, or a file does not match its journalled checksum.
    """
    path = Path(path)
    header, records = _read_journal(path)
    manifest = path / MANIFEST
    rows, cols = header["grid"]["rows"], header["grid"]["cols"]
    entries: dict[tuple[int, int], dict[str, Any]] = {}
    for record in records:
        if record.get("kind") == "frame":
            entries.clear()  # views before a new frame do not count: every view was taken again after it
        if record.get("kind") != "view":
            continue
        key, _ = _view_key(record, rows=rows, cols=cols)
        if key is None:
            continue  # outside the grid: names nothing that is read (the writer ignores it too)
        entries[key] = record  # the last record of a position counts (a retake follows a bad one)
    bad = [(key, r) for key, r in entries.items() if r.get("file") != view_name(*key)]
    if bad:
        (u, v), record = bad[0]
        raise CaptureLayoutError(
            f"{manifest}: the view ({u}, {v}) is journalled as file {record.get('file')!r}, but a view must be "
            f"{view_name(u, v)} inside the capture; run the same `lfrig capture` command again to take it again"
        )
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
    if not _ends_complete(records):
        raise CaptureLayoutError(
            f"{path}: capture is incomplete, every view is on disk but it was not finished ({MANIFEST} has no "
            "'complete' record after them); run the same `lfrig capture` command again to finish it"
        )
    paths = [path / entries[(u, v)]["file"] for u in range(rows) for v in range(cols)]
    for p in paths:
        if p.is_symlink() or not _inside(path, p):
            raise CaptureLayoutError(f"{p}: a view must be a file inside {path}, not a link elsewhere; replace it with the view itself")
        if not p.is_file():
            raise CaptureLayoutError(f"{p}: journalled view is missing on disk; resume the capture to take it again")
    journalled = {path / entries[(u, v)]["file"]: entries[(u, v)].get("sha256")
                  for u in range(rows) for v in range(cols)}
    views, centre = read_view_grid(paths, (rows, cols), grey=grey,
                                   check=_checksum_check(journalled) if verify else None, decode=decode)
    camera: dict[str, Any] = {"pitch_mm": header["grid"].get("pitch_mm")}
    metadata: dict[str, Any] = {"layout": "lfrig-capture", "header": header,
                                "views": [entries[(u, v)] for u in range(rows) for v in range(cols)]}
    if (path / GROUND_TRUTH).is_file():  # kept by `lfrig import` from a benchmark folder or an lf.h5 file
        metadata["ground_truth"] = str(path / GROUND_TRUTH)
    if (path / PARAMETERS).is_file():
        parameters = read_parameters(path / PARAMETERS)
        metadata["parameters"] = parameters
        _, found = camera_from_parameters(parameters, path=path / PARAMETERS)
        camera.update({k: v for k, v in found.items() if v is not None})
        check_camera_fits(camera, parameters, grid=(rows, cols), image_shape=views.shape[2:4], path=path / PARAMETERS)
    return LightField(views=views, metadata=metadata, source=path, stored_centre=centre, **camera)


def _ends_complete(records: list[dict[str, Any]]) -> bool:
    """Whether the journal's last record (after any retake) is the ``complete`` record."""
    return bool(records) and records[-1].get("kind") == "complete"


def _checksum_check(journalled: dict[Path, Any]) -> Callable[[Path, str], None]:
    """``check(file, sha256_hex)`` for :func:`recon.lf.imageio.read_images`: the bytes read for a view
    must have the SHA-256 its journal records (``journalled[file]``), checked before they are
    decoded, in the one pass that reads them."""

    def check(file: Path, got: str) -> None:
        if journalled[file] != got:
            raise CaptureLayoutError(
                f"{file}: content does not match the checksum in {MANIFEST} (the file was replaced, edited or "
                f"damaged); resume the capture to take it again, or pass --no-verify to use it anyway"
            )

    return check


def write_lightfield(path: str | os.PathLike, lf: LightField, *, header_extra: dict[str, Any] | None = None) -> None:
    """Write a whole light field (e.g. a rectified one) as a complete capture folder.

    ``lf.views`` must be ``uint8`` or ``uint16``. The folder must not exist or be empty, or hold an
    unfinished capture of the same light field (an interrupted earlier run: it is finished, the
    views already on disk with their journalled checksum are kept). The folder is locked meanwhile.
    """
    path = Path(path)
    rows, cols = lf.grid_shape
    grid = {"rows": rows, "cols": cols, "pitch_mm": lf.pitch_mm}
    header = {"grid": grid, "settings": {"grid": grid, "source": str(lf.source) if lf.source else None},
              **(header_extra or {})}
    with FolderLock(path, what="capture") as lock:
        if is_capture(path):
            _, records = _read_journal(path)
            if records and records[-1].get("kind") == "complete":
                raise CaptureLayoutError(f"{path}: folder already holds a complete capture; choose a new output folder")
        elif not _unused(path):
            raise CaptureLayoutError(f"{path}: folder exists and is not empty; choose a new output folder")
        with CaptureWriter(path, header=header, lock=lock) as writer:
            for u in range(rows):
                for v in range(cols):
                    if (u, v) not in writer.completed:
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
