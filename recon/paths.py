"""Output paths checked before the work: a long solve or estimate must not fail at its last write.

:func:`writable_folder` and :func:`writable_file` make sure the folder exists (creating it) and that a
file can be created in it, by creating and removing a small probe file, which is what a read-only
mount, a full disk or missing permissions would refuse. Errors name the path and what to do.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from recon.errors import OutputPathError

_HINTS = {
    errno.EROFS: "the filesystem is read-only; choose another folder",
    errno.EACCES: "no permission to write there; choose another folder or fix its permissions",
    errno.EPERM: "no permission to write there; choose another folder or fix its permissions",
    errno.ENOSPC: "the disk is full; free some space or choose another folder",
    errno.EDQUOT: "the disk quota is used up; free some space or choose another folder",
}


def _describe(error: OSError) -> str:
    return f"{error.strerror or error}; {_HINTS.get(error.errno, 'choose another path')}"


def writable_folder(path: str | os.PathLike, *, what: str = "output folder") -> Path:
    """Create ``path`` if needed and check that files can be written in it; returns it as a Path.

    Raises
    ------
    OutputPathError
        ``path`` is a file, cannot be created, or refuses a new file (read-only, full, no permission).
    """
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise OutputPathError(f"{folder}: is a file, not a folder; give a folder for the {what}")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputPathError(f"{folder}: a part of this path is a file; give a folder for the {what}") from None
    except OSError as error:
        raise OutputPathError(f"{folder}: cannot create the {what} ({_describe(error)})") from None
    probe = folder / f".lfrig-write-probe.{os.getpid()}"
    try:
        with open(probe, "wb") as f:
            f.write(b"lfrig")
            f.flush()
            os.fsync(f.fileno())
    except OSError as error:
        raise OutputPathError(f"{folder}: cannot write the {what} here ({_describe(error)})") from None
    finally:
        try:
            probe.unlink()
        except OSError:
            pass
    return folder


def writable_file(path: str | os.PathLike, *, what: str = "output file") -> Path:
    """Check that the file ``path`` can be written: not a folder, its folder writable (created if
    missing). Returns it as a Path.

    Raises
    ------
    OutputPathError
        As :func:`writable_folder`, or when ``path`` is an existing folder.
    """
    file = Path(path)
    if file.is_dir():
        raise OutputPathError(f"{file}: is a folder; give a file name for the {what}")
    writable_folder(file.parent if str(file.parent) else Path("."), what=f"folder of the {what}")
    return file
