"""The machine frame a capture's views stand in, and the evidence that a resume is still in it.

GRBL counts motor steps from where its frame was set: the homing switches after ``$H``, or wherever
the carriage stood at power-up or a reset (``$22=0``, or an unlock ``$X`` instead of homing). A capture
whose views come from two frames is a shifted light field that looks fine, so the frame is part of a
capture's identity:

- The header's ``frame`` (:func:`present_frame`) says how it was set, ``origin`` ``"homing"`` or
  ``"power-up"`` (GRBL's frame as found, not set by a homing lfrig saw), and holds the settings that
  place a step in it (``grbl``: :data:`rig.grbl.FRAME_SETTINGS` as ``{"$N": value}``), the port's
  record it was taken under (``port``) and that record's ``epoch`` then.
- A resume is refused (:class:`FrameNotProvenError`, before anything moves) unless
  :func:`check_resume` proves the same frame: a resume that homes needs a capture set by homing with
  the same settings; one that does not home needs the same step scale, no doubt since (the driver's,
  the capture folder's, the port's record), and the stage where the journal's last view was read back.
- Doubt outlives the process in two places: the capture's journal (``doubt`` records, cleared by a
  ``homed`` record or a new ``frame``) and a small per-port record (:class:`PortRecord`) under the
  user's state folder, so unlocking and jogging in another process cannot fake the proof.
- ``--retake-all`` (``run_capture(retake_all=True)``) journals a new ``frame``: the views before it no
  longer count and every view is taken again in the present frame.
"""

from __future__ import annotations

import errno
import json
import os
import secrets
import weakref
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence
from urllib.parse import quote

from rig.errors import RigError
from rig.protocols import FrameAware, Stage

HOMING = "homing"
POWER_UP = "power-up"
#: Settings that scale every position (compared on every resume).
SCALE_SETTINGS = ("$13", "$100", "$101", "$102")
#: Settings that fix where homing puts the origin (compared when the frame was set by homing).
HOMING_SETTINGS = ("$22", "$23", "$27", "$130", "$131", "$132")
#: Journal record kinds about the frame (``recon.lf.capture.CaptureWriter.note``).
DOUBT, HOMED = "doubt", "homed"


class FrameNotProvenError(RigError):
    """A resume cannot show that the stage is in the capture's machine frame (nothing moved)."""


class PortStateError(RigError):
    """The per-port record cannot be read or written."""


# --------------------------------------------------------------------------------------------------
# The per-port record


def state_folder() -> Path:
    """Where the per-port records live: ``$XDG_STATE_HOME/lfrig/ports`` (default ``~/.local/state``)."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "lfrig" / "ports"


def port_key(url: str) -> str | None:
    """The key of a port's record: its resolved device path (``/dev/serial/by-id/...`` ->
    ``/dev/ttyUSB0``), or the URL of a network port; ``None`` for the in-process simulated
    controller (``fakegrbl://``), which does not outlive the process."""
    if url.startswith("fakegrbl:"):
        return None
    if "://" not in url:
        return os.path.realpath(url)
    return url


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


@dataclass
class PortRecord:
    """What lfrig knows about a controller's frame between processes.

    ``epoch`` is a random token replaced at every event that may change the frame (a reset or an
    alarm lock seen, a frame-losing alarm, a homing, GRBL found elsewhere than lfrig left it);
    ``event`` says what the last one was; ``homed`` holds the frame settings of the last homing when
    nothing cast doubt since; ``left_mm`` is where GRBL reported the stage standing when lfrig last
    let go of the port (``None`` while a connection holds it, or when that was not known). A capture
    taken without homing records the epoch; a resume without homing needs the same epoch.
    """

    key: str
    file: Path
    epoch: str
    event: str | None = None
    homed: dict[str, float] | None = None
    left_mm: list[float] | None = None

    @classmethod
    def open(cls, url: str) -> "PortRecord | None":
        """The record of the port at ``url`` (created when missing); ``None`` for ``fakegrbl://``."""
        key = port_key(url)
        if key is None:
            return None
        folder = state_folder()
        name = quote(key, safe="") + ".json"
        record = cls(key=key, file=folder / name, epoch="")
        data = record._read()
        if data is None:
            record.epoch = secrets.token_hex(8)
            record._write()
            return record
        epoch, homed = data.get("epoch"), data.get("homed")
        if not isinstance(epoch, str) or not epoch or not (homed is None or isinstance(homed, dict)):
            record.note_doubt(f"lfrig's record of the port ({record.file}) was damaged")
            return record
        record.epoch, record.event, record.homed = epoch, data.get("event"), homed
        left = data.get("left_mm")
        if isinstance(left, list) and len(left) == 3 and all(isinstance(c, (int, float)) for c in left):
            record.left_mm = [float(c) for c in left]
        return record

    def note_doubt(self, reason: str) -> None:
        """The frame may have changed (reset, alarm): a new epoch, and no homing to rely on."""
        self.epoch, self.event, self.homed = secrets.token_hex(8), f"{reason} ({_now()})", None
        self.left_mm = None
        self._write()

    def note_homed(self, settings: dict[str, float]) -> None:
        """A homing completed with these frame settings."""
        self.epoch, self.event, self.homed = secrets.token_hex(8), f"homed ({_now()})", dict(settings)
        self.left_mm = None
        self._write()

    def note_position(self, position_mm: Sequence[float] | None) -> None:
        """Where the stage stands as lfrig lets go of the port (``None``: held, or not known)."""
        left = None if position_mm is None else [float(c) for c in position_mm]
        if left != self.left_mm:
            self.left_mm = left
            self._write()

    # -- files: never through a link, written atomically ----------------------------------------
    def _folder_fd(self, *, create: bool) -> int | None:
        """An fd of the records' folder, opened component by component below the state home without
        following links; ``None`` when it is missing and ``create`` is False."""
        base = self.file.parent.parent.parent  # $XDG_STATE_HOME: the user's own choice of folder
        try:
            if create:
                base.mkdir(parents=True, exist_ok=True)
            fd = os.open(base, os.O_RDONLY | os.O_DIRECTORY)
        except FileNotFoundError:
            return None
        except OSError as error:
            raise PortStateError(f"{base}: cannot open the state folder ({error.strerror}); check it or set "
                                 "XDG_STATE_HOME to a folder you can write") from None
        for part in ("lfrig", "ports"):
            try:
                if create:
                    try:
                        os.mkdir(part, 0o700, dir_fd=fd)
                    except FileExistsError:
                        pass
                child = os.open(part, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW, dir_fd=fd)
            except FileNotFoundError:
                os.close(fd)
                return None
            except OSError as error:
                os.close(fd)
                where = self.file.parent if part == "ports" else self.file.parent.parent
                raise PortStateError(self._problem(where, error)) from None
            os.close(fd)
            fd = child
        return fd

    @staticmethod
    def _problem(path: Path, error: OSError) -> str:
        if error.errno in (errno.ELOOP, errno.ENOTDIR):
            return f"{path} is a symbolic link or not a folder; lfrig does not follow it: remove it and run again"
        return f"{path}: {error.strerror}; check its permissions or set XDG_STATE_HOME to a folder you can write"

    def _read(self) -> dict[str, Any] | None:
        fd = self._folder_fd(create=False)
        if fd is None:
            return None
        try:
            try:
                file = os.open(self.file.name, os.O_RDONLY | os.O_NOFOLLOW, dir_fd=fd)
            except FileNotFoundError:
                return None
            except OSError as error:
                raise PortStateError(self._problem(self.file, error)) from None
            with os.fdopen(file, "rb") as f:
                raw = f.read(1 << 16)
        finally:
            os.close(fd)
        try:
            data = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            return {}
        return data if isinstance(data, dict) else {}

    def _write(self) -> None:
        data = json.dumps({"port": self.key, "epoch": self.epoch, "event": self.event, "homed": self.homed,
                           "left_mm": self.left_mm}, sort_keys=True).encode("utf-8") + b"\n"
        fd = self._folder_fd(create=True)
        assert fd is not None
        tmp = f".{self.file.name}.{os.getpid()}.tmp"
        try:
            try:
                out = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600, dir_fd=fd)
                try:
                    os.write(out, data)
                    os.fsync(out)
                finally:
                    os.close(out)
                os.replace(tmp, self.file.name, src_dir_fd=fd, dst_dir_fd=fd)  # replaces a link, never follows it
                os.fsync(fd)
            except OSError as error:
                try:
                    os.unlink(tmp, dir_fd=fd)
                except OSError:
                    pass
                raise PortStateError(self._problem(self.file, error)) from None
        finally:
            os.close(fd)


class PortWitness:
    """Keeps a port's record in step with what one connection (one stage object) saw."""

    def __init__(self, stage: FrameAware) -> None:
        self.record = PortRecord.open(stage.url) if isinstance(stage.url, str) else None
        self._seen: tuple[str, Any] | None = None
        if self.record is not None and self.record.left_mm is not None:
            # GRBL elsewhere than lfrig left it: a power cycle nobody saw ($22=0 has no alarm lock to
            # show it) restarted its position at 0, or another program moved it
            left, here = self.record.left_mm, stage.still_mm()
            tolerance = getattr(stage, "tolerance_mm", 0.005)
            if here is None or max(abs(a - b) for a, b in zip(here, left)) > tolerance:
                found = f"at {_fmt(here)}" if here is not None else "not standing still (or did not answer)"
                self.record.note_doubt(
                    f"GRBL on {stage.url} reported the stage {found} when lfrig opened the port, but at "
                    f"{_fmt(left)} when lfrig last let go of it: it restarted (power) or another program moved it")
            else:
                self.record.note_position(None)
        self.update(stage)

    def let_go(self, stage: FrameAware) -> None:
        """Record what the connection saw, and where the stage stands as the port is released."""
        self.update(stage)
        if self.record is not None:
            self.record.note_position(stage.still_mm())

    def update(self, stage: FrameAware) -> None:
        """Record a doubt or a homing the connection saw since the last call (once each)."""
        if self.record is None:
            return
        doubt = stage.machine_frame_doubt()
        if doubt:
            state: tuple[str, Any] | None = (DOUBT, doubt)
        elif stage.homed:
            state = (HOMED, stage.frame_settings())
        else:
            state = None
        if state is None or state == self._seen:
            return
        self._seen = state
        if state[0] == DOUBT:
            self.record.note_doubt(f"GRBL on {stage.url}: {doubt}")
        else:
            self.record.note_homed(state[1])


_witnesses: "weakref.WeakKeyDictionary[Any, PortWitness]" = weakref.WeakKeyDictionary()


def let_go(stage: Stage) -> None:
    """Before the port of ``stage`` is closed: its record learns what the connection saw and where the
    stage stands, for the next process that opens it."""
    if isinstance(stage, FrameAware):
        seen = witness(stage)
        if seen is not None:
            seen.let_go(stage)


def witness(stage: Stage) -> PortWitness | None:
    """The :class:`PortWitness` of this stage object (made, and the connection's evidence recorded, on
    the first call), or ``None`` for a stage that does not know its frame."""
    if not isinstance(stage, FrameAware):
        return None
    found = _witnesses.get(stage)
    if found is None:
        found = _witnesses[stage] = PortWitness(stage)
    else:
        found.update(stage)
    return found


# --------------------------------------------------------------------------------------------------
# Frames in the header, and the resume check


def present_frame(stage: Stage, *, homing: bool) -> dict[str, Any] | None:
    """The frame the views of this run will stand in (``None`` for a stage that does not know its
    frame): set by homing when this run homes, the stage was homed through this connection, or the
    port's record says it was homed with the same settings and nothing was seen since; otherwise
    GRBL's frame as found (``"power-up"``)."""
    if not isinstance(stage, FrameAware):
        return None
    seen = witness(stage)
    record = seen.record if seen is not None else None
    settings = stage.frame_settings()
    homed_before = record is not None and record.homed == settings and not stage.machine_frame_doubt()
    origin = HOMING if homing or stage.homed or homed_before else POWER_UP
    # the epoch matters only to a frame as found: homing sets the same frame again whenever it runs
    return {"origin": origin, "grbl": settings, "port": record.key if record else None,
            "epoch": record.epoch if record and origin == POWER_UP else None}


def folder_doubt(events: Sequence[dict[str, Any]]) -> str | None:
    """The doubt a capture's journal holds: the reason of its last ``doubt`` record unless a
    ``homed`` record or a new ``frame`` follows it."""
    doubt = None
    for event in events:
        kind = event.get("kind")
        if kind == DOUBT:
            doubt = str(event.get("reason") or "a doubt about the frame was journalled")
        elif kind in (HOMED, "frame"):
            doubt = None
    return doubt


def _differences(keys: Sequence[str], was: dict[str, Any], now: dict[str, Any]) -> list[str]:
    return [f"{k} was {was.get(k, 'not reported')}, now {now.get(k, 'not reported')}" for k in keys
            if was.get(k) != now.get(k)]


def check_resume(
    path: Path,
    *,
    stage: Stage,
    captured: dict[str, Any] | None,
    present: dict[str, Any] | None,
    homing: bool,
    events: Sequence[dict[str, Any]],
    completed: dict[tuple[int, int], dict[str, Any]],
    tolerance_mm: float,
) -> None:
    """Refuse (:class:`FrameNotProvenError`) to add views to the capture at ``path`` unless its frame
    ``captured`` (the header's, or its last ``frame`` record's) is provably the frame the new views
    will stand in. Nothing to prove while no view is on disk.

    ``present`` is :func:`present_frame` for this run, ``homing`` whether it homes first, ``events``
    the journal's frame records, ``completed`` its views (each with ``readback_mm`` and ``time``).
    """
    if not completed:
        return
    retake = "run it with --retake-all to take every view again in the present frame, or capture into a new folder"
    start = f"cannot prove the stage is in the machine frame {path} was captured in"
    homed_capture = captured is None or captured.get("origin") == HOMING
    if present is not None:
        if captured is None:
            raise FrameNotProvenError(
                f"{start}: its journal does not record the frame (an older lfrig wrote it); {retake}")
        was, now = captured.get("grbl") or {}, present["grbl"]
        changed = _differences(SCALE_SETTINGS + (HOMING_SETTINGS if homed_capture else ()), was, now)
        if changed:
            raise FrameNotProvenError(
                f"{start}: GRBL's settings that place a step in it differ ({'; '.join(changed)}), so the new views "
                f"would stand elsewhere. Set them back ($N=value) and run again, or {retake}")
        if present["origin"] == HOMING and not homed_capture:
            raise FrameNotProvenError(
                f"{start}: it was captured without homing (--no-home, in GRBL's frame as found), and the stage "
                f"{'is homed first by this run' if homing else 'was homed since'}, which moves the frame to the switches; {retake}")
        if homing or (isinstance(stage, FrameAware) and stage.homed):
            return  # the switches set the same frame with the same settings
    if homing:
        return
    advice = ("home it: run the same command without --no-home, or " if homed_capture else "") + retake
    advice = advice[0].upper() + advice[1:]
    doubt = stage.machine_frame_doubt() if isinstance(stage, FrameAware) else None
    if not doubt:
        doubt = folder_doubt(events)
        if doubt:
            doubt = f"the capture's journal records it: {doubt}"
    if not doubt and present is not None and captured is not None:
        doubt = _port_doubt(stage, captured, present)
    if doubt:
        raise FrameNotProvenError(f"{start}: {doubt}; resuming there would shift every new view. {advice}")
    last = max(completed.values(), key=lambda record: str(record.get("time", "")))
    readback = last.get("readback_mm")
    here = stage.position()
    if readback is None or max(abs(a - b) for a, b in zip(here, readback)) > tolerance_mm:
        raise FrameNotProvenError(
            f"{start}: it is at {_fmt(here)}, but the last view was read back at {_fmt(readback)}, and GRBL cannot "
            f"tell whether it moved or restarted its position since (a stopped move, a reset). {advice}")


def _port_doubt(stage: Stage, captured: dict[str, Any], present: dict[str, Any]) -> str | None:
    """Why the port's record does not vouch for the captured frame, or ``None`` when it does (or
    there is no record: a controller that does not outlive the process)."""
    seen = witness(stage)
    record = seen.record if seen is not None else None
    if record is None:
        return None
    if present["origin"] == HOMING:
        return None  # homed since with the capture's settings, nothing seen after (present_frame)
    if captured.get("port") != record.key:
        return (f"it was captured through {captured.get('port')}, now {record.key}, whose record "
                f"({record.file}) says nothing about that frame")
    if captured.get("origin") != HOMING and captured.get("epoch") == record.epoch:
        return None
    return (f"since it was captured, lfrig saw GRBL's frame change ({record.event or 'no homing recorded'}; "
            f"recorded in {record.file}), and only a homing or --retake-all clears that")


def _fmt(position: Sequence[float] | None) -> str:
    if position is None:
        return "(unknown)"
    return "(" + ", ".join(f"{c:.3f}" for c in position) + ") mm"
