"""A small progress bar with ETA for long work, written to stderr.

On a terminal it redraws one line; otherwise (a log file, CI) it prints a line at most every few
seconds, so logs stay short. The ETA comes from this run's own rate, so a resumed job (``done`` > 0
at the start) does not count the work an earlier run did.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def clock_text(seconds: float) -> str:
    """``MM:SS``, or ``H:MM:SS`` from an hour on."""
    seconds = int(round(seconds))
    minutes, seconds = divmod(seconds, 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes:02d}:{seconds:02d}"


class Progress:
    """``Progress("matching", total)``; call ``update(done)``; ``close()`` ends the line.

    Parameters
    ----------
    label
        What is being done, shown first.
    total
        Units of work (views, candidates, ...); ``update`` may change it.
    done
        Units already done when this run starts (resumed work).
    stream
        Where to write; default stderr.
    quiet
        Write nothing.
    """

    def __init__(self, label: str, total: int, *, done: int = 0, stream: TextIO | None = None, quiet: bool = False,
                 interval_s: float = 5.0) -> None:
        self.label = label
        self.total = max(int(total), 1)
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval_s = 0.1 if self.tty else interval_s
        self.start = time.monotonic()
        self.start_done = int(done)
        self.done = int(done)
        self.note = ""
        self.last = -1e9
        self.shown_done = -1

    def eta_s(self) -> float | None:
        """Seconds left at this run's mean rate, or ``None`` before the first unit is done."""
        taken = self.done - self.start_done
        if taken <= 0:
            return None
        return (time.monotonic() - self.start) / taken * (self.total - self.done)

    def line(self) -> str:
        fraction = self.done / self.total
        width = 24
        filled = int(width * fraction)
        eta = self.eta_s()
        eta_text = "--:--" if eta is None or self.done >= self.total else clock_text(eta)
        note = f"  {self.note}" if self.note else ""
        return (f"{self.label} [{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} "
                f"{100 * fraction:5.1f}%{note}  {clock_text(time.monotonic() - self.start)} elapsed, ETA {eta_text}")

    def update(self, done: int, total: int | None = None, *, note: str | None = None) -> None:
        """Record progress; redraws when due (and always at the end)."""
        if total is not None:
            self.total = max(int(total), 1)
        self.done = min(int(done), self.total)
        if note is not None:
            self.note = note
        now = time.monotonic()
        if self.quiet or (now - self.last < self.interval_s and self.done < self.total):
            return
        self.last = now
        self._write()

    def _write(self) -> None:
        self.shown_done = self.done
        self.stream.write(("\r" if self.tty else "") + self.line() + ("" if self.tty else "\n"))
        self.stream.flush()

    def close(self) -> None:
        """Show the final state (once) and end the line."""
        if self.quiet:
            return
        if self.shown_done != self.done:
            self._write()
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
