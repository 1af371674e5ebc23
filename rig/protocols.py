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

from typing import Any, Callable, Protocol, runtime_checkable

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


# --------------------------------------------------------------------------------------------------
# What a stage may offer beyond :class:`Stage` (bluesky's ``Preparable``/``Stageable`` pattern): each
# a small protocol, checked with ``isinstance`` where it is used.


@runtime_checkable
class Preparable(Protocol):
    """A stage that must be set up before moves when it was not homed (units, distance mode)."""

    def prepare(self) -> None:
        """Make the controller ready for absolute moves in mm."""


@runtime_checkable
class Configurable(Protocol):
    """A device that reports its settings, recorded in the capture's header."""

    def settings(self) -> dict[str, Any]:
        """What is worth recording about the device, as plain JSON-able values."""


@runtime_checkable
class Bounded(Protocol):
    """A stage that knows its travel."""

    def limits_mm(self) -> tuple[tuple[float, float], ...] | None:
        """Per-axis ``(min, max)`` machine coordinates in mm a move may target, or ``None`` if unknown."""


@runtime_checkable
class Toleranced(Protocol):
    """A stage with a position tolerance of its own."""

    #: Largest per-axis distance in mm between target and read-back accepted as "at the target".
    tolerance_mm: float


@runtime_checkable
class FrameAware(Protocol):
    """A stage that knows how its machine frame was established and what may have changed it."""

    #: The port's URL or device path.
    url: str
    #: A homing cycle completed through this connection.
    homed: bool
    #: Why the stage must be homed before it moves again (e.g. a reset in motion), or ``None``.
    homing_required: str | None

    def machine_frame_doubt(self) -> str | None:
        """Why the machine coordinates may not be the frame they were before this connection, or ``None``."""

    def frame_settings(self) -> dict[str, float]:
        """The controller settings that place a motor step in the machine frame, ``{"$N": value}``."""

    def still_mm(self) -> tuple[float, float, float] | None:
        """The machine position in mm where the stage stands now, or ``None`` (moving, not answering)."""


@runtime_checkable
class StepGridded(Protocol):
    """A stage whose positions are whole motor steps: it can tell which targets it cannot reach."""

    def check_step_grid(self, targets_mm, *, tolerance_mm: float | None = None) -> None:
        """Raise (a :class:`rig.errors.RigError`) for a target that lies between two motor steps, before anything moves."""


@runtime_checkable
class WireLogged(Protocol):
    """A stage that hands each line it sends or receives to a hook (for the session log)."""

    #: ``on_line(direction, text)``, direction ``">"`` (sent) or ``"<"`` (received), or ``None``.
    on_line: Callable[[str, str], None] | None
