"""The ``lfrig`` command: parse, call the library, write files.

Each package contributes its subcommands through a ``register(subparsers)`` function in its CLI
module, listed in :data:`COMMAND_MODULES`. A handler receives the parsed arguments and returns an
exit code (``None`` means 0). Errors a user can cause are :class:`recon.errors.LfrigError`; they are
printed as one line, without a traceback, and the command exits with status 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from recon.errors import LfrigError

#: Modules whose ``register(subparsers)`` adds subcommands, in the order ``--help`` lists them.
COMMAND_MODULES = [
    "recon.demo",
    "recon.commands",
    "recon.export_cli",
    "rig.cli",
    "recon.scale_cli",
    "calib.cli",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfrig",
        description="Light-field capture on a translation stage, calibration, and disparity/depth reconstruction.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
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
