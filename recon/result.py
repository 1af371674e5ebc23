"""The reconstruction folder: its file names, its record (``result.json``), and the one reader.

A folder written by ``lfrig reconstruct`` (and ``lfrig batch reconstruct``, :mod:`recon.pipeline`)
holds:

- ``disparity.pfm``: ``(H, W)`` float32 disparity of the centre view, pixels per view step
  (``docs/conventions.md``); ``disparity.png``, the same colour-mapped; ``centre_view.png``;
- the method's own maps (entropy: :data:`ENTROPY_MAPS`, written by :mod:`recon.entropy.outputs`);
- ``result.json`` (:class:`ResultRecord`), written last and atomically, so a folder with a readable
  ``result.json`` holds the maps it describes;
- on request, a PLY and depth maps (:mod:`recon.export`, :mod:`recon.depth`).

``docs/capture-format.md`` describes every file.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from recon.camera import Camera
from recon.errors import ExportError
from recon.lf.params import is_finite

RESULT_JSON = "result.json"
DISPARITY_PFM = "disparity.pfm"
DISPARITY_PNG = "disparity.png"
CENTRE_VIEW_PNG = "centre_view.png"
#: The entropy method's maps (``recon.entropy.outputs.write_outputs``).
REGIONS_PNG = "regions.png"
REGIONS_NPY = "regions.npy"
WINDOW_SIZE_PNG = "window_size.png"
WINDOW_SIZE_NPY = "window_size.npy"
WINDOW_SHAPE_PNG = "window_shape.png"
WINDOW_SHAPE_NPY = "window_shape.npy"
VIEW_SET_NPY = "view_set.npy"
INITIAL_DISPARITY_PFM = "initial_disparity.pfm"
MATCHED_DISPARITY_PFM = "matched_disparity.pfm"
REFINED_DISPARITY_PFM = "refined_disparity.pfm"
HOLES_PNG = "holes.png"
#: Per-pixel confidence of disparity.pfm in [0, 1] (recon.entropy.confidence); the export drops
#: pixels below its threshold.
CONFIDENCE_PFM = "confidence.pfm"
CONFIDENCE_PNG = "confidence.png"
ENTROPY_MAPS = (REGIONS_PNG, REGIONS_NPY, WINDOW_SIZE_PNG, WINDOW_SIZE_NPY, WINDOW_SHAPE_PNG, WINDOW_SHAPE_NPY,
                VIEW_SET_NPY, INITIAL_DISPARITY_PFM, MATCHED_DISPARITY_PFM, REFINED_DISPARITY_PFM, HOLES_PNG,
                CONFIDENCE_PFM, CONFIDENCE_PNG)
#: Every name lfrig itself writes into a reconstruction folder; a rerun removes them (:func:`clear_result`).
RESULT_FILES = (RESULT_JSON, DISPARITY_PFM, DISPARITY_PNG, CENTRE_VIEW_PNG) + ENTROPY_MAPS


@dataclass
class ResultRecord:
    """What ``result.json`` records about one reconstruction.

    Attributes
    ----------
    method, options
        The method's name and its options as the method reports them.
    source
        The light-field folder (absolute, or relative to the result folder), or ``None``.
    image, grid
        ``[W, H]`` of the centre view and ``[U, V]`` of the grid.
    focal_px, pitch_mm, disparity_offset, principal_point_px
        The rectified camera (:attr:`camera`); ``focal_px``/``pitch_mm`` are ``None`` when the light
        field did not record them (a benchmark scene without ``parameters.cfg``).
    disparity_png_range
        ``[low, high]`` of ``disparity.png``'s colour map, pixels per view step.
    seconds
        Time of the estimate alone.
    scores
        :func:`recon.evaluate.score` against the light field's ground truth, when it has one.
    files
        The files this run wrote into the folder (relative names), ``result.json`` and a PLY inside the
        folder included; the next run into the folder removes them first (:func:`clear_result`).
    provenance
        How the result was made (:func:`recon.provenance.provenance`: lfrig's version, the command,
        the start time, the input's identity, timings per step, the machine), or ``None`` for a
        folder written before it was recorded.
    extra
        Any further keys (how the work was tiled, a ``mask`` file name, ...), kept as they are.
    """

    method: str | None = None
    options: dict[str, Any] = field(default_factory=dict)
    source: str | None = None
    image: list[int] | None = None
    grid: list[int] | None = None
    focal_px: float | None = None
    pitch_mm: float | None = None
    disparity_offset: float = 0.0
    principal_point_px: list[float] | None = None
    disparity_png_range: list[float] | None = None
    seconds: float | None = None
    scores: dict[str, Any] | None = None
    files: list[str] | None = None
    provenance: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def camera(self) -> Camera | None:
        """The rectified camera, or ``None`` when ``focal_px`` or ``pitch_mm`` is unknown."""
        if self.focal_px is None or self.pitch_mm is None:
            return None
        return Camera(focal_px=self.focal_px, pitch_mm=self.pitch_mm, disparity_offset=self.disparity_offset,
                      principal_point_px=tuple(self.principal_point_px) if self.principal_point_px else None)

    def to_json(self) -> dict[str, Any]:
        """The JSON object of ``result.json`` (``scores`` only when there are any; ``extra`` inline)."""
        optional = ("scores", "files", "provenance", "extra")
        record = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in optional}
        if self.scores is not None:
            record["scores"] = self.scores
        if self.files is not None:
            record["files"] = list(self.files)
        if self.provenance is not None:
            record["provenance"] = self.provenance
        for key, value in self.extra.items():
            if key in record:
                raise ValueError(f"extra key {key!r} would overwrite result.json's own {key!r}")
            record[key] = value
        return record

    @classmethod
    def from_json(cls, record: dict[str, Any], *, where: Path) -> "ResultRecord":
        """Check and type a ``result.json`` object; raises :class:`ExportError` naming ``where``."""
        if not isinstance(record, dict):
            raise ExportError(f"{where}: expected a JSON object with focal_px, pitch_mm, disparity_offset")
        own = {f.name for f in fields(cls)} - {"extra"}
        values = {key: record[key] for key in own if key in record}
        values["focal_px"] = _number(record, "focal_px", where, positive=True)
        values["pitch_mm"] = _number(record, "pitch_mm", where, positive=True)
        values["disparity_offset"] = _number(record, "disparity_offset", where, positive=False) or 0.0
        principal = record.get("principal_point_px")
        if principal is not None:
            if not (isinstance(principal, list) and len(principal) == 2
                    and all(isinstance(c, (int, float)) and not isinstance(c, bool) and is_finite(c) for c in principal)):
                raise ExportError(f"{where}: principal_point_px = {principal!r} must be [cx, cy] in pixels")
            values["principal_point_px"] = [float(c) for c in principal]
        from recon.lf.params import camera_problem

        problem = camera_problem(focal_px=values["focal_px"], pitch_mm=values["pitch_mm"],
                                 disparity_offset=values["disparity_offset"],
                                 principal_point_px=values.get("principal_point_px"))
        if problem is not None:
            raise ExportError(f"{where}: {problem}; fix result.json or run lfrig reconstruct again")
        if values.get("options") is None:
            values["options"] = {}
        for key, kinds, what in (("method", str, "a method name"), ("source", str, "a folder name"),
                                 ("scores", dict, "a JSON object of scores"), ("seconds", (int, float), "a number"),
                                 ("image", list, "[W, H]"), ("grid", list, "[U, V]"),
                                 ("disparity_png_range", list, "[low, high]")):
            value = values.get(key)
            if value is not None and (not isinstance(value, kinds) or isinstance(value, bool)):
                raise ExportError(f"{where}: {key} = {str(value)[:80]!r} must be {what}; fix result.json or run "
                                  "lfrig reconstruct again")
        if not isinstance(values["options"], dict):
            raise ExportError(f"{where}: options = {str(values['options'])[:80]!r} must be a JSON object of the "
                              "method's options; fix result.json or run lfrig reconstruct again")
        files = record.get("files")
        if files is not None and not (isinstance(files, list) and all(isinstance(f, str) for f in files)):
            raise ExportError(f"{where}: files = {files!r} must be a list of file names")
        if values.get("provenance") is not None and not isinstance(values["provenance"], dict):
            raise ExportError(f"{where}: provenance = {values['provenance']!r} must be a JSON object")
        return cls(**values, extra={key: value for key, value in record.items() if key not in own})


def _number(record: dict, key: str, where: Path, *, positive: bool) -> float | None:
    value = record.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not is_finite(value) or (positive and value <= 0):
        need = "a positive number" if positive else "a finite number"
        raise ExportError(f"{where}: {key} = {value!r} must be {need}")
    return float(value)


def write_record(folder: Path, record: ResultRecord) -> Path:
    """Write ``folder/result.json`` atomically (a temporary file renamed over it); returns its path."""
    from recon.lf.imageio import write_bytes_atomic

    path = Path(folder) / RESULT_JSON
    write_bytes_atomic(path, (json.dumps(record.to_json(), indent=2) + "\n").encode("utf-8"))
    return path


def folder_file(folder: Path, name: Any, *, what: str, where: Path) -> Path:
    """``folder / name`` for a file name that ``result.json`` records, checked to stay in the folder.

    ``name`` must be a relative path without ``..`` whose target (symlinks followed) is a regular
    file inside ``folder``; anything else (``../other/x.png``, ``/dev/zero``, a link out) is an
    :class:`ExportError` naming ``where``.
    """
    folder = Path(folder)
    bad = ExportError(f"{where}: {what} = {name!r} must name a file inside {folder} (a relative name without "
                      "'..'); fix result.json or run lfrig reconstruct again")
    if not isinstance(name, str) or not name or "\x00" in name:
        raise bad
    relative = Path(name)
    if relative.is_absolute() or ".." in relative.parts:
        raise bad
    path = folder / relative
    try:
        path.resolve().relative_to(folder.resolve())
    except ValueError:
        raise bad from None
    if path.exists() and not path.is_file():
        raise ExportError(f"{path}: the {what} named by {where.name} is not a regular file")
    return path


def clear_result(folder: str | Path) -> list[str]:
    """Remove the files of a previous run so that the folder will hold one run only.

    ``result.json`` goes first (a folder without it is clearly unfinished), then every file the old
    ``result.json`` listed under ``files`` (inside the folder) and every name in
    :data:`RESULT_FILES`. Files lfrig does not know stay. Returns the names removed.
    """
    folder = Path(folder)
    names = set(RESULT_FILES)
    record_path = folder / RESULT_JSON
    from recon.errors import LfrigError
    from recon.lf.imageio import read_bytes

    try:
        old = json.loads(read_bytes(record_path, error=ExportError).decode("utf-8"))
        listed = old.get("files") if isinstance(old, dict) else None
        if isinstance(listed, list):
            for name in listed:
                try:
                    names.add(folder_file(folder, name, what="files", where=record_path).relative_to(folder).as_posix())
                except (ExportError, ValueError):
                    continue  # a name outside the folder is never removed
    except (LfrigError, ValueError, RecursionError):
        pass  # no (readable) record: the known names are still removed
    from recon.lf.imageio import remove_stale_temporaries

    removed = []
    remove_stale_temporaries(folder)  # called under the folder's lock: a dead run's temporaries
    for name in [RESULT_JSON] + sorted(names - {RESULT_JSON}):
        path = folder / name
        if path.is_file() or path.is_symlink():
            try:
                path.unlink()
            except OSError as error:
                raise ExportError(f"{path}: cannot remove the previous run's file ({error.strerror}); check the folder") from None
            removed.append(name)
    return removed


@dataclass
class ResultFolder:
    """What :func:`read_result` takes from a reconstruction folder.

    ``focal_px``/``pitch_mm`` may be ``None`` when ``result.json`` did not know them (e.g. a
    benchmark scene without ``parameters.cfg``); :meth:`camera` then needs them passed in.
    """

    path: Path
    disparity_px: np.ndarray
    image: np.ndarray | None
    mask: np.ndarray | None
    record: ResultRecord
    #: ``(H, W)`` float32 in ``[0, 1]`` from ``confidence.pfm``, or ``None`` (a method without one).
    confidence: np.ndarray | None = None

    @property
    def search_range(self) -> tuple[float, float] | None:
        """``(min, max)`` disparity the method searched (``options["disparity_range"]``), or ``None``."""
        rng = self.record.options.get("disparity_range")
        if isinstance(rng, (list, tuple)) and len(rng) == 2 and all(isinstance(v, (int, float)) for v in rng):
            return float(rng[0]), float(rng[1])
        return None

    @property
    def focal_px(self) -> float | None:
        return self.record.focal_px

    @property
    def pitch_mm(self) -> float | None:
        return self.record.pitch_mm

    @property
    def disparity_offset(self) -> float:
        return self.record.disparity_offset

    @property
    def principal_point_px(self) -> tuple[float, float] | None:
        principal = self.record.principal_point_px
        return (principal[0], principal[1]) if principal else None

    def camera(self, *, focal_px: float | None = None, pitch_mm: float | None = None,
               disparity_offset: float | None = None) -> Camera:
        """The folder's camera with the caller's overrides (``None`` keeps the folder's value).

        Raises
        ------
        ExportError
            When ``focal_px`` or ``pitch_mm`` is still unknown, naming the flags that give them.
        """
        focal = focal_px if focal_px is not None else self.focal_px
        pitch = pitch_mm if pitch_mm is not None else self.pitch_mm
        missing = [flag for flag, value in (("--focal-px", focal), ("--pitch-mm", pitch)) if value is None]
        if missing:
            raise ExportError(
                f"{self.path / RESULT_JSON}: {', '.join(m[2:].replace('-', '_') for m in missing)} unknown (the light "
                f"field had no camera parameters); metric depth needs them, pass {' and '.join(missing)}"
            )
        offset = disparity_offset if disparity_offset is not None else self.disparity_offset
        try:
            return Camera(focal_px=focal, pitch_mm=pitch, disparity_offset=offset,
                          principal_point_px=self.principal_point_px)
        except ValueError as error:
            raise ExportError(f"{self.path}: {error}") from None


def read_result(result_dir) -> ResultFolder:
    """Read a reconstruction folder written by ``lfrig reconstruct``.

    Reads ``disparity.pfm`` and ``result.json`` (:class:`ResultRecord`: ``focal_px``, ``pitch_mm``,
    ``disparity_offset`` default 0, optionally ``principal_point_px``, ``mask`` (a PNG in the folder,
    non-zero = trusted) and ``source``), and ``confidence.pfm`` when the method wrote one. Colours come from ``centre_view.png`` in the folder if
    present, else from the centre view of ``source``; without either the export has no colours.

    Raises
    ------
    ExportError
        Naming the folder or file and what is wrong.
    """
    from recon.lf.pfm import read_pfm

    folder = Path(result_dir)
    if not folder.is_dir():
        raise ExportError(f"{folder}: no such reconstruction folder (run lfrig reconstruct first)")
    record_path = folder / RESULT_JSON
    if not record_path.is_file():
        raise ExportError(f"{record_path}: missing; RESULT_DIR must be a folder written by lfrig reconstruct")
    from recon.lf.imageio import read_bytes

    try:
        raw = json.loads(read_bytes(record_path, error=ExportError).decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as error:
        raise ExportError(f"{record_path}: not valid JSON ({error})") from None
    record = ResultRecord.from_json(raw, where=record_path)
    disparity_path = folder / DISPARITY_PFM
    if not disparity_path.is_file():
        raise ExportError(f"{disparity_path}: missing; the reconstruction did not finish, run it again")
    disparity = read_pfm(disparity_path)
    if disparity.ndim != 2:
        raise ExportError(f"{disparity_path}: expected a one-channel disparity map, got shape {disparity.shape}")

    mask = None
    if record.extra.get("mask"):
        mask = _read_image(folder_file(folder, record.extra["mask"], what="mask", where=record_path), what="mask")
        mask = (mask if mask.ndim == 2 else mask.max(axis=-1)) > 0
        if mask.shape != disparity.shape:
            raise ExportError(f"{folder / str(record.extra['mask'])}: mask is {mask.shape}, disparity is {disparity.shape}")

    confidence = None
    if (folder / CONFIDENCE_PFM).is_file():
        confidence = read_pfm(folder / CONFIDENCE_PFM)
        if confidence.shape != disparity.shape:
            raise ExportError(f"{folder / CONFIDENCE_PFM}: confidence is {confidence.shape}, disparity is "
                              f"{disparity.shape}; they must come from the same reconstruction")

    image = None
    if (folder / CENTRE_VIEW_PNG).is_file():
        image = _read_image(folder / CENTRE_VIEW_PNG, what="centre view")
    elif record.source:
        source = source_folder(folder, record)
        if source is not None and source.is_dir():
            from recon.lf import read_lightfield

            image = read_lightfield(source).centre_view()
    if image is not None and image.shape[:2] != disparity.shape:
        raise ExportError(
            f"{folder}: centre view is {image.shape[:2]} but disparity.pfm is {disparity.shape}; "
            "they must come from the same reconstruction"
        )
    return ResultFolder(path=folder, disparity_px=disparity, image=image, mask=mask, record=record,
                        confidence=confidence)


def source_folder(folder: Path, record: ResultRecord) -> Path | None:
    """The light-field folder a result came from (``source`` is absolute or relative to ``folder``)."""
    if not record.source:
        return None
    source = Path(str(record.source))
    return source if source.is_absolute() else Path(folder) / source


def _read_image(path: Path, *, what: str) -> np.ndarray:
    from recon.lf.imageio import read_image

    if not path.is_file():
        raise ExportError(f"{path}: the {what} named by result.json is missing")
    return read_image(path)
