"""The progress protocol every long piece of lfrig work reports through, and the bar that shows it.

Long work takes ``progress`` as a keyword option: ``None``, or any callable
``progress(fraction, message)`` (:class:`ProgressCallback`), called with the share of the work done
(``0.0 .. 1.0``, never decreasing) and a short text of what is happening now ("u03 v04",
"matching", "IMG_0012.png"). A function that runs another one as a part of its work hands on
:func:`part` of its own callback.

:class:`Progress` is the bar the command line shows: on a terminal it redraws one line on stderr;
otherwise (a log file, CI) it prints a line at most every few seconds, so logs stay short. The ETA
comes from this run's own rate, so resumed work (a first fraction above 0) does not count the work
an earlier run did. :func:`step` shows a step that reports no fraction (its start and its end).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Protocol, TextIO


class ProgressCallback(Protocol):
    """``progress(fraction, message)``: ``fraction`` of the work done in ``[0, 1]``, what is happening now."""

    def __call__(self, fraction: float, message: str = "") -> None: ...


def report(progress: ProgressCallback | None, fraction: float, message: str = "") -> None:
    """Call ``progress(fraction, message)`` when there is a callback."""
    if progress is not None:
        progress(fraction, message)


def part(progress: ProgressCallback | None, start: float, end: float) -> ProgressCallback | None:
    """The callback for a part of the work that spans ``start .. end`` of ``progress``'s fraction."""
    if progress is None:
        return None
    span = end - start

    def sub(fraction: float, message: str = "") -> None:
        progress(start + span * min(max(fraction, 0.0), 1.0), message)

    return sub


def clock_text(seconds: float) -> str:
    """``MM:SS``, or ``H:MM:SS`` from an hour on."""
    seconds = int(round(seconds))
    minutes, seconds = divmod(seconds, 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes:02d}:{seconds:02d}"


class Progress:
    """A progress bar with ETA: ``bar = Progress("matching")``, pass ``bar`` as ``progress=``, then
    ``bar.close()`` (or use it as a context manager).

    Parameters
    ----------
    label
        What is being done, shown first.
    stream
        Where to write; default stderr.
    quiet
        Write nothing.
    interval_s
        Least time between two lines when the stream is not a terminal.
    """

    def __init__(self, label: str, *, stream: TextIO | None = None, quiet: bool = False,
                 interval_s: float = 5.0) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval_s = 0.1 if self.tty else interval_s
        self.start = time.monotonic()
        self.start_fraction: float | None = None
        self.fraction = 0.0
        self.message = ""
        self.last = -1e9
        self.shown: tuple[float, str] | None = None

    def eta_s(self) -> float | None:
        """Seconds left at this run's mean rate, or ``None`` before any work of this run is done."""
        if self.start_fraction is None:
            return None
        taken = self.fraction - self.start_fraction
        if taken <= 0:
            return None
        return (time.monotonic() - self.start) / taken * (1.0 - self.fraction)

    def line(self) -> str:
        width = 24
        filled = int(width * self.fraction)
        eta = self.eta_s()
        eta_text = "--:--" if eta is None or self.fraction >= 1.0 else clock_text(eta)
        message = f"  {self.message}" if self.message else ""
        return (f"{self.label} [{'#' * filled}{'.' * (width - filled)}] {100 * self.fraction:5.1f}%{message}  "
                f"{clock_text(time.monotonic() - self.start)} elapsed, ETA {eta_text}")

    def __call__(self, fraction: float, message: str = "") -> None:
        """Record progress (:class:`ProgressCallback`); redraws when due, and always at the end."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        if self.start_fraction is None:
            self.start_fraction = fraction
            self.start = time.monotonic()
        self.fraction = max(self.fraction, fraction)
        if message:
            self.message = message
        now = time.monotonic()
        if self.quiet or (now - self.last < self.interval_s and self.fraction < 1.0):
            return
        self.last = now
        self._write()

    def say(self, text: str) -> None:
        """Print a line of its own (a warning, an interruption) without breaking the bar."""
        if self.quiet:
            return
        self.stream.write(("\n" if self.tty else "") + text + "\n")
        self.stream.flush()

    def _write(self) -> None:
        self.shown = (self.fraction, self.message)
        self.stream.write(("\r" if self.tty else "") + self.line() + ("" if self.tty else "\n"))
        self.stream.flush()

    def close(self) -> None:
        """Show the final state (once) and end the line."""
        if self.quiet or self.start_fraction is None:
            return
        if self.shown != (self.fraction, self.message):
            self._write()
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def step(label: str, message: str, *, quiet: bool = False, stream: TextIO | None = None) -> Iterator["Progress"]:
    """A step that cannot report a fraction (one call into a library, e.g. open3d's Poisson meshing):
    a bar line ``label [...] 0.0%  message`` when it starts and one at 100 % with its time when it
    ends; nothing when it fails (the error says why) or with ``quiet``."""
    with Progress(label, stream=stream, quiet=quiet) as bar:
        bar(0.0, message)
        yield bar
        bar(1.0, message)
