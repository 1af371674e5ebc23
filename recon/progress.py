"""A small progress bar with ETA for long work, written to stderr.

On a terminal it redraws one line; otherwise (a log file, CI) it prints a line at most every few
seconds, so logs stay short.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    minutes, seconds = divmod(seconds, 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes:02d}:{seconds:02d}"


class Progress:
    """``Progress("matching", total)``; call ``update(done)``; ``close()`` prints the final line."""

    def __init__(self, label: str, total: int, *, stream: TextIO | None = None, quiet: bool = False,
                 interval_s: float = 5.0) -> None:
        self.label = label
        self.total = max(int(total), 1)
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.tty = getattr(self.stream, "isatty", lambda: False)()
        self.interval_s = 0.1 if self.tty else interval_s
        self.start = time.monotonic()
        self.last = -1e9
        self.done = 0

    def line(self) -> str:
        elapsed = time.monotonic() - self.start
        fraction = self.done / self.total
        width = 24
        filled = int(round(width * fraction))
        bar = "#" * filled + "-" * (width - filled)
        eta = _clock(elapsed / fraction - elapsed) if 0 < fraction < 1 else "--:--"
        return f"{self.label} [{bar}] {self.done}/{self.total} {100 * fraction:3.0f}% {_clock(elapsed)} elapsed, ETA {eta}"

    def update(self, done: int, total: int | None = None) -> None:
        if total is not None:
            self.total = max(int(total), 1)
        self.done = min(int(done), self.total)
        now = time.monotonic()
        if self.quiet or (now - self.last < self.interval_s and self.done < self.total):
            return
        self.last = now
        if self.tty:
            self.stream.write("\r" + self.line())
        else:
            self.stream.write(self.line() + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.quiet:
            return
        if self.tty:
            self.stream.write("\r" + self.line() + "\n")
            self.stream.flush()
        elif self.last < 0 or self.done < self.total:
            self.stream.write(self.line() + "\n")
            self.stream.flush()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
