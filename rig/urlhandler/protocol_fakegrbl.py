"""``fakegrbl://``: pyserial's way to the simulated GRBL controller (:class:`rig.fakegrbl.FakeGrbl`).

pyserial imports this module for a ``fakegrbl://`` URL when ``rig.urlhandler`` is in
``serial.protocol_handler_packages`` (:func:`rig.grbl.open_port` puts it there) and opens a
:class:`Serial` on it, as it does ``loop://`` with ``serial.urlhandler.protocol_loop``.

- ``fakegrbl://NAME``: the controller made reachable with :func:`register` (the way ``lfrig
  --stage fake`` shares one controller between the driver and the simulated camera);
- ``fakegrbl://`` alone: a fresh controller;
- query options (:func:`parse_options`): ``clock=virtual|real``, ``fault=KIND``, ``after=N``.
"""

from __future__ import annotations

import itertools
import urllib.parse
from dataclasses import dataclass
from typing import Any

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from rig.clock import SystemClock, VirtualClock
from rig.fakegrbl import FAULTS, FakeGrbl


@dataclass(frozen=True)
class FakeOptions:
    """The query options of a ``fakegrbl://`` URL or an ``lfrig --stage fake?...`` spec."""

    clock: str
    fault: str | None = None
    after: int = 0


def parse_options(query: str, *, default_clock: str) -> FakeOptions:
    """Parse ``clock=virtual|real&fault=KIND&after=N``; raises ``ValueError`` naming what is wrong."""
    options = {k: v[-1] for k, v in urllib.parse.parse_qs(query).items()}
    unknown = set(options) - {"clock", "fault", "after"}
    if unknown:
        raise ValueError(f"unknown option(s) {', '.join(sorted(unknown))}; known: clock, fault, after")
    clock = options.get("clock", default_clock)
    if clock not in ("virtual", "real"):
        raise ValueError(f"clock must be 'virtual' or 'real'; got {clock!r}")
    fault = options.get("fault")
    if fault is not None and fault not in FAULTS:
        raise ValueError(f"unknown fault {fault!r}; choose one of {', '.join(FAULTS)}")
    try:
        after = int(options.get("after", "0"))
    except ValueError:
        raise ValueError(f"after must be a whole number of moves; got {options['after']!r}") from None
    if after < 0:
        raise ValueError(f"after must be 0 or more moves; got {after}")
    return FakeOptions(clock=clock, fault=fault, after=after)


_REGISTRY: dict[str, FakeGrbl] = {}
_names = itertools.count(1)


def register(controller: FakeGrbl, name: str | None = None) -> str:
    """Make ``controller`` reachable as ``fakegrbl://NAME``; returns the URL."""
    if name is None:
        name = f"fake{next(_names)}"
    if not name.replace("-", "").replace("_", "").isalnum():
        raise ValueError(f"fake GRBL names are letters, digits, '-' and '_'; got {name!r}")
    _REGISTRY[name] = controller
    return f"fakegrbl://{name}"


def unregister(name_or_url: str) -> None:
    _REGISTRY.pop(name_or_url.removeprefix("fakegrbl://"), None)


def controller_for_url(url: str) -> FakeGrbl:
    """The controller a ``fakegrbl://`` URL names (a new one for an unnamed URL)."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != "fakegrbl":
        raise SerialException(f"expected a fakegrbl:// URL; got {url!r}")
    name = (parts.netloc + parts.path).strip("/")
    try:
        options = parse_options(parts.query, default_clock="real")
    except ValueError as error:
        raise SerialException(f"{url!r}: {error}") from None
    if name:
        if name not in _REGISTRY:
            raise SerialException(f"no fake GRBL controller is registered as {name!r} (URL {url!r})")
        controller = _REGISTRY[name]
    else:
        controller = FakeGrbl(clock=SystemClock() if options.clock == "real" else VirtualClock())
    if options.fault is not None:
        controller.arm_fault(options.fault, after=options.after)
    return controller


class Serial(SerialBase):
    """A pyserial port whose other end is a :class:`FakeGrbl`. Reads wait on the controller's clock."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.controller: FakeGrbl | None = None
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self.is_open:
            raise SerialException("port is already open")
        if self._port is None:
            raise SerialException("port must be configured before it can be used")
        controller = controller_for_url(self.port)
        if self._exclusive and controller._ports_open:  # like a tty opened with exclusive=True (flock)
            raise SerialException(f"Could not exclusively lock port {self.port}: [Errno 11] Resource temporarily unavailable")
        self.controller = controller
        self.controller.power_on()
        self.controller._ports_open += 1
        self.is_open = True

    def close(self) -> None:
        if self.is_open and self.controller is not None:
            self.controller._ports_open = max(self.controller._ports_open - 1, 0)
        self.is_open = False

    def _reconfigure_port(self, *args: Any, **kwargs: Any) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_break_state(self) -> None:
        pass

    def _alive(self) -> FakeGrbl:
        if not self.is_open or self.controller is None:
            raise PortNotOpenError()
        if self.controller.disconnected:
            raise SerialException(f"device reports readiness to read but returned no data (device disconnected?) [{self.port}]")
        return self.controller

    @property
    def in_waiting(self) -> int:
        return self._alive().pending_output()

    def read(self, size: int = 1) -> bytes:
        controller = self._alive()
        clock = controller.clock
        timeout = self._timeout
        deadline = None if timeout is None else clock.monotonic() + timeout
        data = bytearray()
        while len(data) < size:
            data += controller.take_output(size - len(data))
            self._alive()
            if len(data) >= size or timeout == 0:
                break
            now = clock.monotonic()
            if deadline is not None and now >= deadline:
                break
            event = controller.next_event_time()
            wake = min(t for t in (deadline, event) if t is not None) if (deadline is not None or event is not None) else None
            if wake is None:
                raise SerialException(f"{self.port}: read() without a timeout would wait forever (nothing is running)")
            wait = max(wake - now, 0.0)
            if isinstance(clock, VirtualClock):
                clock.sleep(wait)
            else:
                clock.sleep(min(wait, 0.005))
        return bytes(data)

    def write(self, data: bytes) -> int:
        controller = self._alive()
        data = bytes(data)
        controller.receive(data)
        self._alive()
        return len(data)

    def flush(self) -> None:
        self._alive()

    def reset_input_buffer(self) -> None:
        self._alive().discard_output()

    def reset_output_buffer(self) -> None:
        self._alive()

    @property
    def out_waiting(self) -> int:
        return 0

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True


