"""The ``lfrig`` command: the top of the house.

Each package contributes its subcommands through the ``register(subparsers)`` of its ``cli`` module:
:mod:`rig.demo` (``demo``), :mod:`recon.cli` (``info``, ``reconstruct``, ``evaluate``, ``export``,
``batch``), :mod:`rig.cli` (``capture``, ``stage``, ``camera``) and :mod:`calib.cli` (``calibrate``, ``rectify``).
A handler receives the parsed arguments and returns an exit code (``None`` means 0). Errors a user
can cause are :class:`recon.errors.LfrigError`; they are printed as one line, without a traceback,
and the command exits with status 2. So are usage errors (a flag's value is checked by the types of
:mod:`recon.cliargs`) and an ``OSError`` that a user's path or disk causes (read-only, full, no
permission: :data:`USER_PATH_ERRNOS`, when the error names a path). Anything else is a bug and keeps
its traceback. Ctrl-C is ``lfrig: interrupted`` and status 130 at any moment of :func:`main`, also
while the command modules load (they bring numba and scipy); ``SIGTERM`` and ``SIGHUP`` stop a command
the same way (:class:`Stopped`), so that its writers remove their temporary files, with status 128 +
the signal.

A process that ran :func:`main` ends without the interpreter's last garbage collections
(:func:`_skip_final_collections`): after a reconstruction they walk numba's and LLVM's objects for
0.3-0.4 s of CPU, to free memory that the end of the process frees anyway.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import errno
import gc
import signal
import sys
from typing import Iterator

from recon.cliargs import OneLineParser, print_error
from recon.errors import LfrigError

#: ``OSError``s that a user's paths or disks cause (a read-only or full output folder, a file where a
#: folder should be, no permission...): printed as one line naming the path, exit status 2. Any other
#: ``OSError``, or one without a path, is a bug and keeps its traceback.
USER_PATH_ERRNOS = {
    errno.EACCES: "choose a folder you may write to, or fix its permissions",
    errno.EPERM: "choose a folder you may write to, or fix its permissions",
    errno.EROFS: "the filesystem is read-only; choose another folder",
    errno.ENOSPC: "the disk is full; free some space or choose another folder, then run the same command again",
    errno.EDQUOT: "the disk quota is used up; free some space or choose another folder",
    errno.EFBIG: "the file is too large for this filesystem; choose another folder",
    errno.EEXIST: "choose another path",
    errno.ENOTDIR: "a part of the path is a file, not a folder; choose another path",
    errno.EISDIR: "it is a folder; give a file name",
    errno.ENOENT: "check the path",
    errno.ENAMETOOLONG: "choose a shorter path",
    errno.ELOOP: "the path loops through symbolic links",
}


def user_path_error(error: OSError) -> str | None:
    """The one line for an ``OSError`` caused by a user's path or disk, or ``None`` for anything else."""
    hint = USER_PATH_ERRNOS.get(error.errno)
    if hint is None or error.filename is None:
        return None
    path = error.filename if error.filename2 is None else f"{error.filename} -> {error.filename2}"
    return f"{path}: {error.strerror or 'OS error'}; {hint}"


class _Version(argparse.Action):
    """``--version``: the version is looked up only when asked for (it may ask git)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from recon.provenance import lfrig_version

        print(f"lfrig {lfrig_version()}")
        parser.exit()


#: The modules whose ``register(subparsers)`` add subcommands, in the order ``--help`` lists them,
#: each with the commands it adds. Imported by :func:`build_parser` (inside :func:`main`'s handling
#: of Ctrl-C: they load numba and scipy).
COMMAND_MODULES = {
    "rig.demo": ("demo",),
    "recon.cli": ("info", "reconstruct", "evaluate", "export", "batch", "import"),
    "rig.cli": ("capture", "stage", "camera"),
    "calib.cli": ("calibrate", "rectify"),
}


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``lfrig`` parser. For a command line ``argv`` that starts with a command, only the module
    that adds it registers its subcommands: a command does not pay for the others' imports and
    flags (~40 ms of the 0.13-0.17 s that building the whole parser takes). Without one (``lfrig``,
    ``lfrig --help``, a misspelt command) every module does, so that help and errors list them all."""
    import importlib

    command = argv[0] if argv else None
    modules = [name for name, commands in COMMAND_MODULES.items() if command in commands] or list(COMMAND_MODULES)
    parser = OneLineParser(
        prog="lfrig",
        description="Light-field capture on a translation stage, calibration, and disparity/depth reconstruction.",
    )
    parser.add_argument("--version", action=_Version, help="print lfrig's version (with the git commit of a checkout) and exit")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in modules:
        importlib.import_module(name).register(subparsers)
    return parser


class Stopped(KeyboardInterrupt):
    """``SIGTERM`` or ``SIGHUP`` arrived: raised like Ctrl-C, so that a command stops the way it stops
    for Ctrl-C (a capture parks the stage, every writer removes its temporary files) and exits
    with ``128 + signal``."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """Turn ``SIGTERM`` and ``SIGHUP`` into :class:`Stopped` while the block runs (main thread only;
    elsewhere, and for signals a caller chose to ignore, nothing changes)."""
    def stop(signum: int, frame: object) -> None:
        raise Stopped(signum)

    saved = {}
    try:
        for signum in (signal.SIGTERM, signal.SIGHUP):
            if signal.getsignal(signum) is not signal.SIG_IGN:  # e.g. nohup's SIGHUP stays ignored
                saved[signum] = signal.signal(signum, stop)
    except ValueError:  # not the main thread
        pass
    try:
        yield
    finally:
        for signum, handler in saved.items():
            signal.signal(signum, handler)


def _skip_final_collections() -> None:
    # Run at exit (after the atexit functions registered later): the objects alive now are left out
    # of the collections of the interpreter's shutdown. Files are closed by then (every writer of
    # lfrig closes its own; sys.stdout and sys.stderr are flushed by the shutdown itself).
    gc.freeze()


def main(argv: list[str] | None = None) -> int:
    atexit.unregister(_skip_final_collections)  # once per process, however often main runs
    atexit.register(_skip_final_collections)
    try:
        with stop_signals():
            return _main(argv)
    except KeyboardInterrupt as stop:  # Ctrl-C or a stop signal, even while the modules load
        print("lfrig: interrupted" if not isinstance(stop, Stopped) else
              f"lfrig: stopped by {signal.Signals(stop.signum).name}", file=sys.stderr)
        return 128 + (stop.signum if isinstance(stop, Stopped) else signal.SIGINT)


def _main(argv: list[str] | None) -> int:
    from recon.provenance import set_command

    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    set_command(["lfrig", *argv])
    parser = build_parser(argv)
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help (0) or a usage error, already printed as one line (2)
        return done.code if isinstance(done.code, int) else 2
    try:
        status = args.handler(args)
    except LfrigError as error:
        print_error(str(error))
        return 2
    except OSError as error:
        line = user_path_error(error)
        if line is None:
            raise
        print_error(line)
        return 2
    return 0 if status is None else int(status)


if __name__ == "__main__":
    sys.exit(main())
