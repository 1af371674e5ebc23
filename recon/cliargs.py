"""Argument types shared by every ``cli`` module (``recon.cli``, ``calib.cli``, ``rig.cli``, ``rig.demo``).

A flag's value is checked where it is parsed, so that a user's mistake is one line from argparse
(``lfrig: error: argument --feed-mm-min: 0 is not a positive number ... (see lfrig capture --help)``) and exit status 2,
before anything is read, moved or written. The library checks the same values again at its public
entry (scikit-image style); these types only make the command line say it earlier and in the flag's
own words.

Every type is a plain function ``str -> value`` raising :class:`argparse.ArgumentTypeError`, usable
as ``type=`` of ``add_argument``. The bounded ones are made by :func:`int_range` and
:func:`float_range`.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Callable, NoReturn


class OneLineParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors are one line (no usage block), exit status 2.

    ``lfrig`` uses it for the top parser; ``add_subparsers`` makes every subcommand's parser of the
    same class, so every command's usage errors are one line too.
    """

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"lfrig: error: {message} (see {self.prog} --help)\n")


def _number(text: str, kind: type) -> float | int:
    try:
        return kind(text)
    except (TypeError, ValueError):
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None


def finite_float(text: str) -> float:
    """A finite float (no ``nan``, ``inf``)."""
    value = float(_number(text, float))
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def positive_float(text: str) -> float:
    """A finite float > 0."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text} is not a positive number; give a value > 0")
    return value


def nonnegative_float(text: str) -> float:
    """A finite float >= 0."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is negative; give a value >= 0")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    value = int(_number(text, int))
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not a positive integer; give a value >= 1")
    return value


def nonnegative_int(text: str) -> int:
    """An integer >= 0."""
    value = int(_number(text, int))
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is negative; give a value >= 0")
    return value


def int_range(low: int, high: int) -> Callable[[str], int]:
    """An integer in ``[low, high]``."""

    def parse(text: str) -> int:
        value = int(_number(text, int))
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{text} is outside {low}..{high}")
        return value

    parse.__name__ = f"int_in_{low}_{high}"
    return parse


def float_range(low: float, high: float, *, low_open: bool = False) -> Callable[[str], float]:
    """A finite float in ``[low, high]`` (``(low, high]`` with ``low_open``)."""

    def parse(text: str) -> float:
        value = finite_float(text)
        if not ((low < value) if low_open else (low <= value)) or not value <= high:
            bracket = "(" if low_open else "["
            raise argparse.ArgumentTypeError(f"{text} is outside {bracket}{low:g}, {high:g}]")
        return value

    parse.__name__ = f"float_in_{low}_{high}"
    return parse


#: Hosts that mean "every interface of this machine": a dashboard there is open to the whole network.
ALL_INTERFACES = ("0.0.0.0", "::")


def host_port(text: str) -> str:
    """``HOST:PORT`` (``[IPv6]:PORT`` for an IPv6 address) with a port from 0 to 65535 (0: any free
    port). An empty host (``:8787``), which servers read as every interface, is refused: name
    ``0.0.0.0`` or ``[::]`` to mean that."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT with a port from 0 to 65535, e.g. 127.0.0.1:8787")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
        if ":" not in host:
            raise argparse.ArgumentTypeError(f"{text!r}: brackets are for IPv6 addresses, e.g. [::1]:8787")
    elif ":" in host:
        raise argparse.ArgumentTypeError(f"{text!r}: write an IPv6 address in brackets, e.g. [::1]:8787")
    if not host:
        raise argparse.ArgumentTypeError(
            f"{text!r} has no host, which would listen on every interface; say 127.0.0.1:{port} for this machine "
            f"only, or 0.0.0.0:{port} to mean every interface")
    if any(c.isspace() or c in "/@?#" for c in host):
        raise argparse.ArgumentTypeError(f"{text!r}: {host!r} is not a host name or address")
    return text


def output_file(text: str) -> Path:
    """A path for a file to write: not an existing folder (its folder is checked when writing)."""
    if not text:
        raise argparse.ArgumentTypeError("empty path")
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder; give a file name")
    return path


def output_folder(text: str) -> Path:
    """A path for a folder to write into: a folder or nothing yet, not an existing file."""
    if not text:
        raise argparse.ArgumentTypeError("empty path")
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file; give a folder (new or existing)")
    return path


def print_error(message: str) -> None:
    """Print a user's error as lfrig's one line on stderr."""
    print(f"lfrig: error: {message}", file=sys.stderr)


def add_json_argument(parser: argparse.ArgumentParser) -> None:
    """``--json``: the command's report as one JSON object on stdout (progress and warnings stay on stderr)."""
    parser.add_argument("--json", action="store_true",
                        help="print what the command reports as one JSON object on stdout (progress stays on stderr)")


class CommandReport:
    """What a command reports on stdout: readable lines, or with ``--json`` one JSON object printed by
    :meth:`finish` (the fields given with each line, merged)."""

    def __init__(self, *, as_json: bool) -> None:
        self.as_json = as_json
        self.fields: dict = {}

    def line(self, text: str, **fields) -> None:
        """Print ``text`` (readable mode) or keep ``fields`` for the JSON object."""
        if self.as_json:
            self.fields.update(fields)
        else:
            print(text, flush=True)

    def finish(self) -> None:
        """Print the JSON object (JSON mode); paths and other objects become strings."""
        if self.as_json:
            import json

            print(json.dumps(self.fields, indent=2, default=str))
