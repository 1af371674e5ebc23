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

The lock file is opened without following a symbolic link (``O_NOFOLLOW``) and without becoming a
terminal's controlling file (``O_NOCTTY``); a lock name that is a link, a folder, a device or a pipe
is refused with :class:`FolderLockError`. lfrig writes its process id into the file only when it is
a regular file of its own user with a single name (never into a hard link to some other file).
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
from pathlib import Path

from recon.errors import LightFieldFormatError

LOCK_NAME = ".lfrig.lock"


class FolderLockedError(LightFieldFormatError):
    """Another lfrig process is writing the folder."""


class FolderLockError(LightFieldFormatError):
    """The folder's lock file cannot be used: it is a symbolic link or not a regular file."""


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
        lock_path = self.folder / LOCK_NAME
        #: The folders the lock created (the folder and missing parents), deepest first.
        self.created: list[Path] = []
        missing = self.folder
        while not missing.exists() and not missing.is_symlink() and missing != missing.parent:
            self.created.append(missing)
            missing = missing.parent
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            self._fd: int | None = os.open(
                lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NOCTTY | os.O_NONBLOCK, 0o644)
        except OSError as error:
            if error.errno == errno.ELOOP:
                raise FolderLockError(
                    f"{lock_path}: is a symbolic link; lfrig does not follow it (remove the link, or use another folder)"
                ) from None
            raise LightFieldFormatError(
                f"{self.folder}: cannot create the folder's lock file ({error.strerror}); check the folder"
            ) from None
        info = os.fstat(self._fd)
        if not stat.S_ISREG(info.st_mode):
            os.close(self._fd)
            self._fd = None
            raise FolderLockError(f"{lock_path}: is not a regular file; remove it, or use another folder")
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
        if info.st_uid == os.geteuid() and info.st_nlink == 1:  # our own file, no other name: say who holds it
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
