"""The rig package's exceptions."""

from __future__ import annotations

from recon.errors import LfrigError


class RigError(LfrigError):
    """An error of the stage, the camera or a capture session."""
