"""The calib package's exceptions."""

from __future__ import annotations

from recon.errors import LfrigError


class CalibError(LfrigError):
    """An error in calibration or rectification."""
