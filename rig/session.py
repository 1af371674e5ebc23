"""The capture session: the one place that drives both the stage and the camera.

For each view of the grid, in scan order: move (with a backlash take-up move when needed), wait until
the stage reports ``Idle`` at the target, wait the settle time, check that it is still idle there,
trigger the camera, write the frame atomically and journal it (:class:`recon.lf.capture.CaptureWriter`).
A frame is never taken while the stage moves.

Resuming: the same command on the same folder takes only the views the journal does not have (whose
files are on disk with the journalled checksum); with other settings the writer refuses and says
which differ. A resume must continue in the machine frame the capture started in (:mod:`rig.frames`):
the header records how the frame was set and the GRBL settings that place a step in it, and a resume
that cannot prove the same frame refuses (:class:`FrameNotProvenError`) before anything moves, unless
asked to retake every view in the present frame (``retake_all``). A capture refused before its first
view leaves no journal behind.

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
import os
import signal
import sys
import threading
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Sequence, TextIO

from recon.errors import LfrigError
from recon.progress import ProgressCallback, report
from rig.errors import RigError
from rig.clock import Clock, SystemClock
from rig.frames import DOUBT, HOMED, FrameNotProvenError, check_resume, folder_doubt, present_frame, witness
from rig.grid import GridSpec, Move, check_limits, plan_moves
from recon.lf.capture import CaptureWriter, is_capture
from recon.lf.lock import FolderLock
from rig.protocols import (Bounded, Camera, Configurable, FrameAware, Preparable, Stage, StepGridded, Toleranced,
                           WireLogged)

__all__ = ["CaptureAborted", "CaptureInterrupted", "FrameNotProvenError", "SessionResult", "StageNotSettledError",
           "build_header", "plan_summary", "run_capture"]

LOG_NAME = "session.log"


class CaptureAborted(RigError):
    """A device error stopped the capture; the views taken so far are kept for a resume."""


class CaptureInterrupted(RigError):
    """A second Ctrl-C stopped the stage at once."""


class StageNotSettledError(RigError):
    """The stage was not idle at the target when the frame was due."""


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
    """Appends timestamped lines to ``session.log`` (flushed at once, so a crash keeps them).

    Safe to call from a signal handler: a line logged while another is being written (the handler
    ran in the middle of that write; a buffered file must not be re-entered) waits and is written
    right after it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = open(path, "a", encoding="utf-8")
        self._writing = False
        self._waiting: list[str] = []

    def __call__(self, message: str) -> None:
        stamp = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
        self._waiting.append(f"{stamp}  {message}\n")
        if self._writing:  # a signal handler inside the write below: its line follows that one
            return
        self._writing = True
        try:
            while self._waiting:
                self._file.write(self._waiting.pop(0))
            self._file.flush()
        finally:
            self._writing = False

    def close(self) -> None:
        for line in self._waiting:
            self._file.write(line)
        self._waiting.clear()
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
        if self.stream is None:
            return
        try:  # straight to the file descriptor: the handler may have interrupted a write to the stream
            fd = self.stream.fileno()
        except (AttributeError, OSError, ValueError):
            fd = None
        if fd is None:
            self.stream.write("\n" + text + "\n")
            self.stream.flush()
        else:
            os.write(fd, ("\n" + text + "\n").encode("utf-8", "replace"))

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
    retake_all: bool = False,
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
        The capture's frame is then the switches'; without it, GRBL's frame as found.
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
    retake_all
        On a folder being resumed: journal the present frame as the capture's new frame and take every
        view again in it (the way forward when the old frame cannot be proven).

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
        A folder being resumed whose machine frame this run cannot prove it is in
        (:func:`rig.frames.check_resume`). Nothing moved.
    """
    _check_session_values(settle_s=settle_s, feed_mm_min=feed_mm_min, tolerance_mm=tolerance_mm)
    path = Path(path)
    clock = clock if clock is not None else SystemClock()
    if tolerance_mm is not None:
        tolerance = tolerance_mm
    else:
        tolerance = stage.tolerance_mm if isinstance(stage, Toleranced) else 0.005
    if limits_mm is None and isinstance(stage, Bounded):
        limits_mm = stage.limits_mm()
    present = present_frame(stage, homing=home)  # records what the connection saw in the port's record first
    header = build_header(
        grid,
        camera_request=camera_request,
        camera_settings=camera.settings(),
        stage_settings=stage.settings() if isinstance(stage, Configurable) else {},
        extra={**(header_extra or {}), **({"frame": present} if present is not None else {})},
    )
    if not is_capture(path):  # refuse before the header is written: the corrected command starts afresh
        check_limits(plan_moves(grid), limits_mm)
    writer = CaptureWriter(path, header=header, lock=lock)
    log_was_there = (path / LOG_NAME).exists()
    log = SessionLog(path / LOG_NAME)
    interrupts = _Interrupts(log, sys.stderr)
    total = grid.rows * grid.cols
    started = clock.monotonic()
    taken = 0
    failed = False
    wire_hook = stage.on_line if isinstance(stage, WireLogged) else None
    try:
        retake = retake_all and not writer.created
        done_before = 0 if retake else len(writer.completed)
        remaining = [uv for uv in _all_views(grid) if retake or uv not in writer.completed]
        log(
            f"session start: {path}, grid {grid.rows}x{grid.cols} at {grid.pitch_mm} mm, "
            f"{done_before} of {total} views already on disk, {len(remaining)} to take"
            + (" (retaking every view in the present frame)" if retake else "")
        )
        if not remaining:
            _finish(writer, grid, camera, log, path)
            return SessionResult(path, total, total, 0, False, clock.monotonic() - started)
        moves = plan_moves(grid, views=remaining)
        check_limits(moves, limits_mm)
        if isinstance(stage, StepGridded):  # a target between two motor steps would fail its position check mid-capture
            stage.check_step_grid([m.target_mm for m in moves], tolerance_mm=tolerance)
        if not retake:
            check_resume(path, stage=stage, captured=writer.frame, present=present, homing=home,
                         events=writer.events, completed=writer.completed, tolerance_mm=tolerance)
        if not home and isinstance(stage, FrameAware):
            doubt = stage.machine_frame_doubt()
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
                witness(stage)  # the port's record: homed
                if writer.completed and not retake and folder_doubt(writer.events):
                    writer.note(HOMED)  # the same frame again: the journal's doubt is answered
            elif isinstance(stage, Preparable):
                stage.prepare()
            if present is not None and (retake or (not writer.completed and writer.frame != present)):
                writer.new_frame(present)  # no view stands in the old frame any more
                log(f"the capture's frame from here on: {present['origin']}")
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
            lost = stage.homing_required if isinstance(stage, FrameAware) else None
            _note_doubt(writer, stage, log)
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
            _note_doubt(writer, stage, log)
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
    except BaseException:
        failed = True
        raise
    finally:
        try:
            witness(stage)  # the port's record: a doubt or a homing seen during the run
        finally:
            # refused or failed before the first view of a capture this run began: leave no journal
            discarded = failed and writer.discard()
            if isinstance(stage, WireLogged):  # the stage outlives the log: its later lines are not this capture's
                stage.on_line = wire_hook
            log.close()
            if discarded and not log_was_there:
                (path / LOG_NAME).unlink(missing_ok=True)
            writer.close()


def _note_doubt(writer: CaptureWriter, stage: Stage, log: Callable[[str], None]) -> None:
    """Journal the stage's doubt about its frame after a stop or an error (a reset, a frame-losing
    alarm), so that a resume without homing in another process refuses."""
    doubt = stage.machine_frame_doubt() if isinstance(stage, FrameAware) else None
    if not doubt or not writer.completed or folder_doubt(writer.events) == doubt:
        return
    try:
        writer.note(DOUBT, reason=doubt)
    except LfrigError as error:  # a journal that cannot be written: the port's record still has it
        log(f"could not journal the doubt about the frame: {error}")


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


def _attach_wire_log(stage: Stage, log: Callable[[str], None]) -> None:
    """Log the stage's line commands and non-routine replies (not the status polls)."""
    if not isinstance(stage, WireLogged):
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
