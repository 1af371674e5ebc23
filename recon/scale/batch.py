"""Many captures on a cluster: one task per capture (reconstruct + export), skip what is complete.

Each capture ``CAPTURE_DIR`` goes to ``OUT_DIR/<folder name of CAPTURE_DIR>/``: the result folder of
:func:`recon.pipeline.reconstruct_to_folder` (``disparity.pfm``, ``disparity.png``,
``centre_view.png``, ``result.json``), the PLY (``mesh.ply`` or ``points.ply``) and, written last,
``batch.json``: the marker that says the folder is complete.

**Complete** means: ``batch.json`` parses, was made for the same request (method, options, export,
tile), for the same input (a fingerprint of the light-field files' names, sizes and modification
times), and every output it lists exists with the recorded size and SHA-256. The marker is replaced
atomically and removed before a capture is redone, so a run that dies half-way leaves an incomplete
folder, which the next run redoes.

**Data transfer** (``docs/scale-out.md``):

- ``shared``: workers read ``CAPTURE_DIR`` and write ``OUT_DIR`` themselves. Both must be the same
  absolute paths on every worker and on this machine (a shared filesystem). A local cluster uses this.
- ``ship``: this machine reads the light-field files and sends their bytes with the task; the worker
  reconstructs in a temporary folder and sends the output files back; this machine writes them. The
  workers need no access to any path (default with ``--scheduler``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

from recon.pipeline import metric_camera_missing, reconstruct_to_folder, write_json_atomic
from recon.provenance import current_command, lightfield_files, provenance, utc_now
from recon.result import RESULT_JSON
from recon.scale import ScaleError

MARKER = "batch.json"
SUMMARY = "batch-summary.json"
MARKER_FORMAT = "lfrig-batch-task"
MARKER_VERSION = 1

#: How often a capture whose worker was lost (killed, out of memory, its shipped views gone with it)
#: is submitted again before it is reported as failed.
MAX_ATTEMPTS = 3
#: How long the batch waits for a worker when none is connected to the scheduler, seconds.
NO_WORKER_TIMEOUT_S = 60.0
#: How long a lost connection to the scheduler may take to come back before the batch stops, seconds.
SCHEDULER_GRACE_S = 10.0

Transfer = Literal["shared", "ship"]
Status = Literal["ok", "skipped", "failed"]

# Only the files a light-field reader uses (recon.provenance.lightfield_files) are fingerprinted and
# shipped, not e.g. a benchmark's high-resolution truth.


# --------------------------------------------------------------------------------------------------
# the request and its outcome
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BatchRequest:
    """What to do with every capture of a batch.

    ``export`` is ``"mesh"``, ``"points"`` or ``None`` (no PLY); ``tile`` is the tile side in pixels
    or ``None`` (untiled), ``halo`` the tiles' halo (``None``: the method's).
    """

    method: str = "baseline"
    options: dict[str, Any] = field(default_factory=dict)
    export: Literal["mesh", "points"] | None = "mesh"
    tile: int | None = None
    halo: int | None = None

    def identity(self) -> dict[str, Any]:
        """The part that decides the outputs (compared with a finished folder's marker)."""
        return json.loads(json.dumps({"method": self.method, "options": self.options, "export": self.export,
                                      "tile": self.tile, "halo": self.halo}))

    @property
    def ply_name(self) -> str | None:
        return None if self.export is None else f"{self.export}.ply"


@dataclass
class CaptureJob:
    """One capture: its folder as this machine sees it and its output folder."""

    name: str
    source: Path
    out_dir: Path


@dataclass
class Outcome:
    """How one capture went. ``seconds``: wall time of its task (for a skipped one, of the run that
    made it); ``scores``: :func:`recon.evaluate.score` when the capture has ground truth."""

    name: str
    source: str
    out_dir: str
    status: Status
    seconds: float | None = None
    scores: dict[str, float] | None = None
    error: str | None = None
    detail: str | None = None
    worker: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def plan_jobs(captures: Sequence[str | os.PathLike], out_dir: str | os.PathLike) -> list[CaptureJob]:
    """One :class:`CaptureJob` per capture, output ``out_dir/<folder name>``.

    Raises
    ------
    ScaleError
        Two captures with the same folder name (their outputs would collide), or a capture path
        that is not a folder.
    """
    out = Path(out_dir)
    jobs: list[CaptureJob] = []
    seen: dict[str, Path] = {}
    for capture in captures:
        source = Path(capture).resolve()
        if not source.is_dir():
            raise ScaleError(f"{capture}: not a folder; pass light-field folders (benchmark or capture layout)")
        name = source.name
        if name in seen:
            raise ScaleError(
                f"{seen[name]} and {source} have the same folder name {name!r}, so their results would share "
                f"{out / name}; rename one, or run them in separate batches"
            )
        seen[name] = source
        jobs.append(CaptureJob(name=name, source=source, out_dir=(out / name).resolve()))
    return jobs


# --------------------------------------------------------------------------------------------------
# inputs, outputs, completeness
# --------------------------------------------------------------------------------------------------


def input_fingerprint(source: Path) -> str:
    """SHA-256 over the light-field files' names, sizes and modification times (cheap: no reading)."""
    digest = hashlib.sha256()
    for rel in lightfield_files(source):
        st = (source / rel).stat()
        digest.update(f"{rel}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def file_digest(path: Path) -> dict[str, Any]:
    """``{"bytes": size, "sha256": hex}`` of a file."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return {"bytes": path.stat().st_size, "sha256": digest.hexdigest()}


def check_complete(job: CaptureJob, request: BatchRequest, fingerprint: str) -> tuple[dict[str, Any] | None, str]:
    """``(marker, "")`` when ``job.out_dir`` is complete for this request and input, else
    ``(None, why not)``."""
    path = job.out_dir / MARKER
    if not path.is_file():
        return None, "not done yet"
    from recon.errors import LfrigError
    from recon.lf.imageio import read_bytes

    try:
        marker = json.loads(read_bytes(path).decode("utf-8"))
    except (LfrigError, ValueError, RecursionError) as error:
        return None, f"{path} unreadable ({error})"
    if not isinstance(marker, dict):
        return None, f"{path} is not a JSON object"
    if marker.get("format") != MARKER_FORMAT or marker.get("version") != MARKER_VERSION:
        return None, f"{path} is not a version-{MARKER_VERSION} {MARKER_FORMAT} marker"
    if marker.get("request") != request.identity():
        return None, "made with other options"
    if marker.get("input") != fingerprint:
        return None, "the light-field files changed since"
    outputs = marker.get("outputs") or {}
    if RESULT_JSON not in outputs:
        return None, f"{path} lists no {RESULT_JSON}"
    for name, recorded in outputs.items():
        file = job.out_dir / name
        if not file.is_file():
            return None, f"{file} is missing"
        if file.stat().st_size != recorded.get("bytes") or file_digest(file) != recorded:
            return None, f"{file} changed or is truncated"
    return marker, ""


def write_marker(job: CaptureJob, request: BatchRequest, fingerprint: str, outcome: Outcome,
                 files: Sequence[str]) -> None:
    """Checksum the outputs and write ``batch.json`` atomically (the last write of a capture)."""
    marker = {
        "format": MARKER_FORMAT, "version": MARKER_VERSION, "capture": job.name, "source": str(job.source),
        "request": request.identity(), "input": fingerprint,
        "outputs": {name: file_digest(job.out_dir / name) for name in sorted(files)},
        "seconds": outcome.seconds, "scores": outcome.scores, "worker": outcome.worker,
        "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    write_json_atomic(job.out_dir / MARKER, marker)


# --------------------------------------------------------------------------------------------------
# the task (runs on a worker)
# --------------------------------------------------------------------------------------------------


def _worker_address() -> str | None:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return None


def reconstruct_capture(
    source: str,
    out_dir: str | None,
    request: BatchRequest,
    payload: dict[str, bytes] | None = None,
    threads: int | None = None,
    command: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Reconstruct (and export) one capture; the cluster task. Never raises for a bad capture.

    Shared mode (``payload is None``): read ``source``, write into ``out_dir``. Ship mode: ``payload``
    maps relative paths to the light-field files' bytes; the work happens in a temporary folder and
    the output files come back as ``files`` (name -> bytes). ``threads`` caps numba/OpenCV threads.
    ``command`` is the batch's command line, recorded in ``result.json``'s provenance.

    Returns
    -------
    ``{"status": "ok" | "failed", "seconds", "scores", "error", "detail", "worker", "names"}`` and, in
    ship mode, ``"files"``.
    """
    from recon.errors import LfrigError
    from recon.scale.cluster import limit_threads

    started = time.perf_counter()
    report: dict[str, Any] = {"status": "failed", "scores": None, "error": None, "detail": None,
                              "worker": _worker_address(), "names": []}
    scratch = tempfile.mkdtemp(prefix="lfrig-batch-") if payload is not None else None
    try:
        limit_threads(threads)
        if payload is not None:
            lf_dir = Path(scratch) / "input" / Path(source).name
            for rel, data in payload.items():
                target = lf_dir / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(data)
            target_dir = Path(scratch) / "output"
        else:
            lf_dir = Path(source)
            target_dir = Path(out_dir)
        extra: dict[str, Any] = {}
        estimate = None
        if request.tile:
            from recon.scale.tiles import tiled_estimator

            tiling: dict[str, Any] = {}
            extra["tiling"] = tiling
            estimate = tiled_estimator(tile=request.tile, halo=request.halo, threads=threads,
                                       record=tiling)
        ply = target_dir / request.ply_name if request.ply_name else None
        folder = reconstruct_to_folder(
            lf_dir, target_dir, method=request.method, options=request.options, ply=ply,
            ply_kind=request.export or "mesh", estimate=estimate, source=str(source), extra=extra, command=command,
        )
        names = list(folder.files) + ([request.ply_name] if ply is not None else [])
        report.update(status="ok", scores=folder.record.scores, names=names)
        if payload is not None:
            report["files"] = {name: (target_dir / name).read_bytes() for name in names}
    except LfrigError as error:
        report["error"] = str(error)
    except Exception as error:  # noqa: BLE001 - a bug on one capture must not stop the batch
        report["error"] = f"{type(error).__name__}: {error}"
        report["detail"] = traceback.format_exc()
    finally:
        if scratch is not None and report["error"]:  # name the user's folder, not the worker's copy
            report["error"] = report["error"].replace(str(Path(scratch) / "input" / Path(source).name), source)
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
    report["seconds"] = round(time.perf_counter() - started, 3)
    return report


# --------------------------------------------------------------------------------------------------
# the driver (runs here)
# --------------------------------------------------------------------------------------------------


def read_payload(source: Path) -> dict[str, bytes]:
    """The light-field files' bytes by relative path, for ship mode."""
    files = lightfield_files(source)
    if not files:
        raise ScaleError(f"{source}: no light-field files (input_CamNNN.png or manifest.jsonl + views/)")
    from recon.lf.imageio import MAX_IMAGE_BYTES, read_bytes

    return {rel: read_bytes(source / rel, error=ScaleError, max_bytes=MAX_IMAGE_BYTES) for rel in files}


def _finish(job: CaptureJob, request: BatchRequest, fingerprint: str, report: dict[str, Any],
            transfer: Transfer) -> Outcome:
    outcome = Outcome(name=job.name, source=str(job.source), out_dir=str(job.out_dir), status="failed",
                      seconds=report.get("seconds"), scores=report.get("scores"), error=report.get("error"),
                      detail=report.get("detail"), worker=report.get("worker"))
    if report.get("status") != "ok":
        return outcome
    names = report["names"]
    if transfer == "ship":
        from recon.lf.imageio import write_bytes_atomic
        from recon.lf.lock import FolderLock
        from recon.result import clear_result

        with FolderLock(job.out_dir, what="reconstruction"):
            clear_result(job.out_dir)  # one run per folder, as reconstruct_to_folder does on the worker
            for name in sorted(names, key=lambda n: n == RESULT_JSON):  # result.json last, as on the worker
                (job.out_dir / name).parent.mkdir(parents=True, exist_ok=True)
                write_bytes_atomic(job.out_dir / name, report["files"][name])
    missing = [name for name in names if not (job.out_dir / name).is_file()]
    if missing:
        outcome.error = (
            f"worker {outcome.worker} wrote {', '.join(missing)} but {job.out_dir} does not show them here: "
            "OUT_DIR must be on a filesystem shared at the same path by the workers and this machine, or "
            "use --transfer ship"
        )
        return outcome
    outcome.status = "ok"
    write_marker(job, request, fingerprint, outcome, names)
    return outcome


@dataclass
class BatchPlan:
    """A batch split into captures already complete (their outcomes) and captures to run."""

    jobs: list[CaptureJob]
    out_dir: Path
    request: BatchRequest
    done: list[Outcome]
    todo: list[tuple[CaptureJob, str]]  # (job, input fingerprint)
    command: list[str] = field(default_factory=current_command)  # recorded in every result and the summary
    started_utc: str = field(default_factory=utc_now)


def prepare_batch(captures: Sequence[str | os.PathLike], out_dir: str | os.PathLike, *,
                  request: BatchRequest, force: bool = False) -> BatchPlan:
    """Check every capture's output folder (:func:`check_complete`); no cluster needed.

    ``force`` redoes complete captures too. The marker of every capture to run is removed now, so
    its folder reads as incomplete until the run writes a new one.

    Raises
    ------
    ScaleError
        When a PLY is asked for (``request.export``) and a capture does not record the focal length
        and pitch that metric depth needs: before any work, naming the captures.
    """
    started = utc_now()
    jobs = plan_jobs(captures, out_dir)
    if request.export is not None:
        lacking = {job.name: metric_camera_missing(job.source) for job in jobs}
        lacking = {name: missing for name, missing in lacking.items() if missing}
        if lacking:
            which = "; ".join(f"{name} has no {' or '.join(missing)}" for name, missing in lacking.items())
            raise ScaleError(f"{which} (parameters.cfg), so no metric PLY can be made: run the batch with "
                             "--export none for disparity only, or import the views again with --focal-px and "
                             "--pitch-mm")
    done: list[Outcome] = []
    todo: list[tuple[CaptureJob, str]] = []
    for job in jobs:
        fingerprint = input_fingerprint(job.source)
        marker, _ = (None, "") if force else check_complete(job, request, fingerprint)
        if marker is not None:
            done.append(Outcome(name=job.name, source=str(job.source), out_dir=str(job.out_dir), status="skipped",
                                seconds=marker.get("seconds"), scores=marker.get("scores"),
                                worker=marker.get("worker")))
        else:
            (job.out_dir / MARKER).unlink(missing_ok=True)
            todo.append((job, fingerprint))
    return BatchPlan(jobs=jobs, out_dir=Path(out_dir), request=request, done=done, todo=todo, started_utc=started)


def run_batch(
    client: Any,
    plan: BatchPlan,
    *,
    transfer: Transfer = "shared",
    threads: int | None = None,
    max_in_flight: int | None = None,
    on_outcome: Callable[[Outcome, int, int], None] | None = None,
    on_note: Callable[[str], None] | None = None,
    no_worker_timeout_s: float = NO_WORKER_TIMEOUT_S,
) -> list[Outcome]:
    """Run the captures of ``plan`` still to do on ``client`` (a ``distributed.Client``; may be
    ``None`` when there is nothing to do); return one :class:`Outcome` per capture, in the order given.

    Parameters
    ----------
    plan
        From :func:`prepare_batch`.
    transfer
        ``"shared"`` or ``"ship"`` (module docstring).
    threads
        numba/OpenCV threads per task (``None``: the worker's setting).
    max_in_flight
        Captures submitted but not finished at any time (default twice the cluster's threads), so
        that shipped views do not pile up in the workers' memory.
    on_outcome
        ``on_outcome(outcome, done, total)`` as each capture finishes (skipped ones first).
    on_note
        ``on_note(text)`` for what happens to the cluster: a lost worker's capture submitted again, no
        worker connected (and connected again).
    no_worker_timeout_s
        With no worker connected for this long, the captures not run yet are reported as failed and
        the batch stops.

    A capture whose worker dies (killed, out of memory, and with it the views shipped to it) is
    submitted again, up to :data:`MAX_ATTEMPTS` times in all. Losing the scheduler raises
    :class:`ScaleError` (the summary is not written; complete captures keep their markers).

    A capture that fails (bad folder, a bug, a worker that died) is an outcome with ``status
    "failed"`` and its ``error``; the others go on. ``OUT_DIR/batch-summary.json`` lists all outcomes.
    """
    if transfer not in ("shared", "ship"):
        raise ValueError(f"transfer must be 'shared' or 'ship'; got {transfer!r}")
    request = plan.request
    started = time.perf_counter()
    plan.out_dir.mkdir(parents=True, exist_ok=True)
    outcomes: dict[str, Outcome] = {}
    total = len(plan.jobs)

    def report(outcome: Outcome) -> None:
        outcomes[outcome.name] = outcome
        if on_outcome:
            on_outcome(outcome, len(outcomes), total)

    for outcome in plan.done:
        report(outcome)
    if plan.todo:
        if client is None:
            raise ValueError(f"{len(plan.todo)} capture(s) to run but no client")
        _run(client, plan, transfer=transfer, threads=threads, max_in_flight=max_in_flight, report=report,
             note=on_note, no_worker_timeout_s=no_worker_timeout_s)
    ordered = [outcomes[job.name] for job in plan.jobs]
    made = provenance(input={"kind": "batch", "path": str(plan.out_dir.resolve()),
                             "captures": {job.name: _recorded_input(job) for job in plan.jobs}},
                      timings_s={"total": time.perf_counter() - started}, command=plan.command,
                      started_utc=plan.started_utc)
    write_json_atomic(plan.out_dir / SUMMARY, {"request": request.identity(), "transfer": transfer,
                                               "captures": [o.as_dict() for o in ordered], "provenance": made})
    return ordered


def _recorded_input(job: CaptureJob) -> dict[str, Any] | None:
    """The input identity a capture's ``result.json`` records (its provenance), or ``None``."""
    try:
        record = json.loads((job.out_dir / RESULT_JSON).read_text(encoding="utf-8"))
        return (record.get("provenance") or {}).get("input")
    except (OSError, ValueError, AttributeError):
        return None


@dataclass
class _Task:
    job: CaptureJob
    fingerprint: str
    attempt: int = 1
    sends: int = 0  # failed attempts to send it (the views to a worker, or the task to the scheduler)
    payload: Any = None  # the scattered views (ship mode): kept referenced while the task runs


def _lost_with_worker(error: BaseException) -> bool:
    """Whether a task's exception means its worker (or the data shipped to it) was lost, rather than
    a failure of the capture itself: such a task is submitted again."""
    from concurrent.futures import CancelledError

    from distributed.comm.core import CommClosedError

    return isinstance(error, (CancelledError, CommClosedError, ConnectionError))


def _run(client: Any, plan: BatchPlan, *, transfer: Transfer, threads: int | None, max_in_flight: int | None,
         report: Callable[[Outcome], None], note: Callable[[str], None] | None = None,
         attempts: int = MAX_ATTEMPTS, no_worker_timeout_s: float = NO_WORKER_TIMEOUT_S,
         poll_s: float = 0.2) -> None:
    """Submit the captures, at most ``window`` at a time; resubmit one whose worker was lost (up to
    ``attempts`` times); stop when no worker is connected for ``no_worker_timeout_s``; raise
    :class:`ScaleError` when the scheduler is gone."""
    from collections import deque

    from distributed import KilledWorker
    from distributed.comm.core import CommClosedError

    say = note or (lambda text: None)
    request = plan.request
    address = getattr(client.scheduler, "address", "?")
    window = max_in_flight or max(2, 2 * (sum(client.nthreads().values()) or 1))
    pending: deque[_Task] = deque(_Task(job, fingerprint) for job, fingerprint in plan.todo)
    running: dict[Any, _Task] = {}
    no_worker_since: float | None = None
    disconnected_since: float | None = None
    finished: set[str] = set()

    def report_one(outcome: Outcome) -> None:
        finished.add(outcome.name)
        report(outcome)

    def failed(task: _Task, error: str) -> None:
        report_one(Outcome(name=task.job.name, source=str(task.job.source), out_dir=str(task.job.out_dir),
                       status="failed", error=error))

    def workers() -> int:
        try:
            return len(client.scheduler_info().get("workers", {}))
        except Exception:  # noqa: BLE001 - asked while the connection is down: treat as none
            return 0

    def submit(task: _Task) -> bool:
        """Submit one capture; False when sending failed (the task is back in ``pending``)."""
        job = task.job
        try:
            payload = read_payload(job.source) if transfer == "ship" else None
        except (OSError, ScaleError) as error:
            failed(task, str(error))
            return True
        try:
            if payload is not None:
                # straight to a worker, not through the scheduler's graph (a list, so the dict is one piece)
                task.payload = client.scatter([payload], hash=False)[0]
            future = client.submit(reconstruct_capture, str(job.source),
                                   None if transfer == "ship" else str(job.out_dir), request, task.payload, threads,
                                   plan.command, pure=False, key=f"lfrig-capture-{job.name}-{os.urandom(4).hex()}")
        except (CommClosedError, OSError) as error:
            # the worker chosen for the views (or the scheduler) went away during the call. distributed
            # raises a bare OSError when it cannot reach a worker the scheduler has not yet dropped
            # (a killed one, for up to its connect timeout): try again, a bounded number of times;
            # if it was the scheduler, the loop's status check stops the batch
            task.payload = None
            task.sends += 1
            if task.sends >= attempts:
                failed(task, f"sending it to a worker failed {task.sends} times ({type(error).__name__}: {error}); "
                             "check the workers' logs and run the same command again")
                return True
            pending.appendleft(task)
            say(f"{job.name}: sending it failed ({type(error).__name__}); trying again "
                f"(attempt {task.sends + 1} of {attempts})")
            return False
        running[future] = task
        return True

    def release(future: Any, task: _Task) -> None:
        future.release()
        if task.payload is not None:
            task.payload.release()
            task.payload = None

    def scheduler_lost() -> ScaleError:
        return ScaleError(
            f"lost the connection to the Dask scheduler at {address}; {len(plan.todo) - len(finished)} capture(s) "
            "were not finished. Start the scheduler and workers again and run the same command: complete "
            "captures are skipped"
        )

    def loop() -> None:
        nonlocal no_worker_since, disconnected_since
        while pending or running:
            status = getattr(client, "status", "running")
            if status != "running":
                now = time.monotonic()
                disconnected_since = disconnected_since or now
                if status in ("closed", "closing", "failed") or now - disconnected_since > SCHEDULER_GRACE_S:
                    raise scheduler_lost()
            else:
                disconnected_since = None
            count = workers() if status == "running" else 0
            if count == 0:
                now = time.monotonic()
                if no_worker_since is None:
                    no_worker_since = now
                    say(f"no Dask worker is connected to {address}; waiting up to {no_worker_timeout_s:.0f} s for one "
                        f"(start one with `dask worker {address} --nthreads 1`)")
                elif now - no_worker_since > no_worker_timeout_s:
                    left = list(running.values()) + list(pending)
                    for future, task in list(running.items()):
                        future.cancel()
                        release(future, task)
                    running.clear()
                    pending.clear()
                    why = (f"not run: no Dask worker was connected to {address} for {no_worker_timeout_s:.0f} s; "
                           "start workers and run the same command again")
                    say(f"no Dask worker for {no_worker_timeout_s:.0f} s: stopping; {len(left)} capture(s) not run")
                    for task in left:
                        failed(task, why)
                    break
            elif no_worker_since is not None:
                no_worker_since = None
                say(f"{count} Dask worker(s) connected again; going on")
            while count and pending and len(running) < window:
                if not submit(pending.popleft()):
                    time.sleep(poll_s)
                    break
            if not running:
                time.sleep(poll_s)
                continue
            done = [future for future in running if future.done()]  # finished, failed or cancelled
            if not done:
                time.sleep(poll_s)
                continue
            for future in done:
                task = running.pop(future)
                try:
                    result = future.result()
                except KilledWorker as error:  # this capture's task took several workers down with it
                    result = {"status": "failed", "seconds": None,
                              "error": f"its task killed {error.args[0] if error.args else 'several'} worker(s) in a row "
                                       "(out of memory?); not tried again"}
                except Exception as error:  # noqa: BLE001 - a lost worker, or a task that raised
                    if getattr(client, "status", "running") != "running":
                        release(future, task)
                        pending.appendleft(task)
                        raise scheduler_lost() from None
                    if _lost_with_worker(error) and task.attempt < attempts:
                        release(future, task)
                        task.attempt += 1
                        say(f"{task.job.name}: its worker was lost ({type(error).__name__}); running it again "
                            f"(attempt {task.attempt} of {attempts})")
                        pending.appendleft(task)
                        continue
                    reason = f"lost with its worker {attempts} times; " if _lost_with_worker(error) else ""
                    result = {"status": "failed", "error": f"{reason}{type(error).__name__}: {error}", "seconds": None}
                release(future, task)
                report_one(_finish(task.job, request, task.fingerprint, result, transfer))

    try:
        loop()
    except (CommClosedError, ConnectionError):  # the scheduler went away mid-call (a status query, a release)
        deadline = time.monotonic() + SCHEDULER_GRACE_S
        while getattr(client, "status", "running") == "running" and time.monotonic() < deadline:
            time.sleep(poll_s)
        if getattr(client, "status", "running") == "running":
            raise  # not the scheduler: a bug, keep the traceback
        raise scheduler_lost() from None



def format_summary(outcomes: Sequence[Outcome]) -> str:
    """The table printed at the end: capture, status, time, MSE x100 and BadPix 0.07 where scored;
    then each failure's error."""
    header = ("capture", "status", "time s", "MSE x100", "BadPix 0.07 %")
    rows = []
    for o in outcomes:
        s = o.scores or {}
        rows.append((o.name, o.status, "" if o.seconds is None else f"{o.seconds:.1f}",
                     f"{s['mse_x100']:.3f}" if "mse_x100" in s else "-",
                     f"{s['badpix_0.07']:.2f}" if "badpix_0.07" in s else "-"))
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    line = lambda r: "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))  # noqa: E731
    out = [line(header), "  ".join("-" * w for w in widths), *map(line, rows)]
    counts = {status: sum(o.status == status for o in outcomes) for status in ("ok", "skipped", "failed")}
    out.append(f"{counts['ok']} done, {counts['skipped']} already complete, {counts['failed']} failed")
    for o in outcomes:
        if o.status == "failed":
            out.append(f"FAILED {o.name} ({o.source}): {o.error}")
    return "\n".join(out)
