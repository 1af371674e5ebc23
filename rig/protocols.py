"""The two devices of a capture rig, as small protocols.

The capture loop (``rig.session``) is the one place that touches both. Real drivers
(``rig.grbl.GrblStage``, ``rig.camera.OpenCVCamera``, ``rig.aravis.AravisCamera``) and their simulated
twins (``rig.fakegrbl`` behind a pyserial URL, ``rig.fakecam.FakeCamera``; Aravis's own ``Fake_1``)
implement them.

Frames and units (see ``docs/conventions.md``): stage positions are machine coordinates in mm as
GRBL reports them (``MPos``), ordered ``(x, y, z)``; images are ``(H, W)`` or ``(H, W, 3)`` arrays,
row 0 at the top, colour in RGB order, dtype ``uint8`` or ``uint16``.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Stage(Protocol):
    """A three-axis translation stage."""

    def home(self) -> None:
        """Run the homing cycle; positions are meaningful only afterwards."""

    def move_to(self, position_mm: tuple[float, float, float], *, feed_mm_min: float | None = None) -> None:
        """Start an absolute move to ``position_mm`` (x, y, z in mm). Returns before the motion ends."""

    def wait_until_idle(self, *, timeout_s: float | None = None) -> tuple[float, float, float]:
        """Block until the motion is done; return the read-back position in mm."""

    def position(self) -> tuple[float, float, float]:
        """The current read-back machine position in mm."""

    def status(self) -> dict[str, Any]:
        """The controller's state, e.g. ``{"state": "Idle", "mpos_mm": (x, y, z), ...}``."""

    def stop(self) -> None:
        """Stop motion at once (feed hold, then reset)."""

    def close(self) -> None:
        """Release the port."""


@runtime_checkable
class Camera(Protocol):
    """A camera that takes one fresh frame per trigger."""

    def trigger(self) -> np.ndarray:
        """Expose and return a new frame taken after this call began (never a buffered one)."""

    def settings(self) -> dict[str, Any]:
        """Exposure, gain, size and anything else worth recording, as read back from the device."""

    def close(self) -> None:
        """Release the device."""
