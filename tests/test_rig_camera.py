"""OpenCVCamera against a simulated VideoCapture: fresh frames, settings read back, hardware trigger."""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np
import pytest

from rig.camera import CameraError, OpenCVCamera, parse_source
from rig.clock import VirtualClock
from rig.fakegrbl import FakeGrbl
from rig.urlhandler.protocol_fakegrbl import register, unregister
from rig.grbl import GrblStage
from rig.protocols import Camera


class FakeCapture:
    """Behaves like a V4L2 VideoCapture: keeps up to ``queue`` buffered frames, each stamped with the
    scene's state when it was exposed; some properties are clamped by the 'driver'."""

    def __init__(self, *, queue: int = 4, ignore_buffersize: bool = False, exposure_step: float = 1.0) -> None:
        self.scene = 0  # what the camera sees right now (e.g. a view number)
        self.buffer: deque = deque()
        self.queue = queue
        self.ignore_buffersize = ignore_buffersize
        self.exposure_step = exposure_step
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 640.0, cv2.CAP_PROP_FRAME_HEIGHT: 480.0,
                      cv2.CAP_PROP_EXPOSURE: 100.0, cv2.CAP_PROP_GAIN: 0.0, cv2.CAP_PROP_FPS: 30.0,
                      cv2.CAP_PROP_AUTO_EXPOSURE: 3.0, cv2.CAP_PROP_BUFFERSIZE: 4.0}
        self.grabbed = None
        self.released = False
        self.triggered_only = False

    def expose(self) -> None:
        """The camera exposes a frame of the current scene into its buffer (dropping the oldest)."""
        self.buffer.append(self.scene)
        while len(self.buffer) > self.queue:
            self.buffer.popleft()

    def isOpened(self) -> bool:
        return True

    def set(self, prop, value) -> bool:
        if prop == cv2.CAP_PROP_BUFFERSIZE:
            if not self.ignore_buffersize:
                self.queue = int(value)
        if prop == cv2.CAP_PROP_EXPOSURE:
            value = round(value / self.exposure_step) * self.exposure_step
        self.props[prop] = float(value)
        return True

    def get(self, prop) -> float:
        return self.props.get(prop, 0.0)

    def grab(self) -> bool:
        if not self.buffer:
            if self.triggered_only:
                return False
            self.expose()
        self.grabbed = self.buffer.popleft()
        return True

    def retrieve(self):
        h, w = int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]), int(self.props[cv2.CAP_PROP_FRAME_WIDTH])
        frame = np.zeros((h, w, 3), np.uint8)
        frame[..., 0] = 200  # blue in OpenCV's BGR order
        frame[0, 0, 1] = self.grabbed
        return True, frame

    def getBackendName(self) -> str:
        return "FAKE"

    def release(self) -> None:
        self.released = True


def test_trigger_returns_a_frame_exposed_after_the_call():
    cap = FakeCapture(queue=4, ignore_buffersize=True)  # a backend that keeps 4 stale frames
    camera = OpenCVCamera(0, capture=cap)
    assert isinstance(camera, Camera)
    for view in range(1, 6):
        for _ in range(4):  # frames exposed while the stage was still moving to this view
            cap.expose()
        cap.scene = view
        frame = camera.trigger()
        assert frame[0, 0, 1] == view
    camera.close()
    assert cap.released


def test_too_few_dropped_frames_would_return_a_stale_one():
    cap = FakeCapture(queue=4, ignore_buffersize=True)
    camera = OpenCVCamera(0, capture=cap, drop_frames=1)
    for _ in range(4):
        cap.expose()
    cap.scene = 7
    assert camera.trigger()[0, 0, 1] == 0  # what the test above guards against


def test_frames_are_rgb():
    camera = OpenCVCamera(0, capture=FakeCapture(), width=32, height=24)
    frame = camera.trigger()
    assert frame.shape == (24, 32, 3) and frame.dtype == np.uint8
    assert frame[5, 5, 2] == 200 and frame[5, 5, 0] == 0


def test_settings_are_set_and_read_back():
    cap = FakeCapture(exposure_step=10.0)
    camera = OpenCVCamera(0, capture=cap, width=320, height=240, exposure=123.0, gain=2.0)
    settings = camera.settings()
    assert settings["requested"] == {"width": 320, "height": 240, "exposure": 123.0, "gain": 2.0}
    assert settings["readback"]["exposure"] == 120.0  # what the device really uses is recorded
    assert settings["readback"]["gain"] == 2.0 and settings["readback"]["auto_exposure"] == 1.0
    assert settings["readback"]["buffer_size"] == 1.0 and settings["backend"] == "FAKE"


def test_hardware_trigger_pulses_the_stage_output():
    clock = VirtualClock()
    controller = FakeGrbl(clock=clock)
    url = register(controller)
    cap = FakeCapture()
    cap.triggered_only = True
    try:
        with GrblStage(url, clock=clock) as stage:
            stage.home()

            def line(on: bool) -> None:
                stage.set_output(on)
                if on:
                    cap.expose()  # the trigger input makes the camera expose one frame

            camera = OpenCVCamera(0, capture=cap, hardware_trigger=line, clock=clock)
            assert camera.drop_frames == 0
            cap.scene = 3
            assert camera.trigger()[0, 0, 1] == 3
            assert [on for _, on, _ in controller.output_events] == [True, False]
            assert b"M8\nM9\n" in bytes(controller.rx_log)
    finally:
        unregister(url)


def test_errors_name_the_camera():
    class Closed(FakeCapture):
        def isOpened(self) -> bool:
            return False

    with pytest.raises(CameraError, match="cannot open camera 3"):
        OpenCVCamera(3, capture=Closed())
    cap = FakeCapture()
    cap.triggered_only = True
    camera = OpenCVCamera("/dev/video9", capture=cap, drop_frames=0)
    with pytest.raises(CameraError, match="'/dev/video9' delivered no frame"):
        camera.trigger()
    assert parse_source("0") == 0 and parse_source("/dev/video2") == "/dev/video2"
