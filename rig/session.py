"""The capture session: the one place that drives both the stage and the camera.

For each view of the grid, in scan order: move (with a backlash take-up move when needed), wait until
the stage reports ``Idle`` at the target, wait the settle time, check that it is still idle there,
trigger the camera, write the frame atomically and journal it (:class:`recon.lf.capture.CaptureWriter`).
A frame is never taken while the stage moves.

Resuming: the same command on the same folder takes only the views the journal does not have (whose
files are on disk with the journalled checksum); with other settings the writer refuses and says
which differ. A resume must continue in the machine frame the capture started in: it homes first
(the default), or, without homing, proves the frame is unchanged (the controller did not reset or
lock since, and the stage stands where the journal's last view was read back) and otherwise refuses
(:class:`FrameNotProvenError`) before anything moves.

Interrupting: the first Ctrl-C (SIGINT) lets the current view finish and then stops cleanly (during a
backlash take-up move, the view it leads to: the stage stops on the journal's last view, where a
resume without homing looks for it); a second one stops the stage at once (feed hold, then soft reset)
and raises :class:`CaptureInterrupted`.

Progress goes to ``progress(fraction, message)`` (:mod:`recon.progress`); a human-readable log is
appended to ``OUT_DIR/session.log``.
"""

from __future__ import annotations

import json
import math
import signal
import sys
import threading
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Sequence, TextIO

from recon.progress import ProgressCallback, report
from rig.errors import RigError
from rig.clock import Clock, SystemClock
from rig.grid import GridSpec, Move, check_limits, plan_moves
from recon.lf.capture import CaptureWriter
from recon.lf.lock import FolderLock
from rig.protocols import Camera, Stage

LOG_NAME = "session.log"


class CaptureAborted(RigError):
    """A device error stopped the capture; the views taken so far are kept for a resume."""


class CaptureInterrupted(RigError):
    """A second Ctrl-C stopped the stage at once."""


class StageNotSettledError(RigError):
    """The stage was not idle at the target when the frame was due."""


class FrameNotProvenError(RigError):
    """A resume without homing cannot show that the stage is in the capture's machine frame."""


def check_machine_frame(
    stage: Stage, completed: dict[tuple[int, int], dict[str, Any]], *, tolerance_mm: float, path: Path
) -> None:
    """Refuse to resume without homing unless the machine frame is proven: homed through this
    connection (``stage.homed``), or unchanged: no reset or alarm lock seen by the driver
    (``stage.machine_frame_doubt()``) and the stage at the position read back for the journal's last
    view. Nothing to prove for a fresh capture."""
    if not completed or getattr(stage, "homed", False):  # homed since power-up: the frame is the switches'
        return
    advice = (
        "home it: run the same command without --no-home (with homing disabled, $22=0, enable it and home, or "
        "capture into a new folder)"
    )
    doubt_of = getattr(stage, "machine_frame_doubt", None)
    doubt = doubt_of() if callable(doubt_of) else None
    if doubt:
        raise FrameNotProvenError(
            f"cannot prove the stage is in the machine frame {path} was captured in: {doubt}; "
            f"resuming there would shift every new view. {advice[0].upper()}{advice[1:]}"
        )
    last = max(completed.values(), key=lambda record: str(record.get("time", "")))
    readback = last.get("readback_mm")
    here = stage.position()
    if readback is None or max(abs(a - b) for a, b in zip(here, readback)) > tolerance_mm:
        raise FrameNotProvenError(
            f"cannot prove the stage is in the machine frame {path} was captured in: it is at {_fmt(here)}, but the "
            f"last view was read back at {_fmt(readback)}, and GRBL cannot tell whether it moved or restarted its "
            f"position since (a stopped move, a reset). {advice[0].upper()}{advice[1:]}"
        )


@dataclass
class SessionResult:
    path: Path
    total: int
    completed: int  # views on disk now
    taken: int  # views taken in this run
    interrupted: bool  # stopped by a first Ctrl-C (or ``should_stop``) before the end
    elapsed_s: float

    @property
    def complete(self) -> bool:
        return self.completed == self.total


class SessionLog:
    """Appends timestamped lines to ``session.log`` (flushed at once, so a crash keeps them)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = open(path, "a", encoding="utf-8")

    def __call__(self, message: str) -> None:
        stamp = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
        self._file.write(f"{stamp}  {message}\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


class _HardStop(BaseException):
    """Raised from the SIGINT handler on the second Ctrl-C (BaseException: nothing swallows it)."""


class _Interrupts:
    """First SIGINT: set a flag. Second: raise :class:`_HardStop`, but not in the middle of writing a
    view (it is raised right after the write)."""

    def __init__(self, log: Callable[[str], None], stream: TextIO | None) -> None:
        self.count = 0
        self.in_write = False
        self.pending = False
        #: Set when the hard stop is raised: later Ctrl-Cs must not interrupt the stop itself.
        self.hard_stopping = False
        self.log = log
        self.stream = stream
        self._old: Any = None
        self._installed = False

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handler)
            self._installed = True

    def uninstall(self) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._old)
            self._installed = False

    def _say(self, text: str) -> None:
        self.log(text)
        if self.stream is not None:
            self.stream.write("\n" + text + "\n")
            self.stream.flush()

    def _handler(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.count == 1:
            self._say("Ctrl-C: finishing the current view, then stopping (Ctrl-C again stops the stage at once)")
            return
        if self.hard_stopping:
            # A third Ctrl-C while the stage is being stopped: raising again would abort the feed
            # hold and soft reset half-sent. Say so and let the stop finish.
            self._say("Ctrl-C: already stopping the stage (feed hold + soft reset), please wait")
            return
        if self.in_write:
            self.pending = True
            return
        self.hard_stopping = True
        raise _HardStop()

    @property
    def stop_requested(self) -> bool:
        return self.count >= 1

    def end_write(self) -> None:
        self.in_write = False
        if self.pending:
            self.pending = False
            self.hard_stopping = True
            raise _HardStop()


def build_header(
    spec: GridSpec,
    *,
    camera_request: dict[str, Any] | None = None,
    camera_settings: dict[str, Any] | None = None,
    stage_settings: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The manifest header: ``settings`` holds what a resume must match (grid and requested camera
    settings); the read-back device settings are recorded but may differ between runs."""
    header: dict[str, Any] = {
        "grid": {"rows": spec.rows, "cols": spec.cols, "pitch_mm": spec.pitch_mm},
        "settings": {**spec.settings(), **{f"camera.{k}": v for k, v in (camera_request or {}).items()}},
        "camera": dict(camera_settings or {}),
        "stage": dict(stage_settings or {}),
    }
    header.update(extra or {})
    return json.loads(json.dumps(header, default=_json_default))


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    return str(value)


def run_capture(
    path: str | Path,
    *,
    stage: Stage,
    camera: Camera,
    grid: GridSpec,
    settle_s: float = 0.2,
    feed_mm_min: float | None = None,
    home: bool = True,
    limits_mm: Sequence[tuple[float, float]] | None = None,
    tolerance_mm: float | None = None,
    camera_request: dict[str, Any] | None = None,
    header_extra: dict[str, Any] | None = None,
    clock: Clock | None = None,
    progress: ProgressCallback | None = None,
    handle_sigint: bool = True,
    should_stop: Callable[[], bool] | None = None,
    lock: FolderLock | None = None,
) -> SessionResult:
    """Capture (or resume) the grid into the folder ``path``.

    Parameters
    ----------
    stage, camera
        Open devices (:class:`rig.protocols.Stage`, :class:`rig.protocols.Camera`); not closed here.
    grid
        The scan; its :meth:`GridSpec.settings` must match a folder being resumed.
    settle_s
        Wait after the stage reports Idle at the target before triggering (vibrations die out).
    feed_mm_min
        ``None`` for rapid moves (``G0``), else the feed of ``G1`` moves.
    home
        Run the homing cycle first (recommended: a resumed session may follow an alarm or reset).
    limits_mm
        Per-axis ``(min, max)`` travel; default ``stage.limits_mm()`` when the stage has it. Every
        move is checked before the first one starts.
    tolerance_mm
        Largest allowed drift between the read-back position after settling and the one before.
    camera_request
        Requested camera settings (exposure, gain, size...): part of the settings a resume must match.
    progress
        ``progress(fraction, message)`` after each view (:mod:`recon.progress`), or ``None``.
    should_stop
        Called after each view; returning True stops like a first Ctrl-C (for embedding and tests).
    lock
        The folder's lock (:class:`recon.lf.lock.FolderLock`) when the caller took it already (the
        command line takes it before it opens the devices); else it is taken here.

    Returns
    -------
    SessionResult
        ``interrupted`` is True after a clean stop on request; ``complete`` when every view is on disk.

    Raises
    ------
    recon.errors.CaptureLayoutError
        The folder holds a capture with other settings (nothing moved).
    recon.lf.lock.FolderLockedError
        Another capture is running in the folder (nothing moved).
    rig.grid.GridError
        A move lies outside the stage's travel (nothing moved).
    CaptureAborted
        A stage or camera error; its ``__cause__`` is the device's error. The views on disk are kept.
    CaptureInterrupted
        A second Ctrl-C: feed hold and soft reset were sent.
    FrameNotProvenError
        ``home=False`` on a folder being resumed, and the machine frame is not proven unchanged
        (:func:`check_machine_frame`). Nothing moved.
    """
    _check_session_values(settle_s=settle_s, feed_mm_min=feed_mm_min, tolerance_mm=tolerance_mm)
    path = Path(path)
    clock = clock if clock is not None else SystemClock()
    tolerance = tolerance_mm if tolerance_mm is not None else getattr(stage, "tolerance_mm", 0.005)
    stage_settings = stage.settings() if hasattr(stage, "settings") else {}
    header = build_header(
        grid,
        camera_request=camera_request,
        camera_settings=camera.settings(),
        stage_settings=stage_settings,
        extra=header_extra,
    )
    writer = CaptureWriter(path, header=header, lock=lock)
    log = SessionLog(path / LOG_NAME)
    interrupts = _Interrupts(log, sys.stderr)
    total = grid.rows * grid.cols
    started = clock.monotonic()
    taken = 0
    try:
        done_before = len(writer.completed)
        remaining = [uv for uv in _all_views(grid) if uv not in writer.completed]
        log(
            f"session start: {path}, grid {grid.rows}x{grid.cols} at {grid.pitch_mm} mm, "
            f"{done_before} of {total} views already on disk, {len(remaining)} to take"
        )
        if not remaining:
            _finish(writer, grid, camera, log, path)
            return SessionResult(path, total, total, 0, False, clock.monotonic() - started)
        moves = plan_moves(grid, views=remaining)
        if limits_mm is None and hasattr(stage, "limits_mm"):
            limits_mm = stage.limits_mm()
        check_limits(moves, limits_mm)
        check_steps = getattr(stage, "check_step_grid", None)
        if callable(check_steps):  # a target between two motor steps would fail its position check mid-capture
            check_steps([m.target_mm for m in moves], tolerance_mm=tolerance)
        if not home:
            check_machine_frame(stage, writer.completed, tolerance_mm=tolerance, path=path)
            doubt_of = getattr(stage, "machine_frame_doubt", None)
            doubt = doubt_of() if callable(doubt_of) else None
            if doubt:
                log(f"warning: not homing although {doubt}; the views are in that frame")
        if handle_sigint:
            interrupts.install()
        report(progress, done_before / total, f"{done_before} of {total} views on disk")
        try:
            _attach_wire_log(stage, log)
            if home:
                log("homing")
                stage.home()
                log(f"homed at {_fmt(stage.position())}")
            elif hasattr(stage, "prepare"):
                stage.prepare()
            taking_up = False  # the last move was a backlash take-up: its view comes next
            for move in moves:
                # a stop request waits for the view a take-up leads to: stopping on the overshoot would
                # leave the stage off the journal's last view, and a resume without homing must find it there
                if not taking_up and (interrupts.stop_requested or (should_stop is not None and should_stop())):
                    break
                taking_up = move.view is None
                stage.move_to(move.target_mm, feed_mm_min=feed_mm_min)
                readback = stage.wait_until_idle()
                if move.view is None:
                    continue
                u, v = move.view
                clock.sleep(settle_s)
                settled = stage.status()
                position = settled.get("mpos_mm")
                if settled.get("state") != "Idle" or position is None or max(
                    abs(a - b) for a, b in zip(position, readback)
                ) > tolerance:
                    raise StageNotSettledError(
                        f"the stage was not idle at {_fmt(readback)} after settling for view ({u}, {v}): "
                        f"{settled.get('state')} at {_fmt(position)}; no frame taken"
                    )
                image = camera.trigger()
                record = {
                    "commanded_mm": list(move.target_mm),
                    "readback_mm": list(position),
                    "camera": camera.settings(),
                }
                interrupts.in_write = True
                writer.write_view(u, v, image, json.loads(json.dumps(record, default=_json_default)))
                interrupts.end_write()
                taken += 1
                log(f"view u={u:02d} v={v:02d} at {_fmt(position)} (commanded {_fmt(move.target_mm)})")
                report(progress, len(writer.completed) / total, f"view {len(writer.completed)}/{total}: u{u:02d} v{v:02d}")
                if should_stop is not None and should_stop():
                    interrupts.count = max(interrupts.count, 1)
        except _HardStop:
            log("second Ctrl-C: feed hold and soft reset")
            try:
                stage.stop()
            except RigError as error:
                log(f"stopping the stage failed: {error}")
            lost = getattr(stage, "homing_required", None)
            if lost:
                log(f"the stage was still moving at the reset: {lost}")
            raise CaptureInterrupted(
                "stopped at once by a second Ctrl-C (feed hold + soft reset sent"
                + (f"; GRBL raised {lost}" if lost else "")
                + f"); {len(writer.completed)} of {total} views are in {path}. Home the stage and run the same "
                "command again to resume"
            ) from None
        except RigError as error:
            log(f"error: {error}")
            raise CaptureAborted(
                f"{error} [capture stopped with {len(writer.completed)} of {total} views in {path}; "
                "fix the cause and run the same command again to resume]"
            ) from error
        finally:
            interrupts.uninstall()
        completed = len(writer.completed)
        interrupted = completed < total
        if interrupted:
            log(f"stopped on request with {completed} of {total} views; run again to resume")
        else:
            _finish(writer, grid, camera, log, path)
        return SessionResult(path, total, completed, taken, interrupted, clock.monotonic() - started)
    finally:
        writer.close()
        log.close()


def _check_session_values(*, settle_s: float, feed_mm_min: float | None, tolerance_mm: float | None) -> None:
    """Reject values that cannot drive a capture, before the stage moves (each names its flag)."""
    def finite(value: Any) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

    if not (finite(settle_s) and settle_s >= 0):
        raise RigError(f"settle time {settle_s!r} s (--settle-s): give a number of seconds >= 0")
    if feed_mm_min is not None and not (finite(feed_mm_min) and feed_mm_min > 0):
        raise RigError(f"feed {feed_mm_min!r} mm/min (--feed-mm-min): give a positive feed, or none for rapid moves")
    if tolerance_mm is not None and not (finite(tolerance_mm) and tolerance_mm > 0):
        raise RigError(f"tolerance {tolerance_mm!r} mm (--tolerance-mm): give a positive distance")


def _all_views(grid: GridSpec) -> list[tuple[int, int]]:
    return [(u, v) for u in range(grid.rows) for v in range(grid.cols)]


def _finish(writer: CaptureWriter, grid: GridSpec, camera: Camera, log: Callable[[str], None], path: Path) -> None:
    """Write ``parameters.cfg`` and the completion marker (once)."""
    if writer.marked_complete:
        log("capture already complete")
        return
    first = next(iter(writer.completed.values()))
    from recon.lf.imageio import read_image  # local: only needed once per capture

    shape = read_image(path / first["file"]).shape[:2]
    settings = camera.settings()
    writer.write_parameters(
        image_shape=(int(shape[0]), int(shape[1])),
        pitch_mm=grid.pitch_mm,
        focal_px=settings.get("focal_px", getattr(camera, "focal_px", None)),
        disparity_range=settings.get("disparity_range"),
    )
    writer.mark_complete()
    log(f"capture complete: {grid.rows * grid.cols} views")


def _attach_wire_log(stage: Any, log: Callable[[str], None]) -> None:
    """Log the stage's line commands and non-routine replies (not the status polls)."""
    if not hasattr(stage, "on_line"):
        return

    def on_line(direction: str, text: str) -> None:
        if direction == ">" and text in ("?",):
            return
        if direction == "<" and (text == "ok" or text.startswith("<")):
            return
        log(f"grbl {direction} {text.strip()!r}")

    stage.on_line = on_line


def _fmt(position: Sequence[float] | None) -> str:
    if position is None:
        return "(unknown)"
    return "(" + ", ".join(f"{c:.3f}" for c in position) + ") mm"


def plan_summary(moves: Sequence[Move]) -> str:
    views = sum(1 for m in moves if m.view is not None)
    return f"{len(moves)} moves, {views} views, {len(moves) - views} backlash take-up moves"
