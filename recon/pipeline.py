"""One light field in, one result folder out: what ``lfrig reconstruct`` and ``lfrig batch`` both do.

:func:`reconstruct_to_folder` reads a light-field folder, estimates the centre view's disparity and
writes the result folder (:mod:`recon.result` names its files): ``disparity.pfm``, ``disparity.png``,
``centre_view.png``, the method's own maps (:attr:`recon.methods.MethodResult.write_extras`) and
``result.json`` (:class:`recon.result.ResultRecord`, with ``scores`` when the light field has ground
truth), and, on request, a PLY mesh or point cloud through :func:`recon.export.export_result`.

``result.json`` is written last and atomically (a temporary file renamed over it), so a folder with a
readable ``result.json`` holds the disparity maps it describes.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from recon.errors import ReconError
from recon.paths import writable_file, writable_folder
from recon.lf.lightfield import LightField
from recon.lf.params import disparity_range_problem
from recon.methods import DEFAULT_METHOD, MethodResult, Warming, check_method_options, run_method, warm_in_background
from recon.progress import ProgressCallback
from recon.lf.lock import FolderLock
from recon.result import (CENTRE_VIEW_PNG, DISPARITY_PFM, DISPARITY_PNG, RESULT_JSON, ResultRecord, clear_result,
                          write_record)

#: ``estimate(lf, method, options, progress) -> MethodResult``: how the disparity is computed. The
#: default runs :func:`recon.methods.run_method` in this process; tiled runs on a cluster plug in
#: here (:func:`recon.scale.tiles.tiled_estimator`). ``progress`` is ``None`` or
#: ``progress(fraction, message)`` (:mod:`recon.progress`).
Estimator = Callable[[LightField, str, dict[str, Any], Any], MethodResult]

#: The finest candidate spacing accepted (pixels per view step): finer steps resolve nothing more
#: (the sub-step parabola does that) and make the cost volume enormous.
MIN_STEP_PX = 1e-3
#: The largest matching window accepted (pixels).
MAX_WINDOW_PX = 255


@dataclass
class FolderResult:
    """What :func:`reconstruct_to_folder` wrote: the folder, ``result.json``'s record, the PLY (if any)."""

    out_dir: Path
    record: ResultRecord
    ply: Path | None = None
    export: Any = None  # recon.export.ExportSummary when a PLY was written
    files: list[str] = field(default_factory=list)


def run_in_process(lf: LightField, method: str, options: dict[str, Any],
                   progress: ProgressCallback | None) -> MethodResult:
    """The default :data:`Estimator`: :func:`recon.methods.run_method` here and now."""
    return run_method(method, lf, progress=progress, **options)


def jsonable(options: Mapping[str, Any]) -> dict[str, Any]:
    """``options`` as JSON would give them back (tuples become lists, anything odd a string)."""
    return json.loads(json.dumps(dict(options), default=str))


def check_options(method: str, options: Mapping[str, Any]) -> None:
    """Reject option values before any work starts, naming the value (a :class:`ReconError`).

    Only this check turns a ``ValueError`` into a user's error: one raised while the estimate runs is
    a bug and keeps its traceback.
    """
    rng = options.get("disparity_range")
    if rng is not None:
        try:
            low, high = (float(v) for v in rng)
        except (TypeError, ValueError):
            raise ReconError(f"disparity range {rng!r}: give two numbers, MIN and MAX") from None
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ReconError(f"disparity range ({low}, {high}): give finite MIN < MAX, pixels per view step")
    for name, value in options.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise ReconError(f"{method}: {name} = {value}: give a finite number")
    for name in ("step", "initial_step"):
        value = options.get(name)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < MIN_STEP_PX:
            raise ReconError(f"{method}: {name} = {value:g} px is finer than any estimate resolves and would make "
                             f"millions of candidate disparities; give at least {MIN_STEP_PX:g}, e.g. 0.02")
    sizes = [options.get("window")] + list(options.get("window_sizes") or [])
    for size in sizes:
        if isinstance(size, int) and not isinstance(size, bool) and size > MAX_WINDOW_PX:
            raise ReconError(f"{method}: window of {size} px is larger than {MAX_WINDOW_PX} px; give a smaller one")
    try:
        check_method_options(method, options)
    except (ValueError, TypeError) as error:
        raise ReconError(f"{method}: {error}") from None


def check_output_outside(source: str | os.PathLike, out_dir: str | os.PathLike) -> None:
    """Refuse a result folder that is the light-field folder itself or lies inside its views
    (``CAP/views``: the files written there would break the capture), naming both.

    Raises
    ------
    ReconError
    """
    source_path, out_path = Path(source).resolve(), Path(out_dir).resolve()
    where = ("the light-field folder" if out_path == source_path
             else "inside the views of" if out_path.is_relative_to(source_path / "views") else None)
    if where is not None:
        raise ReconError(f"{out_dir}: is {where} {source}; the results would mix with its data: give a folder of "
                         "its own for them")


#: The camera values metric depth needs (``Z = focal_px * pitch_mm / (d + d0)``).
METRIC_CAMERA = ("focal_px", "pitch_mm")


def metric_camera_missing(lf: str | os.PathLike | LightField) -> list[str]:
    """Which of :data:`METRIC_CAMERA` a light field does not record, without reading its views (a
    folder: its ``parameters.cfg``, the only place either layout keeps them)."""
    if isinstance(lf, LightField):
        return [name for name in METRIC_CAMERA if getattr(lf, name) is None]
    from recon.lf.params import camera_from_parameters, read_parameters

    cfg = Path(lf) / "parameters.cfg"
    if not cfg.is_file():
        return list(METRIC_CAMERA)
    _, camera = camera_from_parameters(read_parameters(cfg), path=cfg)
    return [name for name in METRIC_CAMERA if camera.get(name) is None]


def write_json_atomic(path: Path, record: Any) -> None:
    """Write ``record`` as indented JSON to ``path`` through a temporary file renamed over it."""
    from recon.lf.imageio import write_bytes_atomic

    write_bytes_atomic(path, (json.dumps(record, indent=2) + "\n").encode("utf-8"))


def reconstruct_to_folder(
    lf_dir: str | os.PathLike | LightField,
    out_dir: str | os.PathLike,
    *,
    method: str = DEFAULT_METHOD,
    options: Mapping[str, Any] | None = None,
    ply: str | os.PathLike | None = None,
    ply_kind: Literal["mesh", "points"] = "mesh",
    progress: ProgressCallback | None = None,
    estimate: Estimator | None = None,
    source: str | None = None,
    extra: Mapping[str, Any] | None = None,
    verify: bool = True,
    command: Sequence[str] | None = None,
) -> FolderResult:
    """Reconstruct one light field into ``out_dir`` (created if needed); see the module docstring.

    Parameters
    ----------
    lf_dir
        Light-field folder (benchmark or capture layout), or an already read :class:`LightField`.
    out_dir
        Result folder.
    method, options
        Method name (``recon.methods.METHODS``) and its keyword options, recorded in ``result.json``.
        ``options["disparity_range"]`` is ``None`` or ``(min, max)`` with ``min < max``.
    ply, ply_kind
        Also export a PLY ``"mesh"`` or ``"points"`` to this path (after ``result.json``).
    progress
        ``None`` or ``progress(fraction, message)`` (:mod:`recon.progress`).
    estimate
        How the disparity is computed (:data:`Estimator`); default :func:`run_in_process`.
    source
        What ``result.json`` records as the source (default: the light field's resolved folder). A
        batch that ships the views to a worker passes the folder the views came from.
    extra
        More keys for ``result.json`` (e.g. how the work was tiled); they must not clash.
    verify
        Check a capture's views against their journalled checksums (:func:`recon.lf.capture.read_capture`).
    command
        The command line recorded in ``result.json``'s ``provenance`` (default: this process's,
        :func:`recon.provenance.current_command`); a batch passes the command that started it.

    Raises
    ------
    recon.errors.LfrigError
        For an unreadable light field, a bad disparity range, or a failed export.
    """
    from recon.lf import read_lightfield
    from recon.provenance import current_command, utc_now

    started_utc, started = utc_now(), time.perf_counter()
    command = current_command() if command is None else [str(part) for part in command]
    # numba's start-up runs beside the decoding of the views (which leaves the interpreter free).
    warming = warm_in_background(method) if estimate is None and not isinstance(lf_dir, LightField) else None
    # An estimate in this process reads only the grey views (recon.methods): they are read as grey, the
    # centre view kept in its colours for the folder. A tiled one cuts the views as stored into tiles.
    if isinstance(lf_dir, LightField):
        lf = lf_dir
    else:  # read for this one estimate: the estimator lets the grey views go after the last step that
        # reads them (what follows here reads the centre view, kept in its colours, and the shapes)
        lf = read_lightfield(lf_dir, verify=verify, grey=estimate is None)
        lf.views_once = estimate is None
    if warming is not None:  # the rest of the warm-up (scipy's import) now, beside the checks and the first phase
        warming.begin_later()
    if lf.source is not None:
        check_output_outside(lf.source, out_dir)
    read_s = time.perf_counter() - started
    opts: dict[str, Any] = dict(options or {})
    check_options(method, opts)
    missing = metric_camera_missing(lf) if ply is not None else []
    if missing:
        raise ReconError(f"{lf.source or 'the light field'}: no {' or '.join(missing)} recorded (parameters.cfg), "
                         "so no metric PLY can be made; reconstruct without the PLY (drop --ply) and give the camera "
                         "to `lfrig export RESULT_DIR --ply OUT.ply --focal-px F --pitch-mm P`")
    if opts.get("disparity_range") is not None:
        opts["disparity_range"] = tuple(float(v) for v in opts["disparity_range"])
        problem = disparity_range_problem(opts["disparity_range"], grid=lf.grid_shape, image_shape=lf.image_shape)
        if problem is not None:
            raise ReconError(f"{problem} (pixels per view step)")
    out = writable_folder(out_dir, what="result folder")  # a file, read-only, full: now, not after the work
    if ply is not None:
        writable_file(ply, what="PLY")
    # One writer per result folder; the lock ends with the process, whatever way it ends.
    with FolderLock(out, what="reconstruction"):
        return _reconstruct_locked(lf, out, method=method, opts=opts, ply=ply, ply_kind=ply_kind,
                                   progress=progress, estimate=estimate, source=source, extra=extra,
                                   made={"command": command, "started_utc": started_utc, "read": read_s},
                                   warming=warming)


def _reconstruct_locked(lf: LightField, out: Path, *, method: str, opts: dict[str, Any], ply, ply_kind,
                        progress, estimate, source, extra, made: dict[str, Any],
                        warming: Warming | None = None) -> FolderResult:
    from recon.colour import colourise
    from recon.evaluate import score
    from recon.lf.imageio import write_png
    from recon.lf import read_ground_truth
    from recon.lf.pfm import write_pfm
    from recon.provenance import input_identity, lfrig_version, provenance

    gt = read_ground_truth(lf)  # before the work: a broken truth file fails now, not after the estimate
    if gt is not None and gt.shape != lf.image_shape:
        from recon.evaluate import describe_map

        raise ReconError(f"{lf.metadata.get('ground_truth')}: ground truth is {describe_map(gt)} but the views are "
                         f"{lf.image_shape[1]}x{lf.image_shape[0]}; remove or replace it")
    if gt is not None and not np.isfinite(gt).any():
        raise ReconError(f"{lf.metadata.get('ground_truth')}: ground truth has no finite value (nothing to score "
                         "against); remove or replace it")
    # The folder holds one run: the previous run's files go first, result.json before the rest, so
    # an interrupted run leaves a folder without result.json (clearly unfinished) and never old maps
    # beside new ones. The new result.json is renamed in last.
    clear_result(out)
    # While the estimate runs, two threads write the centre view's PNG (the input's own; OpenCV
    # encodes and the disk syncs without the interpreter lock) and ask git for the version that
    # result.json records (a child process: 20-40 ms of waiting, more under load).
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="lfrig-beside") as beside:
        centre = beside.submit(write_png, out / CENTRE_VIEW_PNG, lf.centre_view())
        version = beside.submit(lfrig_version)  # cached: provenance() below takes it from there
        started = time.perf_counter()
        if warming is not None:
            # what the estimate's first steps need (a long wait says why); the rest loads beside them
            warming.wait(progress)
        method_result = (estimate or run_in_process)(lf, method, opts, progress)
        seconds = time.perf_counter() - started
    centre.result()  # its error (a full disk) is raised here
    version.result()
    disparity = method_result.disparity
    written = time.perf_counter()
    write_pfm(out / DISPARITY_PFM, disparity)
    picture, shown = colourise(disparity, value_range=lf.disparity_range)
    write_png(out / DISPARITY_PNG, picture)
    files = [DISPARITY_PFM, DISPARITY_PNG, CENTRE_VIEW_PNG]
    if method_result.write_extras is not None:
        files += [Path(p).resolve().relative_to(out.resolve()).as_posix() for p in method_result.write_extras(out)]
    if source is None:
        source = str(lf.source.resolve()) if lf.source else None
    files.append(RESULT_JSON)
    listed = list(files)
    if ply is not None:
        try:  # a PLY inside the folder is this run's too (written after result.json)
            listed.append(Path(ply).resolve().relative_to(out.resolve()).as_posix())
        except ValueError:
            pass
    identity = input_identity(lf.source, known_sha256=lf.metadata.get("views_sha256"))
    if source is not None:  # the folder the views came from, not a worker's copy of it
        identity["path"] = source
    timings = {"read": made["read"], "estimate": seconds, "write": time.perf_counter() - written}
    record = ResultRecord(
        provenance=provenance(input=identity, timings_s=timings, command=made["command"],
                              started_utc=made["started_utc"]),
        method=method, options=jsonable(method_result.options), source=source,
        image=[lf.image_shape[1], lf.image_shape[0]], grid=list(lf.grid_shape),
        focal_px=lf.focal_px, pitch_mm=lf.pitch_mm, disparity_offset=lf.disparity_offset,
        principal_point_px=list(lf.principal_point_px) if lf.principal_point_px else None,
        disparity_png_range=list(shown), seconds=round(seconds, 3),
        scores=score(disparity, gt) if gt is not None else None, files=listed, extra=dict(extra or {}),
    )
    write_record(out, record)
    folder = FolderResult(out_dir=out, record=record, files=files)
    if ply is not None:
        from recon.export import export_result

        folder.export = export_result(out, ply, kind=ply_kind, command=made["command"])
        folder.ply = Path(ply)
    return folder
