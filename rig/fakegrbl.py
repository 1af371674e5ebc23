"""A simulated GRBL v1.1 controller with a three-axis stage, reachable through pyserial.

:class:`FakeGrbl` is a state machine on an injectable clock: bytes in (:meth:`FakeGrbl.receive`),
bytes out (:meth:`FakeGrbl.take_output`), and a physical stage whose position follows each move with a
trapezoidal speed profile from the feed rate (or the maximum rates ``$110..$112`` for ``G0``) and the
accelerations ``$120..$122``. It behaves like the firmware where the driver can tell:

- after power-up (every ``fakegrbl://`` port open, like an Arduino that resets on DTR) it prints its
  welcome line and, with homing enabled (``$22=1``), is in ``Alarm`` until homed (``$H``) or unlocked
  (``$X``); G-code in alarm gets ``error:9``;
- the step counter starts at 0 on power-up wherever the stage physically is; homing finds the switches
  at machine zero (or at ``-max_travel`` for an axis set in ``$23``) and leaves the stage ``$27``
  (pull-off) away from them; it gives up with ``ALARM:9`` beyond 1.5 x the travel;
- machine space is ``[-max_travel, 0]`` whichever end an axis homes to (GRBL 1.1h); soft limits
  (``$20=1``, refused without ``$22=1``) reject targets outside it with ``ALARM:2`` and
  ``[MSG:Reset to continue]``; hard limits (``$21=1``) raise ``ALARM:1`` when a move closes a switch;
  only a soft reset (``0x18``) is heard afterwards;
- work coordinate systems ``G54``..``G59`` (set by ``G10 L2``/``L20``, kept across resets like
  GRBL's EEPROM, ``G54`` again after a reset) offset every move but ``G53`` ones;
- ``ok`` for a motion line comes when it is planned, not when it is done; ``G4 P..`` is answered only
  when the planner has emptied and the dwell has elapsed; ``M8``/``M9`` also wait for the planner;
- real-time ``?`` (status report), ``!`` (feed hold: decelerate, ``Hold:1`` then ``Hold:0``), ``~``
  (resume) and ``0x18`` (soft reset; during motion it raises ``ALARM:3``, after a completed hold not);
- positions are whole motor steps (``$100..$102`` steps/mm);
- one port at a time may open it (pyserial's ``exclusive=True``, as on a tty).

Switchable faults (:meth:`FakeGrbl.arm_fault`), each triggered by the n-th motion line after arming:
``lost_ok`` (the line runs, its ``ok`` never comes), ``garbled`` (the line arrives corrupted and is
answered ``error:1``), ``alarm_mid_move`` (``ALARM:1`` hard limit part-way through the move),
``stall`` (the move stops part-way and never completes; the controller stays in ``Run``) and
``disconnect`` (the port dies: every read and write raises).

pyserial reaches it by URL through :mod:`rig.urlhandler.protocol_fakegrbl`:
``serial.serial_for_url("fakegrbl://NAME")`` opens the controller registered under ``NAME`` with
:func:`rig.urlhandler.protocol_fakegrbl.register` (``fakegrbl://`` alone makes a fresh one; query
options ``clock=virtual|real``, ``fault=KIND``, ``after=N``).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Sequence

from rig.clock import Clock, VirtualClock

# --------------------------------------------------------------------------------------------------
# Settings

#: ``$N`` defaults of the simulated controller: a small precision stage (100 x 100 x 50 mm travel,
#: 800 steps/mm, 600 mm/min, 50 mm/s^2), homing (seek 1000, locate 100 mm/min) and soft limits on,
#: status reports in MPos.
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 1, 21: 1, 22: 1, 23: 0, 24: 100.0, 25: 1000.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 800.0, 101: 800.0, 102: 800.0,
    110: 600.0, 111: 600.0, 112: 600.0,
    120: 50.0, 121: 50.0, 122: 50.0,
    130: 100.0, 131: 100.0, 132: 50.0,
}

FAULTS = ("lost_ok", "garbled", "alarm_mid_move", "stall", "disconnect")
PLANNER_BLOCKS = 15
LINE_BUFFER = 80  # GRBL's LINE_BUFFER_SIZE: at most 79 characters per line


# --------------------------------------------------------------------------------------------------
# Motion


@dataclass
class _Profile:
    """1D rest-or-moving-to-rest speed profile: starts at ``v0`` (mm/s), ends at rest after ``length``
    mm, cruising at most at ``vmax`` with acceleration ``accel`` (mm/s^2)."""

    t0: float
    length: float
    vmax: float
    accel: float
    v0: float = 0.0

    def __post_init__(self) -> None:
        a, v0, d = self.accel, self.v0, self.length
        vmax = max(self.vmax, v0)
        needed = (vmax * vmax - v0 * v0) / (2 * a) + vmax * vmax / (2 * a)
        if d >= needed:
            vp = vmax
        else:
            vp = math.sqrt(max((2 * a * d + v0 * v0) / 2.0, v0 * v0))
        self.vp = vp
        self.t_acc = (vp - v0) / a
        self.d_acc = (vp * vp - v0 * v0) / (2 * a)
        self.d_dec = vp * vp / (2 * a)
        cruise = max(d - self.d_acc - self.d_dec, 0.0)
        self.t_cruise = cruise / vp if vp > 0 else 0.0
        self.t_dec = vp / a
        self.duration = self.t_acc + self.t_cruise + self.t_dec

    @property
    def t_end(self) -> float:
        return self.t0 + self.duration

    def at(self, t: float) -> tuple[float, float]:
        """``(distance_mm, speed_mm_s)`` at time ``t``."""
        tau = min(max(t - self.t0, 0.0), self.duration)
        a, v0, vp = self.accel, self.v0, self.vp
        if tau < self.t_acc:
            return v0 * tau + 0.5 * a * tau * tau, v0 + a * tau
        tau -= self.t_acc
        if tau < self.t_cruise:
            return self.d_acc + vp * tau, vp
        tau -= self.t_cruise
        s = self.d_acc + vp * self.t_cruise + vp * tau - 0.5 * a * tau * tau
        if tau >= self.t_dec:
            return self.length, 0.0
        return min(s, self.length), max(vp - a * tau, 0.0)


@dataclass
class _Motion:
    start: tuple[float, float, float]
    target: tuple[float, float, float]  # where the block ends (the planned target)
    direction: tuple[float, float, float]
    profile: _Profile
    line_id: int
    stop_at_s: float | None = None  # stall / alarm: the distance where the motion freezes
    fault: str | None = None

    def position(self, t: float) -> tuple[float, float, float]:
        s, _ = self.profile.at(t)
        if s >= self.profile.length:
            return self.target
        return tuple(p + d * s for p, d in zip(self.start, self.direction))  # type: ignore[return-value]


def _line_rate(direction: Sequence[float], per_axis: Sequence[float]) -> float:
    """GRBL limits a line so that no axis exceeds its own value: min over moving axes of value/|dir|."""
    return min(value / abs(d) for value, d in zip(per_axis, direction) if abs(d) > 1e-12)


def _setting_text(key: int, value: float) -> str:
    """How GRBL prints a setting: rates, lengths and the like with 3 decimals, masks as integers."""
    if key >= 100 or key in (11, 12, 24, 25, 27) or not float(value).is_integer():
        return f"{float(value):.3f}"
    return str(int(value))


class _ParseError(Exception):
    def __init__(self, code: int) -> None:
        self.code = code


# --------------------------------------------------------------------------------------------------
# The controller


class FakeGrbl:
    """A simulated GRBL 1.1 controller and stage; see the module docstring.

    Parameters
    ----------
    clock
        Time source (default a new :class:`VirtualClock`).
    settings
        ``$N`` values overriding :data:`DEFAULT_SETTINGS`.
    start_mm
        Physical position of the stage at power-up, in homed machine coordinates (mm).
    version
        Printed in the welcome line.
    """

    def __init__(
        self,
        *,
        clock: Clock | None = None,
        settings: dict[int, float] | None = None,
        start_mm: Sequence[float] = (-40.0, -30.0, -20.0),
        version: str = "1.1h",
    ) -> None:
        self.clock: Clock = clock if clock is not None else VirtualClock()
        self.settings: dict[int, float] = {**DEFAULT_SETTINGS, **(settings or {})}
        self.version = version
        self._t = self.clock.monotonic()
        self._counter = (0.0, 0.0, 0.0)  # GRBL's step counter, as mm (machine position it reports)
        self._offset = tuple(float(c) for c in start_mm)  # physical = counter + offset
        self._out = bytearray()
        self._rx_line = bytearray()
        self._lines: deque[tuple[int, str]] = deque()
        self._planner: deque[tuple[tuple[float, float, float], float, int]] = deque()
        self._motion: _Motion | None = None
        self._hold_target: tuple[tuple[float, float, float], float, int] | None = None
        self._busy: tuple[str, float, Any] | None = None  # ("dwell"|"home", end time, payload)
        self.state = "Alarm" if self._homing_enabled else "Idle"
        self.substate: int | None = None
        self.critical = False
        self.homed = False
        self.disconnected = False
        self.powered = False
        self.coolant = False
        self.output_events: list[tuple[float, bool, tuple[float, float, float]]] = []
        self.rx_log = bytearray()
        self.lines_received: list[str] = []
        self.alarms: list[int] = []
        self._line_ids = itertools.count(1)
        self._suppress_ok: set[int] = set()
        self._faults: list[dict[str, Any]] = []
        self._line_fault: dict[int, tuple[str, float]] = {}  # line id -> (stall|alarm_mid_move, fraction)
        self._triggered: dict[int, str | None] = {}  # line id -> fault it triggered (decided once)
        self._reports = 0
        # work coordinate systems G54..G59 (1..6), kept like GRBL keeps them in EEPROM
        self.coordinate_systems: dict[int, tuple[float, float, float]] = {n: (0.0, 0.0, 0.0) for n in range(1, 7)}
        self._modal = {"motion": 0, "absolute": True, "mm": True, "feed": None, "wcs": 1}
        self._ports_open = 0

    # -- helpers ------------------------------------------------------------------------------
    @property
    def _homing_enabled(self) -> bool:
        return bool(int(self.settings.get(22, 0)))

    @property
    def _wco(self) -> tuple[float, float, float]:
        """The active work coordinate offset (G54..G59; no G92 or tool offsets here)."""
        return self.coordinate_systems[self._modal["wcs"]]

    def _switch_mm(self, axis: int) -> float:
        """Where the axis' limit switch is, in homed machine coordinates: 0, or ``-max_travel`` for an
        axis homing to its minimum (``$23``)."""
        return -abs(self.settings[130 + axis]) if int(self.settings.get(23, 0)) & (1 << axis) else 0.0

    def _distance_to_switch(self, start_physical: Sequence[float], direction: Sequence[float]) -> float | None:
        """Distance along a straight move from ``start_physical`` at which a limit switch closes
        (``None`` if none does): a hard limit's trigger."""
        mask = int(self.settings.get(23, 0))
        best = None
        for i, (p, d) in enumerate(zip(start_physical, direction)):
            switch = self._switch_mm(i)
            if mask & (1 << i):
                if p > switch and d < -1e-12:
                    s = (switch - p) / d
                    best = s if best is None else min(best, s)
            elif p < switch and d > 1e-12:
                s = (switch - p) / d
                best = s if best is None else min(best, s)
        return best

    def _spm(self, axis: int) -> float:
        return float(self.settings[100 + axis])

    def _quantise(self, position: Sequence[float]) -> tuple[float, float, float]:
        return tuple(round(p * self._spm(i)) / self._spm(i) for i, p in enumerate(position))  # type: ignore[return-value]

    def _emit(self, text: str) -> None:
        self._out += text.encode("ascii") + b"\r\n"

    # -- public inspection --------------------------------------------------------------------
    def advance(self, now: float | None = None) -> None:
        """Run the simulation up to ``now`` (default: the clock's time)."""
        now = self.clock.monotonic() if now is None else now
        while True:
            self._process_lines()
            event = self._next_internal_event()
            if event is None or event > now:
                break
            self._t = max(self._t, event)
            self._fire_events()
        self._t = max(self._t, now)

    def counter_position(self) -> tuple[float, float, float]:
        """The machine position GRBL would report now (mm)."""
        self.advance()
        return self._counter_at(self._t)

    def physical_position(self) -> tuple[float, float, float]:
        """Where the stage physically is now, in homed machine coordinates (mm). A fake camera's
        position source."""
        counter = self.counter_position()
        return tuple(c + o for c, o in zip(counter, self._offset))  # type: ignore[return-value]

    def is_moving(self) -> bool:
        """Whether the stage is physically in motion now."""
        self.advance()
        if self._motion is None:
            return self.state == "Home"
        m = self._motion
        if m.stop_at_s is not None and m.profile.at(self._t)[0] >= m.stop_at_s:
            return False  # stalled: stopped part-way (the controller still says Run)
        return self._t < m.profile.t_end

    def next_event_time(self) -> float | None:
        """When the simulation next changes by itself (a move ends, a dwell ends...), or ``None``."""
        self.advance()
        return self._next_internal_event()

    def arm_fault(self, kind: str, *, after: int = 0, fraction: float = 0.5) -> None:
        """Make the ``after + 1``-th motion line from now fail as ``kind`` (one of :data:`FAULTS`).
        ``fraction`` is how far through the move a ``stall`` or ``alarm_mid_move`` strikes."""
        if kind not in FAULTS:
            raise ValueError(f"unknown fault {kind!r}; choose one of {', '.join(FAULTS)}")
        self._faults.append({"kind": kind, "countdown": int(after), "fraction": float(fraction)})

    def clear_faults(self) -> None:
        self._faults.clear()

    # -- power and bytes ----------------------------------------------------------------------
    def power_on(self, *, start_mm: Sequence[float] | None = None) -> None:
        """What the firmware does at power-up, and when the port opens (Arduino boards reset on
        DTR): motion stops, the step counter restarts at 0 wherever the stage is (or at ``start_mm``,
        in homed machine coordinates, as if it had been moved by hand), and GRBL prints its welcome."""
        self._t = max(self._t, self.clock.monotonic())
        physical = tuple(c + o for c, o in zip(self._counter_at(self._t), self._offset))
        if start_mm is not None:
            physical = tuple(float(c) for c in start_mm)
        self._clear_motion()
        self._offset = physical  # type: ignore[assignment]
        self._counter = (0.0, 0.0, 0.0)
        self._out.clear()
        self._rx_line.clear()
        self._lines.clear()
        self.critical = False
        self.disconnected = False
        self.homed = False
        self.coolant = False
        self.powered = True
        self._modal = {"motion": 0, "absolute": True, "mm": True, "feed": None, "wcs": 1}
        self.state = "Alarm" if self._homing_enabled else "Idle"
        self.substate = None
        self._welcome()

    def _welcome(self) -> None:
        self._reports = 0
        self._emit("")
        self._emit(f"Grbl {self.version} ['$' for help]")
        if self.state == "Alarm":
            self._emit("[MSG:'$H'|'$X' to unlock]")

    def take_output(self, size: int | None = None) -> bytes:
        """Bytes the controller has sent and the host has not read yet (at most ``size``)."""
        self.advance()
        n = len(self._out) if size is None else min(size, len(self._out))
        data = bytes(self._out[:n])
        del self._out[:n]
        return data

    def pending_output(self) -> int:
        self.advance()
        return len(self._out)

    def discard_output(self) -> None:
        self.advance()
        self._out.clear()

    def receive(self, data: bytes) -> None:
        """Bytes from the host: real-time bytes act at once, the rest is split into lines."""
        self.advance()
        self.rx_log += data
        for byte in data:
            if byte == 0x18:
                self._soft_reset()
            elif self.critical:
                continue  # only a reset is heard after a critical alarm
            elif byte == ord("?"):
                if self.state != "Home":
                    self._status_report()
            elif byte == ord("!"):
                self._feed_hold()
            elif byte == ord("~"):
                self._cycle_start()
            elif byte == 0x85:
                self._jog_cancel()
            elif byte >= 0x80:
                continue  # overrides: accepted, not simulated
            elif byte in (ord("\n"), ord("\r")):
                text = self._rx_line.decode("ascii", "replace")
                self._rx_line.clear()
                line_id = next(self._line_ids)
                self.lines_received.append(text)
                self._lines.append((line_id, text))
            else:
                self._rx_line.append(byte)
        self.advance()

    # -- real-time commands -------------------------------------------------------------------
    def _status_report(self) -> None:
        t = self._t
        counter = self._counter_at(t)
        state = self.state + (f":{self.substate}" if self.substate is not None else "")
        feed = 0.0
        if self._motion is not None:
            feed = self._motion.profile.at(t)[1] * 60.0
            if self._motion.stop_at_s is not None and self._motion.profile.at(t)[0] >= self._motion.stop_at_s:
                feed = 0.0
        moving = self.state in ("Run", "Hold", "Jog", "Home")
        if int(self.settings.get(10, 1)) & 1:
            fields = [state, "MPos:" + ",".join(f"{c:.3f}" for c in counter)]
        else:
            fields = [state, "WPos:" + ",".join(f"{c - w:.3f}" for c, w in zip(counter, self._wco))]
        fields.append(f"FS:{feed:.0f},0")
        if self._reports % (10 if moving else 30) == 0:
            fields.append("WCO:" + ",".join(f"{w:.3f}" for w in self._wco))
        elif self._reports % (10 if moving else 20) == 1:
            fields.append("Ov:100,100,100")
        self._reports += 1
        self._emit("<" + "|".join(fields) + ">")

    def _jog_cancel(self) -> None:
        """0x85 in the Jog state: drop the queued jogs and decelerate to a stop, then Idle."""
        if self.state != "Jog":
            return
        self._planner.clear()
        motion = self._motion
        if motion is None:
            self.state, self.substate = "Idle", None
            return
        _, v = motion.profile.at(self._t)
        here = self._counter_at(self._t)
        if v <= 0:
            self._motion = None
            self._counter = here
            self.state, self.substate = "Idle", None
            return
        self._decelerate(motion, here, v)

    def _decelerate(self, motion: _Motion, here: tuple[float, float, float], v: float) -> None:
        """Replace ``motion`` (at ``here``, ``v`` mm/s) by a stop along its direction at its acceleration."""
        stop = v * v / (2 * motion.profile.accel)
        decel = _Profile(self._t, stop, v, motion.profile.accel, v0=v)
        end = tuple(p + d * stop for p, d in zip(here, motion.direction))
        self._motion = _Motion(here, self._quantise(end), motion.direction, decel, motion.line_id)  # type: ignore[arg-type]

    def _feed_hold(self) -> None:
        if self.state == "Jog":  # GRBL: a feed hold during a jog cancels it
            self._jog_cancel()
            return
        if self.state == "Idle":
            self.state, self.substate = "Hold", 0
            return
        if self.state != "Run" or self._motion is None:
            return
        motion = self._motion
        s, v = motion.profile.at(self._t)
        here = self._counter_at(self._t)
        self._hold_target = (motion.target, motion.profile.vmax, motion.line_id)
        if v <= 0 or (motion.stop_at_s is not None and s >= motion.stop_at_s):
            self._motion = None
            self._counter = here
            self.state, self.substate = "Hold", 0
            return
        self._decelerate(motion, here, v)
        self.state, self.substate = "Hold", 1

    def _cycle_start(self) -> None:
        if self.state == "Hold" and self.substate == 0:
            if self._hold_target is not None:
                target, vmax, line_id = self._hold_target
                self._hold_target = None
                self._planner.appendleft((target, vmax * 60.0, line_id))
                self.state, self.substate = "Run", None
                self._start_next_block()
            else:
                self.state, self.substate = "Idle", None

    def _soft_reset(self) -> None:
        moving = self.state in ("Run", "Jog") or (self.state == "Hold" and self.substate == 1)
        homing = self.state == "Home"
        self._counter = self._counter_at(self._t)
        self._clear_motion()
        self._lines.clear()
        self._rx_line.clear()
        self.critical = False
        self.coolant = False
        self._modal.update(motion=0, absolute=True, mm=True, feed=None, wcs=1)  # gc_init: GRBL's defaults, G54
        if homing:
            self._alarm(6, critical=False)
        elif moving:
            self._alarm(3, critical=False)
        elif self.state != "Alarm":
            self.state = "Idle"
        self.substate = None
        self._welcome()

    def _alarm(self, code: int, *, critical: bool) -> None:
        self.alarms.append(code)
        self.state, self.substate = "Alarm", None
        self.homed = self.homed and code == 2
        if critical:
            self.critical = True
            self._emit(f"ALARM:{code}")
            self._emit("[MSG:Reset to continue]")
        elif code in (3, 6):
            self._emit(f"ALARM:{code}")

    def _clear_motion(self) -> None:
        if self._motion is not None:
            self._counter = self._counter_at(self._t)
        self._motion = None
        self._planner.clear()
        self._hold_target = None
        self._busy = None

    # -- time stepping ------------------------------------------------------------------------
    def _counter_at(self, t: float) -> tuple[float, float, float]:
        if self._busy is not None and self._busy[0] == "home":
            _, end, (start, goal, t0, _line_id) = self._busy
            f = min(max((t - t0) / max(end - t0, 1e-9), 0.0), 1.0)
            return tuple(a + (b - a) * f for a, b in zip(start, goal))  # type: ignore[return-value]
        if self._motion is None:
            return self._counter
        m = self._motion
        if m.stop_at_s is not None:
            s, _ = m.profile.at(t)
            if s >= m.stop_at_s:
                return self._quantise(tuple(p + d * m.stop_at_s for p, d in zip(m.start, m.direction)))
        position = m.position(t)
        return position if position == m.target else self._quantise(position)

    def _next_internal_event(self) -> float | None:
        times = []
        if self._motion is not None:
            m = self._motion
            if m.stop_at_s is None:
                times.append(m.profile.t_end)
            elif m.fault == "alarm_mid_move":
                times.append(self._time_at_distance(m, m.stop_at_s))
            # a stalled motion never ends by itself
        if self._busy is not None:
            times.append(self._busy[1])
        return min(times) if times else None

    @staticmethod
    def _time_at_distance(m: _Motion, distance: float) -> float:
        lo, hi = m.profile.t0, m.profile.t_end
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if m.profile.at(mid)[0] < distance:
                lo = mid
            else:
                hi = mid
        return hi

    def _fire_events(self) -> None:
        t = self._t
        m = self._motion
        if m is not None:
            if m.fault == "alarm_mid_move" and m.stop_at_s is not None and t >= self._time_at_distance(m, m.stop_at_s):
                self._counter = self._counter_at(t)
                self._clear_motion()
                self._alarm(1, critical=True)
                return
            if m.stop_at_s is None and t >= m.profile.t_end:
                self._counter = m.target
                self._motion = None
                if self.state == "Hold":
                    self.substate = 0
                else:
                    self._start_next_block()
        if self._busy is not None and t >= self._busy[1]:
            kind, _, payload = self._busy
            self._busy = None
            if kind == "dwell":
                self._ok(payload)
            elif kind == "home":
                goal = payload[1]
                self._counter = self._quantise(goal)
                self._offset = (0.0, 0.0, 0.0)
                self.homed = True
                self.state, self.substate = "Idle", None
                self._ok(payload[3])

    def _start_next_block(self) -> None:
        if self._motion is not None:
            return
        if not self._planner:
            if self.state in ("Run", "Jog"):
                self.state, self.substate = "Idle", None
            return
        target, rate_mm_min, line_id = self._planner.popleft()
        start = self._counter
        delta = [b - a for a, b in zip(start, target)]
        length = math.sqrt(sum(d * d for d in delta))
        if length < 1e-12:
            self._counter = target
            self._start_next_block()
            return
        direction = tuple(d / length for d in delta)
        accel = _line_rate(direction, [self.settings[120 + i] for i in range(3)])
        vmax = min(rate_mm_min, _line_rate(direction, [self.settings[110 + i] for i in range(3)])) / 60.0
        motion = _Motion(start, target, direction, _Profile(self._t, length, vmax, accel), line_id)  # type: ignore[arg-type]
        fault = self._line_fault.pop(line_id, None)
        if fault is not None:
            kind, fraction = fault
            motion.fault = kind
            motion.stop_at_s = fraction * length
        if int(self.settings.get(21, 0)):  # hard limits: a switch closing on the way trips ALARM:1
            physical = tuple(c + o for c, o in zip(start, self._offset))
            hit = self._distance_to_switch(physical, direction)
            if hit is not None and hit <= length + 1e-9 and (motion.stop_at_s is None or hit < motion.stop_at_s):
                motion.fault = "alarm_mid_move"
                motion.stop_at_s = hit
        self._motion = motion
        if self.state in ("Idle", "Run"):
            self.state, self.substate = "Run", None

    # -- line processing ----------------------------------------------------------------------
    def _ok(self, line_id: int) -> None:
        if line_id in self._suppress_ok:
            self._suppress_ok.discard(line_id)
            return
        self._emit("ok")

    def _error(self, code: int) -> None:
        self._emit(f"error:{code}")

    def _planner_empty(self) -> bool:
        return self._motion is None and not self._planner and self.state not in ("Hold",)

    def _process_lines(self) -> None:
        while self._lines and self._busy is None and not self.critical:
            line_id, raw = self._lines[0]
            outcome = self._execute(line_id, raw)
            if outcome == "blocked":
                return
            self._triggered.pop(line_id, None)
            if self._lines and self._lines[0][0] == line_id:
                self._lines.popleft()

    def _take_motion_fault(self, line_id: int, text: str) -> str | None:
        """Count motion lines for armed faults; return the fault this line triggers, if any."""
        if not self._faults:
            return None
        stripped = text.upper().replace(" ", "")
        stripped = stripped[3:] if stripped.startswith("G53") else stripped  # machine-coordinate moves
        if not (stripped.startswith("G0") or stripped.startswith("G1")) or not any(a in stripped for a in "XYZ"):
            return None
        fault = self._faults[0]
        if fault["countdown"] > 0:
            fault["countdown"] -= 1
            return None
        self._faults.pop(0)
        if fault["kind"] in ("stall", "alarm_mid_move"):
            self._line_fault[line_id] = (fault["kind"], fault["fraction"])
        return fault["kind"]

    def _execute(self, line_id: int, raw: str) -> str:
        """Execute one line. Returns ``"done"`` or ``"blocked"`` (retry when the machine changes)."""
        if line_id not in self._triggered:
            self._triggered[line_id] = self._take_motion_fault(line_id, raw)
            kind = self._triggered[line_id]
            if kind == "disconnect":
                self.disconnected = True
                return "done"
            if kind == "lost_ok":
                self._suppress_ok.add(line_id)
            if kind == "garbled":
                index = next((i for i, c in enumerate(raw) if c.upper() in "XYZ"), 0)
                raw = raw[:index] + "#" + raw[index + 1 :]
                self._lines[0] = (line_id, raw)
        if self.disconnected:
            return "done"
        # GRBL's protocol layer: drop whitespace and comments, upper-case, check the length.
        text = self._clean(raw)
        if len(raw) >= LINE_BUFFER:
            self._error(11)
            return "done"
        if text == "":
            self._ok(line_id)
            return "done"
        if text.startswith("$"):
            return self._system_command(line_id, text)
        if self.state == "Alarm":
            self._error(9)
            return "done"
        try:
            block = self._parse_block(text)
        except _ParseError as error:
            self._error(error.code)
            return "done"
        return self._run_block(line_id, block)

    @staticmethod
    def _clean(raw: str) -> str:
        out = []
        depth = 0
        for c in raw:
            if c == "(":
                depth += 1
            elif c == ")" and depth:
                depth -= 1
            elif depth:
                continue
            elif c == ";":
                break
            elif c in " \t":
                continue
            else:
                out.append(c.upper())
        return "".join(out)

    def _system_command(self, line_id: int, text: str) -> str:
        if text.startswith("$J="):
            return self._jog(line_id, text[3:])
        if text == "$$":
            for key in sorted(self.settings):
                self._emit(f"${key}={_setting_text(key, self.settings[key])}")
            self._ok(line_id)
            return "done"
        if text == "$H":
            if not self._homing_enabled:
                self._error(5)
                return "done"
            if self.state not in ("Idle", "Alarm") or not self._planner_empty():
                self._error(8)
                return "done"
            self._start_homing(line_id)
            return "done"
        if text == "$X":
            if self.state == "Alarm":
                self.state, self.substate = "Idle", None
                self._emit("[MSG:Caution: Unlocked]")
            self._ok(line_id)
            return "done"
        if text == "$I":
            self._emit(f"[VER:{self.version}.20190830:lfrig fake]")
            self._emit("[OPT:V,15,128]")
            self._ok(line_id)
            return "done"
        if text == "$G":
            m = self._modal
            feed = m["feed"] or 0
            self._emit(
                f"[GC:G{m['motion']} G{53 + m['wcs']} G17 {'G21' if m['mm'] else 'G20'} {'G90' if m['absolute'] else 'G91'} "
                f"G94 M5 {'M8' if self.coolant else 'M9'} T0 F{feed:g} S0]"
            )
            self._ok(line_id)
            return "done"
        if text == "$#":
            for number, offset in sorted(self.coordinate_systems.items()):
                self._emit(f"[G{53 + number}:" + ",".join(f"{c:.3f}" for c in offset) + "]")
            self._emit("[G28:0.000,0.000,0.000]")
            self._emit("[G30:0.000,0.000,0.000]")
            self._emit("[G92:0.000,0.000,0.000]")
            self._emit("[TLO:0.000]")
            self._emit("[PRB:0.000,0.000,0.000:0]")
            self._ok(line_id)
            return "done"
        match = text[1:].partition("=")
        if match[1] and match[0].isdigit():
            if self.state not in ("Idle", "Alarm"):
                self._error(8)
                return "done"
            try:
                value = float(match[2])
            except ValueError:
                self._error(2)
                return "done"
            if value < 0:
                self._error(4)
                return "done"
            key = int(match[0])
            if key == 20 and value and not self._homing_enabled:
                self._error(10)  # soft limits need homing
                return "done"
            self.settings[key] = value
            if key == 22 and not value:
                self.settings[20] = 0  # GRBL turns soft limits off with homing
            self._ok(line_id)
            return "done"
        self._error(3)
        return "done"

    def _jog(self, line_id: int, text: str) -> str:
        """``$J=``: a jog block (GRBL 1.1). Allowed: G20/G21, G90/G91, G53, axis words and a feed F
        (required); the block's modes do not persist. Beyond the travel with soft limits on: error:15,
        nothing moves. Runs in the Jog state; 0x85 or a feed hold cancels it."""
        if self.state not in ("Idle", "Jog"):
            self._error(8)
            return "done"
        try:
            block = self._parse_block(text)
        except _ParseError as error:
            self._error(error.code)
            return "done"
        groups, words = block["groups"], block["words"]
        if (block["coolant"] is not None or "motion" in groups or groups.get("nonmodal") not in (None, 53)
                or any(k in words for k in "PLSTN")):
            self._error(16)
            return "done"
        if "F" not in words:
            self._error(22)
            return "done"
        if not any(a in words for a in "XYZ"):
            self._ok(line_id)  # GRBL 1.1h accepts a jog without axis words and moves nothing
            return "done"
        if len(self._planner) >= PLANNER_BLOCKS:
            return "blocked"
        scale = 1.0 if groups.get("units", 21 if self._modal["mm"] else 20) == 21 else 25.4
        absolute = groups.get("distance", 90 if self._modal["absolute"] else 91) == 90
        machine = groups.get("nonmodal") == 53
        base = self._planned_end()
        target = list(base)
        for i, a in enumerate("XYZ"):
            if a in words:
                value = words[a] * scale
                target[i] = value if machine else (value + self._wco[i] if absolute else base[i] + value)
        target_q = self._quantise(target)
        if int(self.settings.get(20, 0)) and not self._within_travel(target_q):
            self._error(15)
            return "done"
        self._planner.append((target_q, words["F"] * scale, line_id))
        if self.state == "Idle":
            self.state, self.substate = "Jog", None
            self._start_next_block()
        self._ok(line_id)
        return "done"

    def _start_homing(self, line_id: int) -> None:
        # Physical positions: switches at machine zero (default homing direction); the search runs
        # at $25, the locate and pull-off at $24 (Z first, then X and Y together).
        physical = tuple(c + o for c, o in zip(self._counter, self._offset))
        seek = self.settings[25] / 60.0
        locate = self.settings[24] / 60.0
        pulloff = self.settings[27]
        mask = int(self.settings.get(23, 0))
        switch = [self._switch_mm(i) for i in range(3)]
        distance = [abs(s - p) for s, p in zip(switch, physical)]
        if any(d > 1.5 * abs(self.settings[130 + i]) for i, d in enumerate(distance)):
            self._alarm(9, critical=False)  # GRBL searches 1.5 x the travel, then gives up
            self._emit("ALARM:9")
            return
        duration = distance[2] / seek + max(distance[0], distance[1]) / seek
        duration += 3 * pulloff / locate + 2 * self.settings[26] / 1000.0  # locate, pull off, debounce
        goal = tuple(s + pulloff if mask & (1 << i) else s - pulloff for i, s in enumerate(switch))
        # during homing the counter is meaningless to the host (no reports); show the physical path
        self._offset = (0.0, 0.0, 0.0)
        self._counter = physical  # type: ignore[assignment]
        self.state, self.substate = "Home", None
        self._busy = ("home", self._t + duration, (physical, goal, self._t, line_id))

    def _parse_block(self, text: str) -> dict[str, Any]:
        words: dict[str, float] = {}
        gcodes: list[float] = []
        mcodes: list[float] = []
        i = 0
        number = "0123456789.-+"
        while i < len(text):
            letter = text[i]
            if not ("A" <= letter <= "Z"):
                raise _ParseError(1)
            j = i + 1
            while j < len(text) and text[j] in number:
                j += 1
            try:
                value = float(text[i + 1 : j])
            except ValueError:
                raise _ParseError(2) from None
            if letter == "G":
                gcodes.append(value)
            elif letter == "M":
                mcodes.append(value)
            else:
                if letter in words:
                    raise _ParseError(25)
                if letter not in "XYZFPNSTL":
                    raise _ParseError(20)
                words[letter] = value
            i = j
        groups: dict[str, float] = {}
        for g in gcodes:
            group = {0: "motion", 1: "motion", 80: "motion", 4: "nonmodal", 10: "nonmodal", 53: "nonmodal",
                     20: "units", 21: "units", 90: "distance", 91: "distance", 17: "plane", 94: "feedmode",
                     54: "wcs", 55: "wcs", 56: "wcs", 57: "wcs", 58: "wcs", 59: "wcs"}.get(g)  # type: ignore[call-overload]
            if group is None:
                raise _ParseError(20)
            if group in groups:
                raise _ParseError(21)
            groups[group] = g
        coolant = None
        for m in mcodes:
            if m in (8, 9):
                if coolant is not None:
                    raise _ParseError(21)
                coolant = m == 8
            elif m not in (5,):
                raise _ParseError(20)
        if "F" in words and words["F"] < 0:
            raise _ParseError(4)
        if "P" in words and groups.get("nonmodal") not in (4, 10):
            raise _ParseError(36)
        if "L" in words and groups.get("nonmodal") != 10:
            raise _ParseError(36)
        if groups.get("nonmodal") == 10:
            if "L" not in words or "P" not in words:
                raise _ParseError(28)
            if words["L"] not in (2, 20):
                raise _ParseError(20)
            if not (0 <= words["P"] <= 6) or not float(words["P"]).is_integer():
                raise _ParseError(29)
            if not any(a in words for a in "XYZ"):
                raise _ParseError(26)
        if groups.get("nonmodal") == 4:
            if "P" not in words:
                raise _ParseError(28)
            if words["P"] < 0:
                raise _ParseError(4)
        return {"groups": groups, "words": words, "coolant": coolant}

    def _run_block(self, line_id: int, block: dict[str, Any]) -> str:
        groups, words = block["groups"], block["words"]
        axes = [a for a in "XYZ" if a in words]
        motion_mode = groups.get("motion", self._modal["motion"])
        # Things that must wait for the planner to empty: dwell and coolant (GRBL synchronises both).
        if (groups.get("nonmodal") == 4 or block["coolant"] is not None) and not self._planner_empty():
            return "blocked"
        if axes and motion_mode in (0, 1) and len(self._planner) >= PLANNER_BLOCKS:
            return "blocked"
        # Checks come before any state change (GRBL validates the whole block first).
        mm = groups.get("units", 21 if self._modal["mm"] else 20) == 21
        feed = words.get("F", self._modal["feed"])
        if "F" in words and not mm:
            feed = words["F"] * 25.4
        if axes and motion_mode == 1 and not feed:
            self._error(22)
            return "done"
        if axes and motion_mode == 80:
            self._error(31)
            return "done"
        if groups.get("nonmodal") == 53 and motion_mode not in (0, 1):
            self._error(30)
            return "done"
        # Apply modal state.
        if "F" in words:
            self._modal["feed"] = feed
        if "units" in groups:
            self._modal["mm"] = groups["units"] == 21
        if "distance" in groups:
            self._modal["absolute"] = groups["distance"] == 90
        if "motion" in groups:
            self._modal["motion"] = int(groups["motion"])
        if "wcs" in groups:
            self._modal["wcs"] = int(groups["wcs"]) - 53
        if groups.get("nonmodal") == 10:
            number = int(words["P"]) or self._modal["wcs"]
            offset = list(self.coordinate_systems[number])
            here = self._counter_at(self._t)
            scale = 1.0 if self._modal["mm"] else 25.4
            for i, a in enumerate("XYZ"):
                if a in words:  # L2: the offset itself; L20: so that here reads as the given value
                    offset[i] = words[a] * scale if words["L"] == 2 else here[i] - words[a] * scale
            self.coordinate_systems[number] = tuple(offset)  # type: ignore[assignment]
            self._ok(line_id)
            return "done"
        if block["coolant"] is not None:
            self.coolant = block["coolant"]
            self.output_events.append((self._t, self.coolant, self._counter_at(self._t)))
        if groups.get("nonmodal") == 4:
            self._busy = ("dwell", self._t + words["P"], line_id)
            return "done"
        if axes and motion_mode in (0, 1):
            scale = 1.0 if self._modal["mm"] else 25.4
            base = self._planned_end()
            target = list(base)
            machine = groups.get("nonmodal") == 53  # G53: machine coordinates, absolute
            wco = self._wco
            for i, a in enumerate("XYZ"):
                if a in words:
                    value = words[a] * scale
                    if machine:
                        target[i] = value
                    elif self._modal["absolute"]:
                        target[i] = value + wco[i]
                    else:
                        target[i] = base[i] + value
            target_q = self._quantise(target)
            if int(self.settings.get(20, 0)) and not self._within_travel(target_q):
                self._clear_motion()
                self._alarm(2, critical=True)
                self._lines.clear()
                return "done"
            rate = feed if motion_mode == 1 else float("inf")
            self._planner.append((target_q, rate, line_id))
            if self.state == "Idle":
                self._start_next_block()
            self._ok(line_id)
            return "done"
        self._ok(line_id)
        return "done"

    def _planned_end(self) -> tuple[float, float, float]:
        if self._planner:
            return self._planner[-1][0]
        if self._motion is not None:
            return self._motion.target
        return self._counter

    def _within_travel(self, target: Sequence[float]) -> bool:
        # GRBL 1.1h: machine space is [-max_travel, 0] whichever end an axis homes to ($23)
        for i, value in enumerate(target):
            lo, hi = -abs(self.settings[130 + i]), 0.0
            if not (lo - 1e-9 <= value <= hi + 1e-9):
                return False
        return True
