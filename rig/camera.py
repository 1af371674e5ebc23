"""A real camera through OpenCV's ``VideoCapture`` (implements :class:`rig.protocols.Camera`).

Fresh frames: capture backends queue frames (V4L2 keeps several buffers), so the frame ``read()``
returns may have been exposed before the stage stopped. :meth:`OpenCVCamera.trigger` asks for a
one-frame buffer and then grabs and drops ``drop_frames`` frames before grabbing the one it returns,
so the returned frame was exposed after the call began (raise ``drop_frames`` if a backend ignores
the buffer size).

Hardware trigger: with ``hardware_trigger=`` a callable switching an output (e.g.
:meth:`rig.grbl.GrblStage.set_output`, GRBL's ``M8``/``M9`` coolant pin wired to the camera's trigger
input, with the camera in external-trigger mode), each trigger pulses the output and grabs the frame
that pulse exposed; no frames are dropped by default in that mode (a triggered camera sends none
unasked).

Exposure and gain are set when given and always read back; both values are recorded in
:meth:`settings`. Their units are the backend's (V4L2: exposure in 100 us steps, manual exposure
needs ``CAP_PROP_AUTO_EXPOSURE = 1``).

Frames are returned as ``(H, W, 3)`` RGB (OpenCV delivers BGR) or ``(H, W)`` grey, ``uint8`` or
``uint16`` as the camera delivers them.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import numpy as np

from rig.errors import RigError
from rig.clock import Clock, SystemClock

log = logging.getLogger(__name__)


class CameraError(RigError):
    """The camera could not be opened, configured or read."""


@contextmanager
def quiet_opencv() -> Iterator[None]:
    """OpenCV's own warnings off while opening a capture (a device it cannot open is reported by
    lfrig as one line, not as OpenCV's log lines on stderr); errors still show."""
    import cv2

    logging_ = cv2.utils.logging
    previous = logging_.getLogLevel()
    logging_.setLogLevel(logging_.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        logging_.setLogLevel(previous)


def parse_source(text: str) -> int | str:
    """``"0"`` -> device index 0; anything else (``/dev/video2``, ``rtsp://...``, a file) as is."""
    text = text.strip()
    return int(text) if text.isdigit() else text


class OpenCVCamera:
    """A camera read through ``cv2.VideoCapture``.

    Parameters
    ----------
    source
        Device index or path/URL passed to ``cv2.VideoCapture``.
    width, height
        Requested frame size in pixels (read back; the camera may pick another).
    exposure, gain
        Requested values in the backend's units; ``None`` leaves the camera's setting.
    drop_frames
        Frames grabbed and discarded before the returned one (default 4, or 0 with a hardware trigger).
    hardware_trigger
        ``callable(on: bool)`` switching the camera's trigger line; see the module docstring.
    trigger_pulse_s
        How long the trigger line stays on.
    capture
        An already opened ``VideoCapture``-like object (tests inject a fake here).
    """

    def __init__(
        self,
        source: int | str = 0,
        *,
        width: int | None = None,
        height: int | None = None,
        exposure: float | None = None,
        gain: float | None = None,
        drop_frames: int | None = None,
        hardware_trigger: Callable[[bool], None] | None = None,
        trigger_pulse_s: float = 0.01,
        clock: Clock | None = None,
        capture: Any = None,
    ) -> None:
        import cv2

        self._cv2 = cv2
        self.source = source
        self.hardware_trigger = hardware_trigger
        self.trigger_pulse_s = trigger_pulse_s
        self.drop_frames = (0 if hardware_trigger is not None else 4) if drop_frames is None else int(drop_frames)
        if self.drop_frames < 0:
            raise ValueError(f"drop_frames must be >= 0; got {drop_frames}")
        self.clock = clock if clock is not None else SystemClock()
        self.requested = {"width": width, "height": height, "exposure": exposure, "gain": gain}
        if capture is None:
            with quiet_opencv():
                capture = cv2.VideoCapture(source)
        self._cap = capture
        if not self._cap.isOpened():
            raise CameraError(
                f"cannot open camera {source!r} with OpenCV; check the index or path (ls /dev/video*) "
                "and that no other program uses it"
            )
        self._frames = 0
        self._configure()

    def _configure(self) -> None:
        cv2 = self._cv2
        cap = self._cap
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        if self.requested["width"] is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, float(self.requested["width"]))
        if self.requested["height"] is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, float(self.requested["height"]))
        if self.requested["exposure"] is not None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1.0)  # V4L2: 1 = manual
            cap.set(cv2.CAP_PROP_EXPOSURE, float(self.requested["exposure"]))
        if self.requested["gain"] is not None:
            cap.set(cv2.CAP_PROP_GAIN, float(self.requested["gain"]))
        readback = self._readback()
        for key in ("exposure", "gain"):
            want = self.requested[key]
            if want is not None and abs(readback[key] - want) > 1e-6 * max(1.0, abs(want)):
                log.warning("camera %r: %s requested %s, reads back %s", self.source, key, want, readback[key])

    def _readback(self) -> dict[str, float]:
        cv2 = self._cv2
        cap = self._cap
        return {
            "width": cap.get(cv2.CAP_PROP_FRAME_WIDTH),
            "height": cap.get(cv2.CAP_PROP_FRAME_HEIGHT),
            "exposure": cap.get(cv2.CAP_PROP_EXPOSURE),
            "gain": cap.get(cv2.CAP_PROP_GAIN),
            "auto_exposure": cap.get(cv2.CAP_PROP_AUTO_EXPOSURE),
            "fps": cap.get(cv2.CAP_PROP_FPS),
            "buffer_size": cap.get(cv2.CAP_PROP_BUFFERSIZE),
        }

    def trigger(self) -> np.ndarray:
        """A frame exposed after this call began, as RGB or grey."""
        for _ in range(self.drop_frames):
            if not self._cap.grab():
                raise CameraError(f"camera {self.source!r} stopped delivering frames (grab failed); check the cable")
        if self.hardware_trigger is not None:
            self.hardware_trigger(True)
            self.clock.sleep(self.trigger_pulse_s)
            self.hardware_trigger(False)
        if not self._cap.grab():
            raise CameraError(
                f"camera {self.source!r} delivered no frame"
                + (" after the hardware trigger; is it in external-trigger mode and wired to M8?" if self.hardware_trigger else "")
            )
        ok, frame = self._cap.retrieve()
        if not ok or frame is None:
            raise CameraError(f"camera {self.source!r}: could not decode the grabbed frame")
        self._frames += 1
        if frame.ndim == 3 and frame.shape[2] == 3:
            frame = frame[:, :, ::-1]
        elif frame.ndim == 3 and frame.shape[2] == 1:
            frame = frame[:, :, 0]
        elif frame.ndim == 3 and frame.shape[2] == 4:
            frame = frame[:, :, 2::-1]
        return np.ascontiguousarray(frame)

    def settings(self) -> dict[str, Any]:
        """Requested and read-back settings (recorded with every frame)."""
        backend = None
        if hasattr(self._cap, "getBackendName"):
            try:
                backend = self._cap.getBackendName()
            except Exception:  # not all backends can name themselves
                backend = None
        return {
            "driver": "opencv",
            "source": self.source,
            "backend": backend,
            "requested": dict(self.requested),
            "readback": self._readback(),
            "drop_frames": self.drop_frames,
            "hardware_trigger": self.hardware_trigger is not None,
            "frames": self._frames,
        }

    def close(self) -> None:
        self._cap.release()

    def __enter__(self) -> "OpenCVCamera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
