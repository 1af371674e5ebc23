"""The ``lfrig`` command: the top of the house.

Each package contributes its subcommands through the ``register(subparsers)`` of its ``cli`` module:
:mod:`rig.demo` (``demo``), :mod:`recon.cli` (``info``, ``reconstruct``, ``evaluate``, ``export``,
``batch``), :mod:`rig.cli` (``capture``, ``stage``) and :mod:`calib.cli` (``calibrate``, ``rectify``).
A handler receives the parsed arguments and returns an exit code (``None`` means 0). Errors a user
can cause are :class:`recon.errors.LfrigError`; they are printed as one line, without a traceback,
and the command exits with status 2. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import sys

import calib.cli
import recon.cli
import rig.cli
import rig.demo
from recon.errors import LfrigError

#: The modules whose ``register(subparsers)`` add subcommands, in the order ``--help`` lists them.
COMMAND_MODULES = (rig.demo, recon.cli, rig.cli, calib.cli)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfrig",
        description="Light-field capture on a translation stage, calibration, and disparity/depth reconstruction.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in COMMAND_MODULES:
        module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        status = args.handler(args)
    except LfrigError as error:
        print(f"lfrig: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lfrig: interrupted", file=sys.stderr)
        return 130
    return 0 if status is None else int(status)


if __name__ == "__main__":
    sys.exit(main())
