"""An advisory lock on a folder that lfrig writes: one writer at a time.

The lock is ``fcntl.flock`` on a file ``.lfrig.lock`` in the folder, held for as long as the writer
runs. The kernel drops it when the process ends in any way (also ``kill -9`` or a power cut), so a
lock never outlives its holder and there is nothing to clean up: the lock file itself stays and
means nothing on its own. A second writer does not wait; it fails at once with
:class:`FolderLockedError` naming the folder.

It protects against a second lfrig process (another ``lfrig capture``, ``rectify`` into the same
output, ``reconstruct`` into the same result folder); it is advisory, so it does not stop other
programs, and ``flock`` is not reliable on every network filesystem (NFS before Linux 2.6.12, some
SMB mounts).
"""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path

from recon.errors import LightFieldFormatError

LOCK_NAME = ".lfrig.lock"


class FolderLockedError(LightFieldFormatError):
    """Another lfrig process is writing the folder."""


class FolderLock:
    """Hold the lock on ``folder`` (created if missing) until :meth:`release` or the ``with`` ends.

    Parameters
    ----------
    folder
        The folder to lock.
    what
        What the holder does, for the message a second writer gets (``"capture"``, ``"reconstruction"``).

    Raises
    ------
    FolderLockedError
        When another process holds the lock.
    """

    def __init__(self, folder: str | os.PathLike, *, what: str = "lfrig command") -> None:
        self.folder = Path(folder)
        self.what = what
        #: The folders the lock created (the folder and missing parents), deepest first.
        self.created: list[Path] = []
        missing = self.folder
        while not missing.exists() and not missing.is_symlink() and missing != missing.parent:
            self.created.append(missing)
            missing = missing.parent
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            self._fd: int | None = os.open(self.folder / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as error:
            raise LightFieldFormatError(
                f"{self.folder}: cannot create the folder's lock file ({error.strerror}); check the folder"
            ) from None
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            os.close(self._fd)
            self._fd = None
            if error.errno in (errno.EWOULDBLOCK, errno.EACCES):
                raise FolderLockedError(
                    f"{self.folder}: another {what} is running in this folder (it holds {LOCK_NAME}); "
                    "wait for it to finish or stop it, or use another folder"
                ) from None
            raise LightFieldFormatError(f"{self.folder}: cannot lock the folder ({error.strerror})") from None
        os.ftruncate(self._fd, 0)
        os.write(self._fd, f"{os.getpid()} {what}\n".encode())

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self, *, discard: bool = False) -> None:
        """Drop the lock. With ``discard`` (a command that wrote nothing), also remove the lock file
        and the folders the lock created, those that are empty."""
        if self._fd is not None:
            if discard:
                try:
                    os.unlink(self.folder / LOCK_NAME)  # while held: no other writer is inside
                except OSError:
                    pass
            os.close(self._fd)  # closing the last descriptor drops the flock
            self._fd = None
            if discard:
                for folder in self.created:
                    try:
                        folder.rmdir()  # only when empty
                    except OSError:
                        break

    def __enter__(self) -> "FolderLock":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
