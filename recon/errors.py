"""The root of lfrig's exception tree.

Every error that a user can cause (a bad path, a broken file, a value out of range) is raised as a
subclass of :class:`LfrigError` with a message that names the file or value and says what to do.
The command line prints such errors as one line and exits non-zero; anything else is a bug and
keeps its traceback.

Each package has its own branch: :class:`ReconError` here, ``rig.errors.RigError`` and
``calib.errors.CalibError`` in theirs.
"""

from __future__ import annotations


class LfrigError(Exception):
    """A user-facing error: the message is complete and is shown without a traceback."""


class ReconError(LfrigError):
    """An error in reading, reconstructing or exporting a light field."""


class LightFieldFormatError(ReconError):
    """A light-field folder or file is missing, incomplete or unreadable."""


class CaptureLayoutError(LightFieldFormatError):
    """A capture folder does not match lfrig's capture layout, or conflicts with the settings."""


class ExportError(ReconError):
    """A reconstruction folder cannot be read or exported, or a PLY or depth file cannot be written."""


class OutputPathError(ReconError):
    """An output path cannot be written: a file where a folder is wanted (or the reverse), a
    read-only or full filesystem, no permission. Checked before the work starts."""


class FileWriteError(ReconError):
    """A file could not be written (full disk, no permission, a folder that went away...).

    The message names the file and the system's reason; the file's previous content (if any) is
    left as it was, because every file is written to a temporary name first and renamed into place.
    """
