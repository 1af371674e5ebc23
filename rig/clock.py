"""Clocks: the driver, the fake controller, the cameras and the capture session share one, so a
simulated session can run on virtual time.

- :class:`Clock`: the protocol (``monotonic()``, ``sleep(seconds)``);
- :class:`SystemClock`: the wall clock;
- :class:`VirtualClock`: simulated time whose :meth:`~VirtualClock.sleep` advances at once.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """A monotonic clock that can wait."""

    def monotonic(self) -> float:
        """Seconds since an arbitrary origin; never decreases."""

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` (>= 0)."""


class SystemClock:
    """The wall clock: :func:`time.monotonic` and :func:`time.sleep`."""

    def monotonic(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class VirtualClock:
    """Simulated time: :meth:`sleep` advances it at once. Share one between the fake controller, the
    driver and the capture session to simulate a whole session in milliseconds."""

    def __init__(self, start: float = 0.0) -> None:
        self._now = float(start)

    def monotonic(self) -> float:
        return self._now

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self._now += seconds

    def advance(self, seconds: float) -> None:
        self.sleep(seconds)
