"""``lfrig stage jog``: move the stage from the keyboard to frame a scene and find the grid centre.

Keys (decoded by :func:`decode_keys` from what a terminal sends):

========================  ==========================================================
arrow right / left        +X / -X by one step
arrow up / down           +Y / -Y by one step
Page Up / Page Down       +Z / -Z by one step
``+`` / ``-``             larger / smaller step (:data:`STEPS_MM`)
``f`` / ``s``             faster / slower feed (:data:`FEEDS_MM_MIN`)
``c``                     set as grid centre: wait until the stage stands still, print
                          ``--centre-mm X Y Z`` (the reported machine position) for ``lfrig capture``
space                     stop (jog cancel)
``q``, Ctrl-C             stop and quit
========================  ==========================================================

Each step is a GRBL 1.1 jog (``$J=G91 ...``, :meth:`rig.grbl.GrblStage.jog`): GRBL refuses a
target beyond the travel (soft limits) without moving or locking up, and the jog-cancel real-time
command (0x85) stops motion with a controlled deceleration, keeping the position. The position shown
is the controller's status report (``MPos``), polled while the keys are read. On the way out the jog
is cancelled and the terminal's settings are restored, whatever ended the loop.
"""

from __future__ import annotations

import os
import select
import termios
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from rig.errors import RigError

STEPS_MM = (0.001, 0.01, 0.05, 0.1, 0.5, 1.0, 5.0, 10.0)
FEEDS_MM_MIN = (10.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0)

#: Terminal input -> key name. Arrow keys come as CSI (``ESC [ A``) or, in a terminal's application
#: cursor mode, SS3 (``ESC O A``) sequences.
SEQUENCES = {
    b"\x1b[A": "up", b"\x1bOA": "up", b"\x1b[B": "down", b"\x1bOB": "down",
    b"\x1b[C": "right", b"\x1bOC": "right", b"\x1b[D": "left", b"\x1bOD": "left",
    b"\x1b[5~": "pgup", b"\x1b[6~": "pgdn",
}
SINGLE = {b"+": "step+", b"=": "step+", b"-": "step-", b"f": "feed+", b"s": "feed-", b"c": "centre",
          b" ": "stop", b"q": "quit", b"Q": "quit", b"\x03": "quit", b"\x04": "quit"}
MOVES = {"right": (1, 0, 0), "left": (-1, 0, 0), "up": (0, 1, 0), "down": (0, -1, 0),
         "pgup": (0, 0, 1), "pgdn": (0, 0, -1)}
HELP = ("arrows: X/Y   PgUp/PgDn: Z   +/-: step   f/s: feed   c: set as grid centre   space: stop   q: quit")


def decode_keys(data: bytes) -> tuple[list[str], bytes]:
    """Split terminal input into key names; returns ``(keys, rest)`` with ``rest`` an unfinished escape
    sequence to prepend to the next read. Unknown bytes and sequences are dropped."""
    keys: list[str] = []
    i = 0
    while i < len(data):
        if data[i:i + 1] == b"\x1b":
            for seq, name in SEQUENCES.items():
                if data.startswith(seq, i):
                    keys.append(name)
                    i += len(seq)
                    break
            else:
                rest = data[i:]
                if any(seq.startswith(rest) for seq in SEQUENCES):
                    return keys, rest  # the rest of the sequence is still on its way
                # an unknown sequence: skip ESC and its CSI/SS3 introducer and parameters up to the final byte
                j = i + 1
                if j < len(data) and data[j:j + 1] in (b"[", b"O"):
                    j += 1
                    while j < len(data) and not (0x40 <= data[j] <= 0x7E):
                        j += 1
                    j += 1
                i = j
            continue
        name = SINGLE.get(data[i:i + 1])
        if name is not None:
            keys.append(name)
        i += 1
    return keys, b""


@dataclass
class JogSettings:
    """Step and feed, as indices into :data:`STEPS_MM` and :data:`FEEDS_MM_MIN`."""

    step_index: int
    feed_index: int

    @classmethod
    def nearest(cls, *, step_mm: float, feed_mm_min: float) -> "JogSettings":
        return cls(min(range(len(STEPS_MM)), key=lambda i: abs(STEPS_MM[i] - step_mm)),
                   min(range(len(FEEDS_MM_MIN)), key=lambda i: abs(FEEDS_MM_MIN[i] - feed_mm_min)))

    @property
    def step_mm(self) -> float:
        return STEPS_MM[self.step_index]

    @property
    def feed_mm_min(self) -> float:
        return FEEDS_MM_MIN[self.feed_index]

    def change(self, key: str) -> bool:
        """Apply ``step+``/``step-``/``feed+``/``feed-``; whether ``key`` was one of them."""
        if key in ("step+", "step-"):
            self.step_index = max(0, min(len(STEPS_MM) - 1, self.step_index + (1 if key == "step+" else -1)))
        elif key in ("feed+", "feed-"):
            self.feed_index = max(0, min(len(FEEDS_MM_MIN) - 1, self.feed_index + (1 if key == "feed+" else -1)))
        else:
            return False
        return True


@contextmanager
def keyboard(fd: int) -> Iterator[None]:
    """The terminal on ``fd`` in character mode without echo and without Ctrl-C signals (Ctrl-C comes
    as a byte and quits); the settings it had are restored on the way out."""
    if not os.isatty(fd):
        raise RigError("stage jog reads keys from a terminal, and its input is not one; run it in a terminal "
                       "(over SSH: ssh -t), or move with lfrig stage move X Y Z")
    saved = termios.tcgetattr(fd)
    mode = termios.tcgetattr(fd)
    mode[3] &= ~(termios.ICANON | termios.ECHO | termios.ISIG | termios.IEXTEN)
    mode[6][termios.VMIN] = 0
    mode[6][termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSADRAIN, mode)
    try:
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def format_position(position_mm: tuple[float, float, float] | None) -> str:
    if position_mm is None:
        return "X ? Y ? Z ?"
    return "  ".join(f"{a} {c:9.3f}" for a, c in zip("XYZ", position_mm))


def centre_option(position_mm: tuple[float, float, float]) -> str:
    """``--centre-mm X Y Z`` as ``lfrig capture`` takes it (3 decimals, GRBL's resolution of reports)."""
    return "--centre-mm " + " ".join(f"{c:.3f}" for c in position_mm)


def _moving(status: Any) -> bool:
    return status.state in ("Run", "Jog", "Home") or (status.state == "Hold" and status.substate == 1)


def run_jog(stage: Any, *, fd: int, write: Callable[[str], None], settings: JogSettings,
            poll_s: float = 0.15, stop_timeout_s: float = 30.0) -> tuple[float, float, float] | None:
    """The key loop on terminal input ``fd`` (already in :func:`keyboard` mode) driving ``stage`` (a
    :class:`rig.grbl.GrblStage`); ``write`` shows text. Returns the last centre set with ``c``, or ``None``.
    The jog is cancelled on the way out, and the stage waited for until it stands still."""
    centre: tuple[float, float, float] | None = None
    pending = b""
    status = stage.status_report()
    message = ""

    def show() -> None:
        state = status.state + (f":{status.substate}" if status.substate is not None else "")
        write(f"\r\x1b[K{format_position(status.mpos_mm)} mm  {state:<6}  step {settings.step_mm:g} mm  "
              f"feed {settings.feed_mm_min:g} mm/min{message}")

    def settle() -> Any:
        deadline = time.monotonic() + stop_timeout_s
        report = stage.status_report()
        while _moving(report) and time.monotonic() < deadline:
            time.sleep(0.05)
            report = stage.status_report()
        return report

    show()
    try:
        while True:
            ready, _, _ = select.select([fd], [], [], poll_s)
            keys: list[str] = []
            if ready:
                data = os.read(fd, 256)
                if not data:
                    break  # the terminal went away
                keys, pending = decode_keys(pending + data)
            quit_now = False
            for key in keys:
                message = ""
                if key == "quit":
                    quit_now = True
                    break
                if key in MOVES:
                    delta = tuple(d * settings.step_mm for d in MOVES[key])
                    try:
                        try:
                            stage.jog(delta, feed_mm_min=settings.feed_mm_min)
                        except RigError as error:
                            if getattr(error, "code", None) != 8:
                                raise
                            settle()  # error:8: GRBL was not Idle yet (a jog still ending): once more when it is
                            stage.jog(delta, feed_mm_min=settings.feed_mm_min)
                    except RigError as error:
                        code = getattr(error, "code", None)
                        message = ("  beyond the travel: not moved" if code == 15
                                   else f"  refused: {str(error).splitlines()[0]}")
                elif key == "stop":
                    stage.jog_cancel()
                elif key == "centre":
                    status = settle()
                    if status.mpos_mm is not None and not _moving(status):
                        centre = status.mpos_mm
                        write(f"\r\x1b[Kgrid centre: {centre_option(centre)}\n")
                else:
                    settings.change(key)
            if quit_now:
                break
            status = stage.status_report()
            show()
    finally:
        stage.jog_cancel()
        try:
            status = settle()
        finally:
            write(f"\r\x1b[K")
    write(f"stopped at {format_position(status.mpos_mm)} mm ({status.state})\n")
    return centre
