"""Opening the stage and camera named on the command line (``--stage SPEC``, ``--camera SPEC``).

Stage specs:

- ``fake`` (default): a simulated GRBL controller (:mod:`rig.fakegrbl`) on a virtual clock, driven by
  the real GRBL driver through ``fakegrbl://`` (:mod:`rig.urlhandler.protocol_fakegrbl`);
  ``fake?clock=real`` moves in real time; ``fake?fault=stall&after=10`` arms a fault (``lost_ok``,
  ``garbled``, ``alarm_mid_move``, ``stall``, ``disconnect``).
- ``grbl:///dev/ttyUSB0``, ``/dev/ttyACM0`` or any pyserial URL (``socket://host:23``,
  ``rfc2217://host:port``): a GRBL controller.

Camera specs:

- ``fake`` (default): the simulated camera (:mod:`rig.fakecam`) seeing its default scene from the
  stage's position;
- ``opencv:0`` (device index or path): a camera through OpenCV (:mod:`rig.camera`);
- ``aravis:`` (the first camera found) or ``aravis:DEVICE_ID``: a GenICam (GigE Vision / USB3 Vision)
  camera through Aravis (:mod:`rig.aravis`); ``aravis:Fake_1`` is Aravis's simulated camera.

A new stage driver or camera is opened here: add its spec to :func:`open_stage` or
:func:`open_camera` (see ``docs/architecture.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rig.clock import SystemClock, VirtualClock
from rig.errors import RigError

#: Grid centre used with the fake stage when none is given: well inside its 100 x 100 x 50 mm travel.
FAKE_CENTRE_MM = (-50.0, -50.0, -10.0)
#: The fake camera's binning when a command gives none (``lfrig capture``, ``lfrig demo``): the
#: paper's 640x490 from the 1280x980 detector (``rig.fakecam.FakeCamera`` itself bins nothing unless told).
FAKE_BINNING = 2


class Devices:
    """What the CLI opened: the stage, the fake controller behind it (if any) and the shared clock."""

    def __init__(self) -> None:
        self.stage: Any = None
        self.controller: Any = None
        self.clock: Any = None
        self.url: str | None = None
        self.camera: Any = None

    def close(self) -> None:
        try:
            if self.camera is not None:
                self.camera.close()
        finally:
            if self.stage is not None:
                try:
                    from rig.frames import let_go

                    let_go(self.stage)  # what this connection saw (a reset, an alarm, a homing, where it left the stage)
                finally:
                    self.stage.close()
        if self.url is not None:
            from rig.urlhandler.protocol_fakegrbl import unregister

            unregister(self.url)


def is_fake_stage(spec: str) -> bool:
    return spec == "fake" or spec.startswith("fake?")


def open_stage(spec: str, *, baud: int = 115200, tolerance_mm: float = 0.005, devices: Devices | None = None,
               read_only: bool = False):
    """Open the stage named by ``spec`` (see the module docstring); returns the :class:`Devices`.
    ``read_only``: look without resetting or stopping the controller (:class:`rig.grbl.GrblStage`)."""
    from rig.grbl import GrblStage

    devices = devices if devices is not None else Devices()
    if is_fake_stage(spec):
        from rig.fakegrbl import FakeGrbl
        from rig.urlhandler.protocol_fakegrbl import parse_options, register

        try:
            options = parse_options(spec.partition("?")[2], default_clock="virtual")
        except ValueError as error:
            raise RigError(f"--stage {spec!r}: {error}") from None
        devices.clock = VirtualClock() if options.clock == "virtual" else SystemClock()
        devices.controller = FakeGrbl(clock=devices.clock)
        if options.fault is not None:
            devices.controller.arm_fault(options.fault, after=options.after)
        devices.url = register(devices.controller)
        devices.stage = GrblStage(devices.url, clock=devices.clock, wake_s=0.05, tolerance_mm=tolerance_mm,
                                   read_only=read_only)
    else:
        url = spec[len("grbl://"):] if spec.startswith("grbl://") else spec
        if not url:
            raise RigError(f"--stage {spec!r}: give a device, e.g. grbl:///dev/ttyUSB0")
        devices.clock = SystemClock()
        devices.stage = GrblStage(url, baudrate=baud, clock=devices.clock, tolerance_mm=tolerance_mm,
                                   read_only=read_only)
    from rig.frames import witness

    try:
        witness(devices.stage)  # a reset or alarm lock seen on opening outlives this process
    except BaseException:
        devices.stage.close()
        devices.stage = None
        raise
    return devices


@dataclass(frozen=True)
class CameraOptions:
    """What ``lfrig capture`` asks of its camera (``--camera SPEC`` and the camera flags); each field
    is used by the cameras the comments name, ``None`` keeps the device's own value."""

    spec: str = "fake"
    # fake and aravis
    binning: int | None = None  # fake: None = FAKE_BINNING
    roi: tuple[int, int, int, int] | None = None  # X0, Y0, W, H in pixels of the binned detector
    # fake
    fake_rig: str = "default"  # default, ideal, misaligned
    supersample: int = 2
    noise_sigma: float = 0.0
    bit_depth: int = 8
    # opencv
    width: int | None = None
    height: int | None = None
    exposure: float | None = None  # the backend's units (V4L2: 100 us)
    gain: float | None = None
    drop_frames: int | None = None
    hw_trigger: bool = False  # opencv and aravis: pulse the stage's M8 output per frame
    # aravis
    pixel_format: str | None = None
    exposure_us: float | None = None
    gain_db: float | None = None
    trigger: str = "software"
    frame_timeout_s: float = 5.0


def open_camera(options: CameraOptions, devices: Devices, *, centre_mm: tuple[float, float, float]):
    """Open the camera named by ``options.spec``; returns ``(camera, requested_settings)``."""
    spec = options.spec
    roi = tuple(options.roi) if options.roi else None
    if spec == "fake":
        from rig.fakecam import FakeCamera, FakeRig

        base = {"default": FakeRig, "ideal": FakeRig.ideal, "misaligned": FakeRig.misaligned}[options.fake_rig]
        rig = base(ref_mm=tuple(centre_mm))  # the scene is centred on the grid's centre view
        binning = FAKE_BINNING if options.binning is None else options.binning
        if devices.controller is not None:
            position, moving = devices.controller.physical_position, devices.controller.is_moving
        elif devices.stage is not None:
            position, moving = devices.stage.position, None
        else:  # no stage (camera snap, camera preview): the view from the centre
            position, moving = None, None
        try:
            camera = FakeCamera(position, rig=rig, binning=binning, roi=roi, supersample=options.supersample,
                                noise_sigma=options.noise_sigma, bit_depth=options.bit_depth, is_moving=moving)
        except ValueError as error:
            raise RigError(f"--camera fake: {error}") from None
        request = {"device": "fake", "rig": options.fake_rig, "binning": binning,
                   "roi": list(roi) if roi else None, "supersample": options.supersample,
                   "noise_sigma": options.noise_sigma, "bit_depth": options.bit_depth}
        return camera, request
    if spec.startswith("opencv:"):
        from rig.camera import OpenCVCamera, parse_source

        source = parse_source(spec[len("opencv:"):])
        trigger = devices.stage.set_output if options.hw_trigger else None
        camera = OpenCVCamera(source, width=options.width, height=options.height, exposure=options.exposure,
                              gain=options.gain, drop_frames=options.drop_frames, hardware_trigger=trigger,
                              clock=devices.clock)
        request = {"device": spec, "width": options.width, "height": options.height, "exposure": options.exposure,
                   "gain": options.gain, "hw_trigger": bool(options.hw_trigger)}
        return camera, request
    if spec.startswith("aravis:"):
        from rig.aravis import open_aravis

        if options.hw_trigger and options.trigger in ("software", "free"):
            raise RigError("--hw-trigger needs --trigger LINE: the camera input wired to the stage's M8 (e.g. Line1)")
        return open_aravis(
            spec, pixel_format=options.pixel_format, roi=roi, binning=options.binning,
            exposure_us=options.exposure_us, gain_db=options.gain_db, trigger=options.trigger,
            hardware_trigger=devices.stage.set_output if options.hw_trigger else None,
            timeout_s=options.frame_timeout_s, clock=devices.clock,
        )
    raise RigError(f"--camera {spec!r}: expected 'fake', 'opencv:INDEX' (e.g. opencv:0), 'opencv:/dev/videoN', "
                   "'aravis:' (first GenICam camera) or 'aravis:DEVICE_ID'")
