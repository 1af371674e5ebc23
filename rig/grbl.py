"""GRBL v1.1 over a serial port: the wire protocol as pure functions, and the :class:`GrblStage` driver.

The protocol follows GRBL's own interface documents (``doc/markdown/interface.md``,
``realtime_cmds.md``, ``commands.md`` of gnea/grbl):

- Line commands end in ``\\n`` and are answered by exactly one ``ok`` or ``error:N``. The driver sends
  one line and waits for its answer before sending the next (GRBL's "simple send-response" streaming).
- Real-time commands are single bytes, never followed by a newline and never answered by ``ok``:
  ``?`` status report, ``!`` feed hold, ``~`` cycle start, ``0x18`` soft reset.
- Push messages may arrive at any time: ``<...>`` status reports, ``ALARM:N``, ``[MSG:...]``,
  ``Grbl 1.1h ['$' for help]`` after a reset, ``$N=value`` lines of a ``$$`` listing.

A motion is *done* when a ``G4 P0`` sent after it is answered ``ok`` (GRBL answers a dwell only once
the planner has emptied) **and** a ``?`` status report says ``Idle`` at the target within a tolerance.

The driver never resends a motion command on its own: when a reply goes missing it raises
:class:`GrblTimeoutError` and leaves the decision to the user (the capture session resumes from its
journal after re-homing). Every wait has a timeout.

Positions are machine coordinates (``MPos``) in mm, ``(x, y, z)`` (``docs/conventions.md``).
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from rig.clock import Clock, SystemClock
from rig.errors import RigError

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------------
# Errors


class GrblError(RigError):
    """Something went wrong talking to a GRBL controller."""


class GrblCommandError(GrblError):
    """GRBL answered ``error:N``: the line was not executed."""

    def __init__(self, code: int, line: str, port: str = "") -> None:
        self.code = code
        self.line = line
        where = f" on {port}" if port else ""
        advice = _ERROR_ADVICE.get(code, "")
        super().__init__(
            f"GRBL{where} rejected {line!r} with error:{code} ({describe_error(code)}); "
            "the command was not executed" + (f"; {advice}" if advice else "")
        )


class GrblAlarmError(GrblError):
    """GRBL raised ``ALARM:N``: it stopped and locked out G-code until homed, unlocked or reset."""

    def __init__(self, code: int, port: str = "", context: str = "", *, advice: str | None = None) -> None:
        self.code = code
        where = f" on {port}" if port else ""
        during = f" during {context}" if context else ""
        if advice is None:
            advice = _ALARM_ADVICE.get(code, "reset the controller and home it before moving again")
        super().__init__(f"GRBL{where} raised ALARM:{code}{during} ({describe_alarm(code)}); {advice}")


class GrblTimeoutError(GrblError):
    """A reply did not arrive in time. Motion commands are never resent automatically."""


class GrblConnectionError(GrblError):
    """The port could not be opened, went away, or the controller reset on its own."""


class GrblPositionError(GrblError):
    """The controller reports Idle, but not at the commanded position."""


class GrblLimitError(GrblError):
    """A commanded position lies outside the machine's travel; nothing was sent."""


class GrblSettingsError(GrblError):
    """The controller's ``$$`` settings are ones lfrig cannot work with (nothing was moved)."""


class GrblStepError(GrblError):
    """A commanded position lies between two motor steps, farther than the tolerance; nothing was sent."""


class GrblProtocolError(GrblError):
    """A reply that GRBL's interface does not allow in that place."""


# --------------------------------------------------------------------------------------------------
# GRBL's code tables (facts from GRBL's interface document, worded here).

ERROR_CODES: dict[int, str] = {
    1: "a G-code word has no letter: expected a command letter",
    2: "a numeric value is badly formatted or missing",
    3: "the '$' system command is not recognised or not supported",
    4: "a negative value was given where a positive one is expected",
    5: "homing is not enabled in the settings ($22)",
    6: "the minimum step pulse time must be more than 3 microseconds",
    7: "EEPROM read failed; settings were reset to their defaults",
    8: "this '$' command is only accepted while GRBL is Idle",
    9: "G-code is locked out while GRBL is in alarm or jog state",
    10: "soft limits cannot be enabled without homing",
    11: "the line is longer than GRBL's line buffer and was not processed",
    12: "a '$' setting value exceeds the maximum step rate",
    13: "the safety door is open",
    14: "build info or startup line exceeds the EEPROM line length",
    15: "the jog target exceeds the machine travel; jog ignored",
    16: "jog command without '=' or with a prohibited G-code",
    17: "laser mode requires PWM output",
    20: "unsupported or invalid G-code command in the block",
    21: "more than one G-code command of the same modal group in the block",
    22: "the feed rate has not been set",
    23: "the G-code command requires an integer value",
    24: "two G-code commands in the block both need the XYZ axis words",
    25: "a G-code word is repeated in the block",
    26: "the G-code command needs XYZ axis words but none were given",
    27: "the N line number is outside 1 - 9,999,999",
    28: "the G-code command is missing a required P or L value",
    29: "only work coordinate systems G54-G59 are supported",
    30: "G53 needs G0 or G1 motion mode to be active",
    31: "unused axis words in the block while G80 motion cancel is active",
    32: "G2/G3 arc has no XYZ axis words in the selected plane",
    33: "the motion target is invalid (impossible arc, or probe target at the current position)",
    34: "G2/G3 radius-format arc has a mathematical error",
    35: "G2/G3 offset-format arc is missing its IJK word in the selected plane",
    36: "unused, leftover G-code words in the block",
    37: "G43.1 tool length offset is not on its configured axis",
    38: "the tool number exceeds the maximum supported value",
}

ALARM_CODES: dict[int, str] = {
    1: "hard limit triggered; the machine position is likely lost after the sudden halt",
    2: "the G-code motion target exceeds the machine travel (soft limit); the position was kept",
    3: "reset while in motion; the position cannot be guaranteed and steps may have been lost",
    4: "probe fail: the probe was not in the expected initial state",
    5: "probe fail: the probe did not make contact within the programmed travel",
    6: "homing fail: the homing cycle was reset",
    7: "homing fail: the safety door was opened during homing",
    8: "homing fail: the pull-off did not clear the limit switch",
    9: "homing fail: the limit switch was not found within the search distance",
}

_ERROR_ADVICE = {
    9: "home the stage first (`lfrig stage home`, or `--home`), or unlock it with `lfrig stage unlock`",
    5: "enable homing ($22=1) or unlock with `lfrig stage unlock` instead",
    8: "wait until the stage is Idle",
}

_ALARM_ADVICE = {
    1: "check the stage for an obstruction, then reset and home it (`lfrig stage home`) and run again",
    2: "check the grid centre, size and pitch against the machine travel; reset, then unlock or home",
    3: "home the stage again (`lfrig stage home`) before moving",
    6: "home the stage again",
    8: "check the limit switches and the pull-off setting ($27), then home again",
    9: "check the limit switch wiring and the maximum travel settings ($130-$132), then home again",
}


def describe_error(code: int) -> str:
    """GRBL's meaning of ``error:code``."""
    return ERROR_CODES.get(code, "unknown error code (see GRBL's error_codes document)")


def describe_alarm(code: int) -> str:
    """GRBL's meaning of ``ALARM:code``."""
    return ALARM_CODES.get(code, "unknown alarm code (see GRBL's alarm_codes document)")


# --------------------------------------------------------------------------------------------------
# Encoding (host -> GRBL). Pure functions returning the exact bytes to write.

#: GRBL's serial line buffer holds 80 characters (longer lines get ``error:11``).
LINE_LIMIT = 80
STATUS_QUERY = b"?"
FEED_HOLD = b"!"
CYCLE_START = b"~"
SOFT_RESET = b"\x18"
#: GRBL 1.1's jog cancel: stops a ``$J=`` jog with a controlled deceleration and drops the queued
#: jogs; the position is kept (no reset, no alarm). Ignored outside the Jog state.
JOG_CANCEL = b"\x85"
REALTIME_BYTES = frozenset(b"?!~\x18") | frozenset(range(0x80, 0x100))
#: GRBL's wake-up: blank lines, then wait for it to initialise and flush what it printed.
WAKE = b"\r\n\r\n"


def encode_line(text: str) -> bytes:
    """The bytes of one line command: ASCII ``text`` followed by ``\\n``.

    Raises ``ValueError`` for non-ASCII text, embedded newlines or real-time characters (which GRBL
    would act on immediately instead of buffering), or lines longer than :data:`LINE_LIMIT`.
    """
    if not text.isascii():
        raise ValueError(f"GRBL lines must be ASCII; got {text!r}")
    data = text.encode("ascii")
    if b"\n" in data or b"\r" in data:
        raise ValueError(f"a GRBL line must not contain a newline; got {text!r}")
    if any(b in REALTIME_BYTES for b in data):
        raise ValueError(f"{text!r} contains a real-time character (? ! ~ or ctrl-x) that GRBL would execute at once")
    if len(data) > LINE_LIMIT - 1:
        raise ValueError(f"{text!r} is {len(data)} characters; GRBL's line buffer holds {LINE_LIMIT - 1}")
    return data + b"\n"


def format_mm(value: float) -> str:
    """A coordinate as GRBL-friendly text: fixed point, 3 decimals (1 micrometre), no ``-0.000``."""
    if not math.isfinite(value):
        raise ValueError(f"coordinate must be finite; got {value!r}")
    text = f"{value:.3f}"
    return "0.000" if text == "-0.000" else text


def encode_move(position_mm: Sequence[float], *, feed_mm_min: float | None = None) -> bytes:
    """An absolute move to the machine position ``position_mm = (x, y, z)`` in mm.

    ``G53 G0`` (rapid, at the machine's maximum rates) when ``feed_mm_min`` is ``None``, else
    ``G53 G1 ... F<feed>`` at that feed in mm/min. ``G53`` makes the target machine coordinates
    whatever work offset (``G54``-``G59``, ``G92``) another program left active. Assumes ``G21``
    (set by :func:`encode_modes`); ``G53`` is absolute by itself.
    """
    if len(position_mm) != 3:
        raise ValueError(f"position must be (x, y, z) in mm; got {position_mm!r}")
    x, y, z = (format_mm(float(c)) for c in position_mm)
    if feed_mm_min is None:
        return encode_line(f"G53 G0 X{x} Y{y} Z{z}")
    if not (feed_mm_min > 0 and math.isfinite(feed_mm_min)):
        raise ValueError(f"feed_mm_min must be a positive number; got {feed_mm_min!r}")
    return encode_line(f"G53 G1 X{x} Y{y} Z{z} F{feed_mm_min:.1f}")


def encode_jog(delta_mm: Sequence[float], *, feed_mm_min: float) -> bytes:
    """A relative jog by ``delta_mm = (dx, dy, dz)`` in mm at ``feed_mm_min``: ``$J=G91 G21 X.. F..``.

    GRBL 1.1 runs it in its Jog state: it answers ``error:15`` instead of moving when the target is
    beyond the travel (soft limits on), and :data:`JOG_CANCEL` stops it. Axes with a zero step are
    left out; the modal state (``G90``/``G91``) of later lines is not changed.
    """
    if len(delta_mm) != 3:
        raise ValueError(f"delta must be (dx, dy, dz) in mm; got {delta_mm!r}")
    if not (feed_mm_min > 0 and math.isfinite(feed_mm_min)):
        raise ValueError(f"feed_mm_min must be a positive number; got {feed_mm_min!r}")
    words = [f"{axis}{format_mm(float(d))}" for axis, d in zip("XYZ", delta_mm) if format_mm(float(d)) != "0.000"]
    if not words:
        raise ValueError(f"a jog needs a non-zero step of at least 0.001 mm; got {delta_mm!r}")
    return encode_line(f"$J=G91 G21 {' '.join(words)} F{feed_mm_min:.1f}")


def encode_modes() -> bytes:
    """``G90 G21``: absolute distances, millimetres."""
    return encode_line("G90 G21")


def encode_dwell(seconds: float = 0.0) -> bytes:
    """``G4 P<s>``: GRBL answers ``ok`` only after the planner has emptied and the dwell elapsed."""
    if not seconds >= 0:
        raise ValueError(f"dwell must be >= 0 s; got {seconds!r}")
    return encode_line(f"G4 P{seconds:g}")


def encode_home() -> bytes:
    """``$H``: run the homing cycle (answered ``ok`` when it has finished)."""
    return encode_line("$H")


def encode_unlock() -> bytes:
    """``$X``: clear the alarm lock without homing."""
    return encode_line("$X")


def encode_settings_query() -> bytes:
    """``$$``: list the ``$N=value`` settings, then ``ok``."""
    return encode_line("$$")


def encode_output(on: bool) -> bytes:
    """``M8`` (flood coolant output on) or ``M9`` (off): a spare output used as a camera trigger."""
    return encode_line("M8" if on else "M9")


# --------------------------------------------------------------------------------------------------
# Parsing (GRBL -> host). Pure functions from one line of text (without its line end).


@dataclass(frozen=True)
class Ok:
    pass


@dataclass(frozen=True)
class Error:
    code: int


@dataclass(frozen=True)
class Alarm:
    code: int


@dataclass(frozen=True)
class Welcome:
    version: str


@dataclass(frozen=True)
class Message:
    """A bracketed feedback line, ``[MSG:...]``, ``[GC:...]``, ``[VER:...]``, ..."""

    kind: str
    text: str


@dataclass(frozen=True)
class Setting:
    number: int
    value: float


@dataclass(frozen=True)
class StartupLine:
    """GRBL's echo of a startup block (``$N0``/``$N1``) it ran after a reset: ``>G54:ok`` or
    ``>G20:error:N``."""

    line: str
    result: str


@dataclass(frozen=True)
class Unknown:
    text: str


@dataclass(frozen=True)
class Status:
    """One real-time status report ``<State|MPos:...|...>``.

    ``mpos_mm`` is filled from ``WPos`` + ``WCO`` when the report gives work coordinates and a work
    offset is known (passed to :func:`parse_status`); otherwise it may be ``None``.
    """

    state: str
    substate: int | None = None
    mpos_mm: tuple[float, float, float] | None = None
    wpos_mm: tuple[float, float, float] | None = None
    wco_mm: tuple[float, float, float] | None = None
    feed_mm_min: float | None = None
    spindle_rpm: float | None = None
    buffer: tuple[int, int] | None = None
    line_number: int | None = None
    pins: str = ""
    fields: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "substate": self.substate,
            "mpos_mm": self.mpos_mm,
            "wpos_mm": self.wpos_mm,
            "wco_mm": self.wco_mm,
            "feed_mm_min": self.feed_mm_min,
            "pins": self.pins,
        }


Reply = Ok | Error | Alarm | Welcome | Message | Setting | Status | StartupLine | Unknown

_WELCOME = re.compile(r"^Grbl (\S+) \[.*\]$")
_STARTUP = re.compile(r"^>(.*):(ok|error:\d+)$")
_SETTING = re.compile(r"^\$(\d+)=(-?[0-9.]+)$")
STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")


def _floats(text: str, n: int | None = None) -> tuple[float, ...]:
    values = tuple(float(t) for t in text.split(","))
    if n is not None and len(values) < n:
        raise ValueError(f"expected {n} values in {text!r}")
    return values


def parse_status(text: str, *, wco_mm: Sequence[float] | None = None) -> Status:
    """Parse ``<State|MPos:x,y,z|FS:f,s|WCO:x,y,z|...>``. Raises ``ValueError`` when malformed.

    ``wco_mm`` is the last known work coordinate offset; GRBL sends ``WCO`` only now and then, and
    ``MPos = WPos + WCO`` per axis. Only the first three axes are kept.
    """
    if not (text.startswith("<") and text.endswith(">")):
        raise ValueError(f"not a status report: {text!r}")
    parts = text[1:-1].split("|")
    state, _, sub = parts[0].partition(":")
    if state not in STATES:
        raise ValueError(f"unknown machine state {state!r} in {text!r}")
    substate = int(sub) if sub else None
    fields: dict[str, str] = {}
    for part in parts[1:]:
        key, sep, value = part.partition(":")
        if not sep or not key:
            raise ValueError(f"malformed field {part!r} in {text!r}")
        fields[key] = value
    mpos = wpos = wco = None
    if "MPos" in fields:
        mpos = _floats(fields["MPos"], 3)[:3]
    if "WPos" in fields:
        wpos = _floats(fields["WPos"], 3)[:3]
    if "WCO" in fields:
        wco = _floats(fields["WCO"], 3)[:3]
    if mpos is None and wpos is None:
        raise ValueError(f"status report without MPos or WPos: {text!r}")
    offset = wco if wco is not None else (tuple(wco_mm)[:3] if wco_mm is not None else None)
    if mpos is None and wpos is not None and offset is not None:
        mpos = tuple(w + o for w, o in zip(wpos, offset))
    if wpos is None and mpos is not None and offset is not None:
        wpos = tuple(m - o for m, o in zip(mpos, offset))
    feed = spindle = None
    if "FS" in fields:
        fs = _floats(fields["FS"])
        feed, spindle = fs[0], (fs[1] if len(fs) > 1 else None)
    elif "F" in fields:
        feed = _floats(fields["F"])[0]
    buffer = None
    if "Bf" in fields:
        bf = [int(t) for t in fields["Bf"].split(",")]
        buffer = (bf[0], bf[1])
    line_number = int(fields["Ln"]) if "Ln" in fields else None
    return Status(
        state=state,
        substate=substate,
        mpos_mm=mpos,  # type: ignore[arg-type]
        wpos_mm=wpos,  # type: ignore[arg-type]
        wco_mm=wco,  # type: ignore[arg-type]
        feed_mm_min=feed,
        spindle_rpm=spindle,
        buffer=buffer,
        line_number=line_number,
        pins=fields.get("Pn", ""),
        fields=fields,
    )


def parse_line(text: str, *, wco_mm: Sequence[float] | None = None) -> Reply:
    """Classify one line GRBL sent (line end already stripped). Never raises: unparseable lines,
    including garbled status reports, come back as :class:`Unknown`."""
    text = text.strip()
    if text == "ok":
        return Ok()
    try:
        if text.startswith("error:"):
            return Error(int(text[6:]))
        if text.startswith("ALARM:"):
            return Alarm(int(text[6:]))
        if text.startswith("<"):
            return parse_status(text, wco_mm=wco_mm)
    except ValueError:
        return Unknown(text)
    match = _WELCOME.match(text)
    if match:
        return Welcome(match[1])
    if text.startswith("[") and text.endswith("]"):
        kind, _, rest = text[1:-1].partition(":")
        return Message(kind, rest)
    match = _SETTING.match(text)
    if match:
        return Setting(int(match[1]), float(match[2]))
    match = _STARTUP.match(text)
    if match:
        return StartupLine(match[1], match[2])
    return Unknown(text)


# --------------------------------------------------------------------------------------------------
# Machine geometry from the $$ settings.


def travel_limits_mm(settings: dict[int, float]) -> tuple[tuple[float, float], ...] | None:
    """Per-axis ``(min, max)`` machine coordinates a move may target, from ``$$`` settings.

    GRBL 1.1h's machine space is ``[-max_travel, 0]`` on every axis (``$130..$132``), whichever end
    it homes to: an axis homing to its maximum (the default) has its switch at 0 and is left at
    ``-pulloff``; one whose bit is set in ``$23`` homes to its minimum, has its switch at ``-max_travel``
    and is left at ``-max_travel + pulloff``. Soft limits (``$20``) allow the switch position itself,
    where a hard limit (``$21``) would trip ``ALARM:1``; these limits keep the homing pull-off (``$27``)
    away from the switch. ``None`` without ``$130..$132``.
    """
    if not all(k in settings for k in (130, 131, 132)):
        return None
    mask = int(settings.get(23, 0))
    pulloff = abs(float(settings.get(27, 0.0)))
    limits = []
    for axis in range(3):
        travel = abs(settings[130 + axis])
        margin = min(pulloff, travel)
        limits.append((-travel + margin, 0.0) if mask & (1 << axis) else (-travel, -margin))
    return tuple(limits)


#: The ``$$`` settings that place a motor step in the machine frame: report units (``$13``) and
#: steps/mm (``$100..$102``) scale every position; homing on (``$22``), its direction (``$23``), its
#: pull-off (``$27``) and the travel (``$130..$132``, where an axis homes to its minimum) fix where
#: homing puts the origin.
FRAME_SETTINGS = (13, 22, 23, 27, 100, 101, 102, 130, 131, 132)
#: Alarms after which GRBL's position is no longer the frame it was: a hard limit's sudden halt, a
#: reset in motion, and the homing failures (the cycle had begun to move).
FRAME_LOSING_ALARMS = frozenset({1, 3, 6, 7, 8, 9})


def step_grid_offsets_mm(position_mm: Sequence[float], settings: dict[int, float]) -> tuple[float, ...]:
    """Per axis, how far the machine position ``position_mm = (x, y, z)`` (mm) lies from the nearest
    whole motor step of ``$100..$102`` (steps/mm): GRBL rounds every target to a step, and reports
    that step. The target is taken as it is sent (:func:`format_mm`, 3 decimals). Shape ``(3,)``, mm,
    each in ``[0, 0.5 / steps_per_mm]``; 0 for an axis without a steps/mm setting."""
    offsets = []
    for axis, value in enumerate(position_mm):
        steps_per_mm = abs(float(settings.get(100 + axis, 0.0)))
        sent = float(format_mm(float(value)))
        if steps_per_mm <= 0:
            offsets.append(0.0)
            continue
        offsets.append(abs(sent - round(sent * steps_per_mm) / steps_per_mm))
    return tuple(offsets)


#: GRBL 1.1h's homing search runs up to 1.5 x the travel (``HOMING_AXIS_SEARCH_SCALAR``), the locate
#: phase up to 5 x the pull-off (``HOMING_AXIS_LOCATE_SCALAR``).
HOMING_SEARCH_SCALAR = 1.5
HOMING_LOCATE_SCALAR = 5.0


def homing_time_bound_s(settings: dict[int, float]) -> float:
    """The longest a ``$H`` cycle can take with these ``$$`` settings, in s.

    Per axis (summed, whatever the cycle order): the search over ``1.5 x $13x`` at the seek rate
    ``$25``, a pull-off at ``$25``, the locate over ``5 x $27`` at ``$24``, the final pull-off, each
    move's acceleration and deceleration (``$12x``) and the debounce delays (``$26`` ms). Rates are
    capped by the axis' maximum rate ``$11x``.
    """
    seek = float(settings.get(25, 500.0))
    locate = float(settings.get(24, 25.0))
    pulloff = abs(float(settings.get(27, 1.0)))
    debounce_s = float(settings.get(26, 250.0)) / 1000.0
    total = 0.0
    for axis in range(3):
        rate_cap = float(settings.get(110 + axis, seek)) or seek
        accel = float(settings.get(120 + axis, 10.0)) or 10.0
        travel = abs(float(settings.get(130 + axis, 200.0)))
        v_seek = max(min(seek, rate_cap), 1e-3) / 60.0
        v_locate = max(min(locate, rate_cap), 1e-3) / 60.0
        total += HOMING_SEARCH_SCALAR * travel / v_seek + 2 * pulloff / v_seek
        total += HOMING_LOCATE_SCALAR * pulloff / v_locate
        total += 4 * 2 * v_seek / accel + 4 * debounce_s
    return total


def feed_hold_time_s(speed_mm_min: float, settings: dict[int, float]) -> float:
    """How long a feed hold takes to stop a stage moving at ``speed_mm_min``: the speed over the
    smallest acceleration of ``$120..$122`` (the planner never exceeds any axis' own)."""
    accels = [float(settings.get(120 + axis, 10.0)) for axis in range(3)]
    accel = max(min(accels), 1e-3)
    return max(speed_mm_min, 0.0) / 60.0 / accel


def motion_time_s(distance_mm: float, *, rate_mm_min: float, accel_mm_s2: float) -> float:
    """Duration of a rest-to-rest move with a trapezoidal (or triangular) speed profile."""
    if distance_mm <= 0:
        return 0.0
    v = rate_mm_min / 60.0
    a = accel_mm_s2
    if distance_mm >= v * v / a:
        return distance_mm / v + v / a
    return 2.0 * math.sqrt(distance_mm / a)


# --------------------------------------------------------------------------------------------------
# The driver.


#: Default waits of :class:`GrblStage`, in s (read when a stage is made): for ``ok`` to a line that
#: does not move, or a status report (``reply_timeout_s``); for the first status report after the
#: port opens (``wake_s``: an Arduino's bootloader runs 0.5-3 s); added to twice a move's estimated
#: time before it counts as stalled (``move_timeout_margin_s``).
REPLY_TIMEOUT_S = 2.0
WAKE_S = 5.0
MOVE_TIMEOUT_MARGIN_S = 5.0

#: Who may read GRBL's replies unseen, for messages: Linux lets root open a port in exclusive mode
#: (``TIOCEXCL``), and ``/proc`` does not show other users root's open files.
HIDDEN_READER = ("one run as root can open the port although lfrig holds it exclusively, and other users cannot "
                 "see it: `sudo fuser -v` on the device names it")

#: The package where pyserial finds lfrig's own URL schemes (``protocol_<scheme>`` modules), as it
#: finds its own ``loop://`` in ``serial.urlhandler``: ``fakegrbl://`` is the simulated controller.
URL_HANDLERS = "rig.urlhandler"


def open_port(url: str, *, baudrate: int = 115200, poll_s: float = 0.05):
    """Open a pyserial port by URL or device path (``/dev/ttyUSB0``, ``socket://host:port``,
    ``fakegrbl://name``). Raises :class:`GrblConnectionError` naming the URL on failure.

    The port is opened exclusively twice over: pyserial's ``exclusive=True`` (an advisory lock that
    stops programs taking the same lock, such as a second lfrig) and, on a terminal device, the
    kernel's exclusive mode ``TIOCEXCL``, under which the system refuses every further open of the
    device (``EBUSY``) to programs without administrator rights (``cat``, a serial monitor, a modem
    manager's probe) until :func:`release_port`."""
    import serial  # local: keeps `lfrig --help` fast

    if URL_HANDLERS not in serial.protocol_handler_packages:  # fakegrbl:// (rig/urlhandler/)
        serial.protocol_handler_packages.append(URL_HANDLERS)
    try:
        # exclusive: a second process (or a second lfrig) cannot drive the same controller
        port = serial.serial_for_url(url, baudrate=baudrate, timeout=poll_s, write_timeout=2.0, exclusive=True)
    except (serial.SerialException, ValueError, OSError) as error:
        if "exclusively lock" in str(error):
            raise GrblConnectionError(
                f"the GRBL port {url!r} is in use by another program (lfrig opens it exclusively); "
                "close the other program or lfrig command, then run again"
            ) from None
        raise GrblConnectionError(
            f"cannot open the GRBL port {url!r}: {error}; check the device path or URL "
            "(e.g. /dev/ttyUSB0, socket://host:port) and that no other program holds it"
        ) from None
    _terminal_exclusive(port, True)
    return port


def release_port(port: Any) -> None:
    """Leave the kernel's exclusive mode (if :func:`open_port` set it) and close the port. The mode
    belongs to the device, not to lfrig's descriptor: left set, it would outlive the close while
    another descriptor keeps the device open."""
    _terminal_exclusive(port, False)
    port.close()


def _terminal_exclusive(port: Any, on: bool) -> None:
    import fcntl
    import os
    import termios

    fd = getattr(port, "fd", None)
    if not isinstance(fd, int) or fd < 0:
        return  # not a local device (socket://, rfc2217://, fakegrbl://)
    try:
        if os.isatty(fd):
            fcntl.ioctl(fd, termios.TIOCEXCL if on else termios.TIOCNXCL)
    except OSError as error:  # a terminal without the ioctl: the advisory lock still holds
        log.debug("TIOC%sEXCL on fd %d: %s", "" if on else "N", fd, error)


def port_holders(url: str) -> list[tuple[int, str]]:
    """Other processes that have the device ``url`` open, as ``(pid, command name)`` (Linux, from
    ``/proc``; empty elsewhere, for URLs that are not device paths, or when ``/proc`` cannot be read).
    A program that opened the port before lfrig reads GRBL's replies as well, and whichever reads a
    reply first takes it."""
    import os

    path = url[len("grbl://"):] if url.startswith("grbl://") else url
    if not path.startswith("/") or not os.path.isdir("/proc"):
        return []
    try:
        device = os.stat(path).st_rdev
    except OSError:
        return []
    if not device:
        return []
    holders = []
    me = os.getpid()
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit() or int(entry.name) == me:
            continue
        try:
            fds = os.listdir(f"/proc/{entry.name}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                # stat of /proc/PID/fd/N describes the open file itself (no path is looked up)
                info = os.stat(f"/proc/{entry.name}/fd/{fd}")
            except OSError:
                continue
            if info.st_rdev == device and (info.st_mode & 0o170000) == 0o020000:  # the same character device
                try:
                    with open(f"/proc/{entry.name}/comm", encoding="utf-8", errors="replace") as f:
                        name = f.read().strip()
                except OSError:
                    name = "?"
                holders.append((int(entry.name), name))
                break
    return holders


class GrblStage:
    """A three-axis stage driven by a GRBL v1.1 controller (implements :class:`rig.protocols.Stage`).

    Parameters
    ----------
    url
        Port device or pyserial URL (``/dev/ttyUSB0``, ``socket://host:23``, ``fakegrbl://bench``),
        or an already open pyserial-like object (``port=``).
    clock
        Time source for every timeout and wait (default :class:`SystemClock`).
    reply_timeout_s
        How long to wait for ``ok`` to a non-motion line, or for a status report (default
        :data:`REPLY_TIMEOUT_S`, 2 s).
    home_timeout_s
        How long the homing cycle may take; default: derived from the controller's travel, rates and
        pull-off (:func:`homing_time_bound_s`) plus a margin.
    tolerance_mm
        Largest per-axis distance between the commanded and the reported position accepted as
        "at the target".
    move_timeout_margin_s
        Added to twice a move's estimated time: how long :meth:`wait_until_idle` waits before the
        move counts as stalled (default :data:`MOVE_TIMEOUT_MARGIN_S`, 5 s).
    wake_s
        How long to keep asking GRBL for a status report (``?`` every 0.25 s) after opening the port
        (default :data:`WAKE_S`, 5 s).
        A controller that did not reset answers at once and the wait ends there; a board that resets
        when the port opens (Arduino) answers once its bootloader has handed over, after 0.5-3 s,
        printing its welcome line first (``reset_seen``). No answer at all within ``wake_s`` leaves
        the frame in doubt (``silent_on_open``): a reset cannot be ruled out.
    reset_on_connect
        Send a soft reset (``0x18``) and wait for the welcome line, so the controller starts from a
        known state. A motion still running (a previous process died mid-move) is waited for first:
        a reset in motion would raise ``ALARM:3`` and lose the position.
    read_only
        Only look: no soft reset, no waiting for a running motion, the ``$$`` settings read only
        when GRBL is ``Idle`` or in ``Alarm`` (it refuses ``$`` commands otherwise), and an error
        when no status report comes within ``wake_s`` (GRBL sends none while it homes or after a
        hard or soft limit). Nothing is sent that could stop or change what the controller does.

    Attributes
    ----------
    reset_seen
        GRBL printed its welcome line on its own: it reset when the port opened (Arduino) or later
        (power dip, reset button). After a power-up reset GRBL's machine position restarts at 0
        wherever the carriage stands; only homing restores the machine frame.
    homed
        A homing cycle completed through this driver.
    homing_required
        Why the position can no longer be trusted (``ALARM:3``: reset while moving), or ``None``.
        Moves and ``unlock`` are refused until :meth:`home`.
    open_state
        The controller's state when the port was opened (``Idle``, ``Alarm``, ...).
    silent_on_open
        GRBL sent no status report within ``wake_s`` of the port opening (still booting, homing for
        a program that died, halted by a limit, or not connected): whether it reset is not known.
    """

    def __init__(
        self,
        url: str = "",
        *,
        port: Any = None,
        baudrate: int = 115200,
        clock: Clock | None = None,
        reply_timeout_s: float | None = None,
        home_timeout_s: float | None = None,
        move_timeout_margin_s: float | None = None,
        tolerance_mm: float = 0.005,
        wake_s: float | None = None,
        reset_on_connect: bool = True,
        read_only: bool = False,
        poll_s: float = 0.05,
    ) -> None:
        self.url = url or getattr(port, "port", "") or "<port>"
        self.clock: Clock = clock if clock is not None else SystemClock()
        self.reply_timeout_s = REPLY_TIMEOUT_S if reply_timeout_s is None else reply_timeout_s
        self._home_timeout_s = home_timeout_s
        self.move_timeout_margin_s = MOVE_TIMEOUT_MARGIN_S if move_timeout_margin_s is None else move_timeout_margin_s
        wake_s = WAKE_S if wake_s is None else wake_s
        self.tolerance_mm = tolerance_mm
        self.poll_s = poll_s
        self._rx = bytearray()
        self._wco: tuple[float, float, float] | None = None
        self._target: tuple[float, float, float] | None = None
        self._last_status: Status | None = None
        self._closed = False
        self.version: str | None = None
        self.settings_values: dict[int, float] = {}
        self.reset_seen = False
        self.homed = False
        self.homing_required: str | None = None
        self._homing_required_code = 0
        #: An alarm after which the position may be lost (:data:`FRAME_LOSING_ALARMS`), seen on this connection.
        self.frame_alarm: str | None = None
        self.open_state: str | None = None
        self._empty_buffer: tuple[int, int] | None = None  # Bf of a GRBL with nothing queued (if reported)
        self.silent_on_open = False
        self.read_only = read_only
        self._homing = False  # a $H sent and not yet answered
        self.on_line: Callable[[str, str], None] | None = None  # (direction, text) hook for logs
        # the programs that have the port open when lfrig opens it: named in later errors even after
        # they exit. Looked for before the open: a reader such as `cat` sees end-of-file once pyserial
        # sets the port's VMIN to 0, and may be gone before a look at /proc after it ends.
        self._opened_with: list[tuple[int, str]] = port_holders(url) if port is None else []
        self._port = port if port is not None else open_port(url, baudrate=baudrate, poll_s=poll_s)
        note = self._holders_note() if port is None else ""
        if note:  # opened before lfrig, so the exclusive mode does not keep it out
            log.warning("%s: the port is shared%s", self.url, note)
        try:
            self._connect(wake_s=wake_s, reset=reset_on_connect and not read_only)
        except BaseException:
            self._close_port()
            raise

    # -- context manager ----------------------------------------------------------------------
    def __enter__(self) -> "GrblStage":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Release the port (does not stop a running motion: use :meth:`stop` for that)."""
        self._close_port()

    def _close_port(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                release_port(self._port)
            except Exception:  # closing a dead port must not hide the original error
                pass

    # -- low level I/O ------------------------------------------------------------------------
    def _io_error(self, error: Exception) -> GrblConnectionError:
        names = self._holder_names()
        if "multiple access" in str(error) or names:
            # pyserial's "ready to read but returned no data": another reader took the bytes first
            who = (f"{names} also has the port open and reads GRBL's replies" if names else
                   f"another program may be reading GRBL's replies ({HIDDEN_READER})")
            return GrblConnectionError(
                f"lost GRBL's replies on {self.url}: {error}; {who}: close it, or check the cable and power, "
                "then run again"
            )
        return GrblConnectionError(
            f"lost the connection to GRBL on {self.url}: {error}; check the cable and power, then run again"
        )

    def _write(self, data: bytes) -> None:
        import serial

        self._trace(">", data.decode("ascii", "replace"))
        try:
            self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError) as error:
            raise self._io_error(error) from None

    def _trace(self, direction: str, text: str) -> None:
        log.debug("%s %s %r", self.url, direction, text)
        if self.on_line is not None:
            self.on_line(direction, text)

    def _read_line(self, deadline: float) -> str | None:
        """The next line GRBL sent, without its line end, or ``None`` when ``deadline`` passed."""
        import serial

        while True:
            end = self._rx.find(b"\n")
            if end >= 0:
                raw = bytes(self._rx[:end])
                del self._rx[: end + 1]
                text = raw.decode("ascii", "replace").strip("\r")
                if not text:
                    continue
                self._trace("<", text)
                return text
            if self.clock.monotonic() >= deadline:
                return None
            try:
                waiting = self._port.in_waiting
                chunk = self._port.read(waiting or 1)
            except (serial.SerialException, OSError) as error:
                raise self._io_error(error) from None
            if chunk:
                self._rx += chunk

    def _next_reply(self, deadline: float, *, context: str) -> Reply | None:
        """Read lines until one that matters to a waiting caller; handle push messages."""
        while True:
            text = self._read_line(deadline)
            if text is None:
                return None
            reply = parse_line(text, wco_mm=self._wco)
            if isinstance(reply, Status):
                self._remember(reply)
                return reply
            if isinstance(reply, Alarm):
                self._target = None
                if reply.code in FRAME_LOSING_ALARMS:
                    self.frame_alarm = f"ALARM:{reply.code} ({describe_alarm(reply.code)})"
                raise GrblAlarmError(reply.code, self.url, context)
            if isinstance(reply, Welcome):
                self._target = None
                self.reset_seen = True
                self.homed = False
                self.version = reply.version
                raise GrblConnectionError(
                    f"GRBL on {self.url} restarted during {context}: it printed its welcome line without being "
                    "asked, so its power, its USB connection or its reset line dropped, and its position restarted "
                    "at 0 wherever the carriage stood. Check the supply and cable, home the stage and run again"
                )
            if isinstance(reply, StartupLine):
                log.info("%s: GRBL ran its startup line %r: %s", self.url, reply.line, reply.result)
                continue
            if isinstance(reply, Unknown):
                if reply.text.startswith("<"):
                    return reply  # a garbled status report: the caller asks again
                log.warning("%s: ignoring unrecognised line %r from GRBL", self.url, text)
                continue
            if isinstance(reply, Message) and reply.kind == "MSG":
                log.info("%s: GRBL says %s", self.url, reply.text)
            return reply

    def _remember(self, status: Status) -> None:
        if status.wco_mm is not None:
            self._wco = status.wco_mm
        self._last_status = status

    def command(self, line: str, *, timeout_s: float | None = None) -> list[Reply]:
        """Send one line command and wait for its ``ok``; return the lines that came before it.

        Raises :class:`GrblCommandError` on ``error:N``, :class:`GrblAlarmError` on ``ALARM:N`` and
        :class:`GrblTimeoutError` when no answer arrives within ``timeout_s``. Never resends.
        """
        data = encode_line(line)
        self._write(data)
        timeout = self.reply_timeout_s if timeout_s is None else timeout_s
        deadline = self.clock.monotonic() + timeout
        collected: list[Reply] = []
        while True:
            reply = self._next_reply(deadline, context=repr(line))
            if reply is None:
                raise GrblTimeoutError(
                    f"GRBL on {self.url} did not answer {line!r} within {timeout:g} s{self._silence_cause()}; "
                    "the line may or may not have been executed, so it is not sent again. Check the stage, then "
                    "home it and run again (a capture resumes where it stopped)"
                )
            if isinstance(reply, Ok):
                return collected
            if isinstance(reply, Error):
                raise GrblCommandError(reply.code, line, self.url)
            if not isinstance(reply, (Status, Unknown)):
                collected.append(reply)

    def _silence_cause(self) -> str:
        """Why GRBL may have gone quiet, for a message: whether it still answers ``?``, and the other
        programs that have the port open (they may have read the reply)."""
        try:
            status = self._query_status(timeout_s=min(self.reply_timeout_s, 1.0), attempts=1)
        except GrblError:
            status = None
        if status is None:
            return "; it does not answer a status query either (power, cable?)" + self._holders_note()
        if status.state == "Idle":
            return f"; it reports {_describe(status)}: {self._lost_reply(status)}"
        return f"; it reports {_describe(status)}{self._holders_note()}"

    def _lost_reply(self, status: Status) -> str:
        """The likely cause of a reply that went missing while GRBL is ``Idle`` (``status``), for a
        message. In GRBL's send-response streaming only one line is outstanding, so any reply is
        lfrig's; an Idle GRBL (with ``Bf`` in its reports: the counts of empty buffers, as when the
        port opened) has answered every line it received, so another reader took the reply, or the
        line garbled it."""
        empty = status.buffer is not None and status.buffer == self._empty_buffer
        proof = (f" (its planner and serial buffers are as empty as when the port opened, Bf:{status.buffer[0]},"
                 f"{status.buffer[1]})" if empty and status.buffer else "")
        names = self._holder_names()
        if names:
            reader = f"{names}, which also has the port open, read it: close it"
        else:
            reader = f"another program read it ({HIDDEN_READER}): close it; or the line garbled it: check the cable"
        return (f"GRBL is Idle with nothing left to run{proof}, so it has answered every line it received, and the "
                f"reply went elsewhere; {reader}")

    def _connect(self, *, wake_s: float, reset: bool) -> None:
        # GRBL's interface: wake it up with blank lines and let it initialise. Then ask for a status
        # report until one comes: a controller that resets when the port opens prints its welcome
        # line first (kept as evidence of the reset), one that did not answers at once.
        self._write(WAKE)
        status = self._wake(wake_s)
        if status is None:
            self.silent_on_open = True
            if self.read_only:
                raise GrblTimeoutError(
                    f"GRBL on {self.url} sent no status report within {wake_s:g} s of the port opening: it sends "
                    "none while it runs a homing cycle or after a hard or soft limit (ALARM:1/2, waiting for a "
                    "reset), and none when it is off, still starting, or at another baud rate (115200)"
                    f"{self._holders_note()}; lfrig sent nothing that would stop it"
                )
            log.info("%s: no status report within %g s of opening the port; resetting it", self.url, wake_s)
        elif _is_moving(status) and not self.read_only:
            # A previous process left a motion running (killed mid-move): let it end, since a soft
            # reset in motion aborts it with ALARM:3 and the position is lost.
            log.info("%s: GRBL is still moving (%s); waiting for it to stop before the reset", self.url, status.state)
            status = self._wait_until_still(deadline=self.clock.monotonic() + self._motion_bound_s())
        if reset:
            self.reset()
        else:  # GRBL answers the wake's blank lines with "ok"s that may trail the status report
            self.clock.sleep(0.1)
            self._flush_input()
        if self.read_only and status is not None and status.state not in ("Idle", "Alarm"):
            self.open_state = status.state  # GRBL answers '$$' only when Idle or in Alarm
            return
        self.settings_values = self.read_settings()
        self._check_listing()
        self._check_units()
        if self.version is None:  # no welcome line read: ask for the build info, [VER:1.1h.20190830:]
            for reply in self.command("$I"):
                if isinstance(reply, Message) and reply.kind == "VER":
                    self.version = reply.text.split(":")[0] or None
        try:
            opened = self.status_report()
            self.open_state = opened.state
            if opened.state in ("Idle", "Alarm"):  # nothing queued: the Bf counts of empty buffers
                self._empty_buffer = opened.buffer
        except GrblTimeoutError:  # a critical alarm without the reset: GRBL answers nothing but 0x18
            self.open_state = None

    def _holder_names(self) -> str:
        """The other processes that have the port open (:func:`port_holders`), for a message, or ``""``.
        Those that had it open when lfrig opened it and have since let go are named too: a reader that
        took a reply may exit before the error is built."""
        now = port_holders(self.url)
        gone = [holder for holder in self._opened_with if holder not in now]
        return ", ".join([f"process {pid} ({name})" for pid, name in now] +
                         [f"process {pid} ({name}), which had it open when lfrig opened it and has since closed it"
                          for pid, name in gone])

    def _holders_note(self) -> str:
        names = self._holder_names()
        return f"; {names} also has the port open and may be reading GRBL's replies: close it" if names else ""

    def _check_listing(self) -> None:
        """Refuse a ``$$`` listing without the settings that place a step in the machine frame
        (:data:`FRAME_SETTINGS`, all reported by GRBL 1.1): lines of it were lost on the way, or read
        by another program, and a travel check or a capture's frame built on it would be wrong."""
        missing = [f"${n}" for n in FRAME_SETTINGS if n not in self.settings_values]
        if missing:
            raise GrblProtocolError(
                f"GRBL on {self.url} listed its settings ($$) without {', '.join(missing)}: lines of its reply were "
                f"lost{self._holders_note() or ' (another program reading the port, or noise on the line)'}; "
                "run again"
            )

    def _check_units(self) -> None:
        """Refuse a controller that reports inches (``$13=1``): every position lfrig reads, checks and
        journals is in mm."""
        if int(self.settings_values.get(13, 0)) & 1:
            raise GrblSettingsError(
                f"GRBL on {self.url} reports positions in inches ($13=1), and lfrig reads, checks and records "
                "them as millimetres; set $13=0 (send `$13=0` from a serial terminal), then run again"
            )

    def _wake(self, wake_s: float) -> Status | None:
        """Read what GRBL sends for up to ``wake_s``, asking for a status report every 0.25 s; return
        the first one (``None`` if none came). A welcome line seen on the way means the controller
        reset when the port opened (``reset_seen``), however long its bootloader took."""
        deadline = self.clock.monotonic() + wake_s
        next_query = self.clock.monotonic()
        while True:
            now = self.clock.monotonic()
            if now >= deadline:
                return None
            if now >= next_query:
                self._write(STATUS_QUERY)
                next_query = now + 0.25
            text = self._read_line(min(deadline, next_query))
            if text is None:
                continue
            reply = parse_line(text, wco_mm=self._wco)
            if isinstance(reply, Welcome):
                self.reset_seen = True
                self.version = reply.version
                log.info("%s: GRBL reset when the port opened (welcome line %r)", self.url, text)
            elif isinstance(reply, Alarm):
                log.warning("%s: GRBL reported ALARM:%d (%s) before lfrig connected", self.url, reply.code,
                            describe_alarm(reply.code))
            elif isinstance(reply, Status) and reply.mpos_mm is not None:
                self._remember(reply)
                return reply

    def _motion_bound_s(self) -> float:
        """Long enough for any single move GRBL may still be running (the whole travel diagonal at
        the slowest rate), or a homing cycle."""
        s = self.settings_values
        travel = travel_limits_mm(s) if s else None
        diagonal = math.sqrt(sum((hi - lo) ** 2 for lo, hi in travel)) if travel else 500.0
        rate = min((s.get(110 + i, 500.0) for i in range(3)), default=500.0) if s else 100.0
        accel = min((s.get(120 + i, 10.0) for i in range(3)), default=10.0) if s else 10.0
        return max(motion_time_s(diagonal, rate_mm_min=rate, accel_mm_s2=accel), 60.0 if not s else 0.0) + 10.0

    def _wait_until_still(self, *, deadline: float) -> Status | None:
        """Poll ``?`` until GRBL is not moving (reports do not come during homing). Raises
        :class:`GrblTimeoutError` at ``deadline``."""
        status: Status | None = None
        while True:
            try:
                status = self.status_report()
                if not _is_moving(status):
                    return status
            except GrblTimeoutError:
                pass  # homing: no reports until it ends
            if self.clock.monotonic() >= deadline:
                raise GrblTimeoutError(
                    f"GRBL on {self.url} was still moving when lfrig connected and did not stop "
                    f"(last report: {_describe(status)}); check the stage, then run again"
                )
            self.clock.sleep(self.poll_s)

    def _flush_input(self) -> None:
        import serial

        try:
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError) as error:
            raise self._io_error(error) from None
        self._rx.clear()

    def reset(self) -> list[int]:
        """Soft reset (``0x18``) and wait for the welcome line. Clears queued motions. Returns the
        alarm codes GRBL raised on the way: a reset during motion raises ``ALARM:3`` (steps may have
        been lost), which sets :attr:`homing_required`."""
        self._write(SOFT_RESET)
        deadline = self.clock.monotonic() + self.reply_timeout_s
        alarms: list[int] = []
        while True:
            text = self._read_line(deadline)
            if text is None:
                silent = " nor to status queries for the first seconds after the port opened" if self.silent_on_open else ""
                raise GrblTimeoutError(
                    f"GRBL on {self.url} did not answer a soft reset within {self.reply_timeout_s:g} s{silent}: is the "
                    f"controller powered and connected, is it GRBL, at the right baud rate (115200)?{self._holders_note()}"
                )
            reply = parse_line(text)
            if isinstance(reply, Alarm):
                alarms.append(reply.code)
            if isinstance(reply, Welcome):
                self.version = reply.version
                self._target = None
                self._wco = None
                break
        for code in alarms:
            if code in (1, 3, 6):
                self.homing_required = f"ALARM:{code} ({describe_alarm(code)})"
                self._homing_required_code = code
                self.homed = False
                log.warning("%s: GRBL raised ALARM:%d at the soft reset: %s", self.url, code, describe_alarm(code))
        # Messages that follow the welcome ([MSG:'$H'|'$X' to unlock], startup lines) are read by
        # whatever command comes next.
        return alarms

    def machine_frame_doubt(self) -> str | None:
        """Why GRBL's machine coordinates may not be the frame they were before this connection, or
        ``None`` when nothing says so (homed through this driver, or no reset and no lock seen)."""
        if self.homing_required:
            return f"GRBL raised {self.homing_required}"
        if self.frame_alarm:
            return f"GRBL raised {self.frame_alarm}"
        if self.homed:
            return None
        if self.reset_seen:
            return (
                "GRBL reset when the port opened (it printed its welcome line; Arduino boards reset on open), "
                "so its machine position restarted at 0 wherever the carriage stood"
            )
        if self.silent_on_open:
            return (
                "GRBL did not answer for the first seconds after the port opened (still starting after a reset, "
                "or halted), so lfrig cannot tell whether its machine position restarted"
            )
        if self.open_state == "Alarm":
            return (
                "GRBL was in Alarm when the port opened (after a power-up with homing enabled, a reset during a "
                "move or a limit), so its position is not known to be the one it had"
            )
        return None

    # -- settings -----------------------------------------------------------------------------
    def read_settings(self) -> dict[int, float]:
        """The controller's ``$$`` settings as ``{number: value}``."""
        replies = self.command("$$")
        return {r.number: r.value for r in replies if isinstance(r, Setting)}

    def limits_mm(self) -> tuple[tuple[float, float], ...] | None:
        """Per-axis ``(min, max)`` machine coordinates a move may target (:func:`travel_limits_mm`), or
        ``None`` when the machine frame does not come from homing (soft limits ``$20`` off and not
        hard limits ``$21`` with homing ``$22``) or the travel is unknown."""
        s = self.settings_values
        if not (int(s.get(20, 0)) or (int(s.get(21, 0)) and int(s.get(22, 0)))):
            return None
        return travel_limits_mm(s)

    def settings(self) -> dict[str, Any]:
        """What is worth recording about this stage."""
        return {
            "driver": "grbl",
            "url": self.url,
            "version": self.version,
            "tolerance_mm": self.tolerance_mm,
            "limits_mm": self.limits_mm(),
            "grbl_settings": {f"${k}": v for k, v in sorted(self.settings_values.items())},
        }

    def frame_settings(self) -> dict[str, float]:
        """The controller's :data:`FRAME_SETTINGS` as ``{"$N": value}`` (those it reported)."""
        return {f"${n}": self.settings_values[n] for n in FRAME_SETTINGS if n in self.settings_values}

    def still_mm(self) -> tuple[float, float, float] | None:
        """Where the stage stands, from a fresh status report (``Idle`` or ``Alarm``), in mm; ``None``
        when it moves, does not answer within 0.5 s, or the port is closed."""
        if self._closed:
            return None
        try:
            status = self._query_status(timeout_s=min(self.reply_timeout_s, 0.5), attempts=2)
        except GrblError:
            return None
        if status is None or status.state not in ("Idle", "Alarm"):
            return None
        return status.mpos_mm

    # -- Stage protocol -----------------------------------------------------------------------
    @property
    def home_timeout_s(self) -> float:
        """How long ``$H`` may take: as given, else the homing time bound of the controller's
        settings (:func:`homing_time_bound_s`) x 1.25 + 5 s."""
        if self._home_timeout_s is not None:
            return self._home_timeout_s
        if not self.settings_values:
            return 120.0
        return 1.25 * homing_time_bound_s(self.settings_values) + 5.0

    @home_timeout_s.setter
    def home_timeout_s(self, value: float | None) -> None:
        self._home_timeout_s = value

    def home(self) -> None:
        """``$H`` (wait for the cycle to finish), then ``G90 G21``."""
        self._target = None
        self.homed = False
        self._homing = True  # stays set when a Ctrl-C interrupts the wait: interrupt() must reset
        try:
            self.command("$H", timeout_s=self.home_timeout_s)
        except GrblError:
            self._homing = False
            raise
        self._homing = False
        self.homed = True
        self.homing_required = None
        self._homing_required_code = 0
        self.frame_alarm = None
        self.prepare()

    def _refuse_if_homing_required(self, action: str) -> None:
        if self.homing_required is None:
            return
        if int(self.settings_values.get(22, 1)) and action == "unlocking":
            advice = "home the stage instead (`lfrig stage home`): unlocking would keep a position that may be wrong"
        elif int(self.settings_values.get(22, 1)):
            advice = f"home the stage (`lfrig stage home`, or capture without --no-home) before {action}"
        else:
            advice = (f"enable homing ($22=1) and home the stage before {action}; if you have checked the position "
                      "by other means, `lfrig stage unlock` clears the lock")
        raise GrblAlarmError(self._homing_required_code or 3, self.url, "an earlier soft reset", advice=advice)

    def prepare(self) -> None:
        """``G90 G21``: absolute coordinates in millimetres, assumed by every move."""
        self._refuse_if_homing_required("moving")
        self.command("G90 G21")

    def unlock(self) -> None:
        """``$X``: clear an alarm lock without homing (the position may be wrong), then ``G90 G21``.
        Refused after this driver saw ``ALARM:3`` (steps may have been lost): home instead."""
        self._refuse_if_homing_required("unlocking")
        self.command("$X")
        self.prepare()

    def _check_limits(self, position: tuple[float, float, float]) -> None:
        limits = self.limits_mm()
        if limits is None:
            return
        for axis, (value, (lo, hi)) in enumerate(zip(position, limits)):
            if not (lo - 1e-9 <= value <= hi + 1e-9):
                raise GrblLimitError(
                    f"target {'XYZ'[axis]}={value:.3f} mm is outside the machine travel [{lo:.3f}, {hi:.3f}] mm "
                    f"of {self.url}; nothing was sent. Move the grid centre or shrink the grid"
                )

    def check_step_grid(self, targets_mm: Sequence[Sequence[float]], *, tolerance_mm: float | None = None) -> None:
        """Refuse targets that GRBL cannot reach within ``tolerance_mm`` (default :attr:`tolerance_mm`)
        because they lie between two motor steps (``$100..$102`` steps/mm): GRBL would stop on the
        nearest step and the move would fail its position check. Raises :class:`GrblStepError` for the
        first such target, before anything moves; :meth:`off_step_grid` lists them all."""
        problems = self.off_step_grid(targets_mm, tolerance_mm=tolerance_mm)
        if problems:
            raise GrblStepError(problems[0] + (f" (and {len(problems) - 1} more targets)" if len(problems) > 1 else ""))

    def off_step_grid(self, targets_mm: Sequence[Sequence[float]], *, tolerance_mm: float | None = None) -> list[str]:
        """One message per target (``(x, y, z)`` in mm) that lies farther than ``tolerance_mm`` from
        GRBL's nearest motor step on some axis (:func:`step_grid_offsets_mm`)."""
        tolerance = self.tolerance_mm if tolerance_mm is None else tolerance_mm
        problems = []
        for target in targets_mm:
            for axis, offset in enumerate(step_grid_offsets_mm(target, self.settings_values)):
                if offset > tolerance + 1e-9:
                    steps = float(self.settings_values[100 + axis])
                    problems.append(
                        f"target {'XYZ'[axis]}={float(target[axis]):.3f} mm lies {offset:.4f} mm from the nearest motor "
                        f"step of {self.url} (${100 + axis}={steps:g} steps/mm: steps of {1 / steps:.4f} mm), more than "
                        f"the tolerance {tolerance:g} mm; GRBL would stop on the step and the move fail its check. "
                        f"Choose a pitch and centre on multiples of {1 / steps:.4f} mm, or raise --tolerance-mm"
                    )
                    break
        return problems

    def move_to(self, position_mm: Sequence[float], *, feed_mm_min: float | None = None) -> None:
        """Start an absolute move (``G0``, or ``G1`` at ``feed_mm_min``). Returns once GRBL has
        accepted the line, usually before the motion ends: call :meth:`wait_until_idle`."""
        position = tuple(float(c) for c in position_mm)
        if len(position) != 3:
            raise ValueError(f"position must be (x, y, z) in mm; got {position_mm!r}")
        self._refuse_if_homing_required("moving")
        self._check_limits(position)  # type: ignore[arg-type]
        data = encode_move(position, feed_mm_min=feed_mm_min)
        start = self._last_status.mpos_mm if self._last_status is not None else None
        self._target = None
        self.command(data.decode("ascii").rstrip("\n"))
        self._target = position  # type: ignore[assignment]
        self._move_estimate_s = self._estimate_s(start, position, feed_mm_min)

    def jog(self, delta_mm: Sequence[float], *, feed_mm_min: float) -> None:
        """Start a relative jog (:func:`encode_jog`); returns once GRBL has queued it. A target beyond
        the travel is refused by GRBL (:class:`GrblCommandError` ``error:15``) and nothing moves."""
        self._refuse_if_homing_required("jogging")
        self._target = None
        self.command(encode_jog(delta_mm, feed_mm_min=feed_mm_min).decode("ascii").rstrip("\n"))

    def jog_cancel(self) -> None:
        """Stop jogging: :data:`JOG_CANCEL` (decelerate, drop queued jogs, keep the position)."""
        self._write(JOG_CANCEL)

    def _estimate_s(self, start, end, feed_mm_min) -> float:
        s = self.settings_values
        rates = [s.get(110 + i, 500.0) for i in range(3)]
        accels = [s.get(120 + i, 10.0) for i in range(3)]
        if start is None:
            limits = travel_limits_mm(s)
            distance = math.sqrt(sum((hi - lo) ** 2 for lo, hi in limits)) if limits else 500.0
        else:
            distance = math.dist(start, end)
        rate = min(rates) if feed_mm_min is None else min(feed_mm_min, min(rates))
        return motion_time_s(distance, rate_mm_min=rate, accel_mm_s2=min(accels))

    def wait_until_idle(self, *, timeout_s: float | None = None) -> tuple[float, float, float]:
        """Wait for the commanded motion to finish: ``G4 P0`` answered ``ok``, then a ``?`` report in
        ``Idle`` within ``tolerance_mm`` of the target. Returns the reported machine position."""
        if timeout_s is None:
            timeout_s = 2.0 * getattr(self, "_move_estimate_s", 0.0) + self.move_timeout_margin_s
        start = self.clock.monotonic()
        try:
            self.command("G4 P0", timeout_s=timeout_s)
        except GrblTimeoutError:
            target = self._target
            try:
                status: Status | None = self._query_status(timeout_s=min(self.reply_timeout_s, 1.0), attempts=2)
            except GrblError:
                status = None
            if status is None:
                raise GrblTimeoutError(
                    f"GRBL on {self.url} stopped answering during the move to {_fmt(target)}: no reply to 'G4 P0' "
                    f"within {timeout_s:.1f} s and none to a status query{self._holders_note()}. Check its power "
                    "and cable; then home the stage and run again"
                ) from None
            if status.state == "Idle":
                raise GrblTimeoutError(
                    f"GRBL on {self.url} did not answer 'G4 P0' after the move to {_fmt(target)} within "
                    f"{timeout_s:.1f} s, yet reports {_describe(status)}: {self._lost_reply(status)}. Nothing was "
                    "resent: home the stage and run again (a capture resumes where it stopped)"
                ) from None
            stopped = self._stop_quietly() if _is_moving(status) else ""
            raise GrblTimeoutError(
                f"the stage on {self.url} did not finish its move to {_fmt(target)} within {timeout_s:.1f} s: "
                f"GRBL reports {_describe(status)}{stopped}{self._holders_note()}; an axis may be stalled or "
                "blocked. Check the mechanics, home the stage and run again"
            ) from None
        remaining = max(timeout_s - (self.clock.monotonic() - start), self.reply_timeout_s)
        deadline = self.clock.monotonic() + remaining
        while True:
            status = self.status_report()
            if status.state == "Idle" and status.mpos_mm is not None:
                if self._target is None:
                    return status.mpos_mm
                error = max(abs(a - b) for a, b in zip(status.mpos_mm, self._target))
                if error <= self.tolerance_mm:
                    return status.mpos_mm
                raise GrblPositionError(
                    f"the stage on {self.url} is Idle at {_fmt(status.mpos_mm)} but was sent to {_fmt(self._target)} "
                    f"({error:.4f} mm off, tolerance {self.tolerance_mm} mm); home it and run again"
                )
            if status.state == "Alarm":
                raise GrblError(
                    f"the stage on {self.url} is in Alarm state after a move to {_fmt(self._target)}; "
                    "home it and run again"
                )
            if self.clock.monotonic() >= deadline:
                raise GrblTimeoutError(
                    f"the stage on {self.url} did not report Idle at {_fmt(self._target)} within {timeout_s:.1f} s "
                    f"(last report: {_describe(status)})"
                )
            self.clock.sleep(self.poll_s)

    def _stop_quietly(self) -> str:
        """:meth:`stop`, for an error path: what to add to the message."""
        try:
            self.stop()
        except GrblError as error:
            return f"; stopping it failed ({error})"
        return "; lfrig stopped it (feed hold, then soft reset)"

    #: How many times a status query is sent when the reports come back garbled (noise on the line).
    STATUS_ATTEMPTS = 4

    def _query_status(self, *, timeout_s: float, attempts: int) -> Status | None:
        """Send ``?`` and return the next status report with a machine position; ask again, up to
        ``attempts`` times in all, after a garbled report. ``None`` when no report came in time."""
        garbled: list[str] = []
        for _ in range(attempts):
            self._write(STATUS_QUERY)
            deadline = self.clock.monotonic() + timeout_s
            while True:
                reply = self._next_reply(deadline, context="a status query")
                if reply is None:
                    return None
                if isinstance(reply, Unknown):  # a garbled report: ask again
                    log.warning("%s: garbled status report %r; asking again", self.url, reply.text)
                    garbled.append(reply.text)
                    break
                if isinstance(reply, Status):
                    if reply.mpos_mm is None:
                        # WPos without a known WCO yet: ask again, GRBL sends WCO within a few reports.
                        self._write(STATUS_QUERY)
                        continue
                    return reply
                if isinstance(reply, Error):
                    log.warning("%s: late error:%d (%s) while waiting for a status report", self.url, reply.code,
                                describe_error(reply.code))
                elif isinstance(reply, Ok):  # the answer to a blank line of the wake-up, or a late one
                    log.debug("%s: ok while waiting for a status report", self.url)
        raise GrblProtocolError(
            f"GRBL on {self.url} sent {len(garbled)} garbled status reports in a row (last: {garbled[-1]!r}); "
            "check the cable, its shielding and the baud rate (115200), then run again"
        )

    def status_report(self) -> Status:
        """Send ``?`` and return the next status report (asked again after a garbled one)."""
        status = self._query_status(timeout_s=self.reply_timeout_s, attempts=self.STATUS_ATTEMPTS)
        if status is None:
            raise GrblTimeoutError(
                f"GRBL on {self.url} sent no status report within {self.reply_timeout_s:g} s of '?'; it sends none "
                "while homing or after a hard or soft limit (waiting for a reset), or it is off or disconnected"
                f"{self._holders_note()}"
            )
        return status

    def status(self) -> dict[str, Any]:
        """The controller's state as a dict (``state``, ``mpos_mm``, ``wpos_mm``, ...)."""
        return self.status_report().as_dict()

    def position(self) -> tuple[float, float, float]:
        """The reported machine position (``MPos``) in mm."""
        mpos = self.status_report().mpos_mm
        assert mpos is not None
        return mpos

    def set_output(self, on: bool) -> None:
        """Switch the flood-coolant output (``M8``/``M9``), e.g. wired to a camera trigger input.
        GRBL synchronises coolant changes with motion, so this waits for running moves."""
        self.command("M8" if on else "M9")

    def interrupt(self) -> str:
        """Stop whatever lfrig started, after a Ctrl-C that may have come in the middle of a reply:
        a homing cycle only by a soft reset (GRBL ignores a feed hold while homing; the reset raises
        ``ALARM:6`` and the position is lost), a motion by :meth:`stop` (feed hold, then reset, so
        the position is kept). Returns what was done, for the user. Bytes already read stay: a
        line cut by the Ctrl-C is completed by what follows."""
        if self._homing:
            self._homing = False
            self.homed = False
            try:
                alarms = self.reset()
            except GrblTimeoutError:
                alarms = []
            self.homing_required = self.homing_required or "ALARM:6 (homing fail: the homing cycle was reset)"
            self._homing_required_code = self._homing_required_code or 6
            return ("homing stopped by a soft reset"
                    + (f" (GRBL raised {', '.join(f'ALARM:{c}' for c in alarms)})" if alarms else "")
                    + "; the position is lost")
        self.stop()
        if self.homing_required:
            return f"stopped by a feed hold and a soft reset, but GRBL raised {self.homing_required}"
        return "stopped by a feed hold, then a soft reset (the position is kept)"

    def stop(self) -> None:
        """Stop at once: feed hold (``!``), wait until GRBL reports the hold complete (``Hold:0``;
        the time a stop from the current speed takes at ``$120..$122``, with a margin), then soft
        reset. A reset before the hold completed would abort the motion (``ALARM:3``)."""
        self._write(FEED_HOLD)
        start = self.clock.monotonic()
        deadline: float | None = None
        status: Status | None = None
        while True:
            try:
                status = self.status_report()
            except GrblError:
                break
            if not _is_moving(status):
                break
            if deadline is None:  # from the first report after the hold: the speed it stops from
                speed = status.feed_mm_min
                if speed is None:
                    speed = max((self.settings_values.get(110 + i, 500.0) for i in range(3)), default=500.0)
                deadline = start + 1.5 * feed_hold_time_s(speed, self.settings_values) + max(self.reply_timeout_s, 0.5)
            if self.clock.monotonic() >= deadline:
                log.warning("%s: the feed hold did not complete within %.1f s (%s); resetting anyway",
                            self.url, self.clock.monotonic() - start, _describe(status))
                break
            self.clock.sleep(self.poll_s)
        try:
            self.reset()
        except GrblTimeoutError:
            log.warning("%s: no welcome line after the soft reset", self.url)
        self._target = None


def _is_moving(status: Status) -> bool:
    """Whether a report says the axes may be moving (a hold still decelerating counts)."""
    return status.state in ("Run", "Jog", "Home") or (status.state == "Hold" and status.substate == 1)


def _fmt(position: Sequence[float] | None) -> str:
    if position is None:
        return "(unknown)"
    return "(" + ", ".join(f"{c:.3f}" for c in position) + ") mm"


def _describe(status: Status | None) -> str:
    if status is None:
        return "none"
    state = status.state + (f":{status.substate}" if status.substate is not None else "")
    return f"{state} at {_fmt(status.mpos_mm)}"
