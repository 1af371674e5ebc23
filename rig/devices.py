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

from typing import Any

from rig.clock import SystemClock, VirtualClock
from rig.errors import RigError

#: Grid centre used with the fake stage when none is given: well inside its 100 x 100 x 50 mm travel.
FAKE_CENTRE_MM = (-50.0, -50.0, -10.0)


class Devices:
    """What the CLI opened: the stage, the fake controller behind it (if any) and the shared clock."""

    def __init__(self) -> None:
        self.stage: Any = None
        self.controller: Any = None
        self.clock: Any = None
        self.url: str | None = None
        self.camera: Any = None

    def close(self) -> None:
        if self.camera is not None:
            self.camera.close()
        if self.stage is not None:
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
    return devices


def open_camera(args: Any, devices: Devices, *, centre_mm: tuple[float, float, float]):
    """Open the camera named by ``args.camera``; returns ``(camera, requested_settings)``.

    ``args`` carries the camera options of ``lfrig capture`` (``binning``, ``roi``, ``exposure``, ...:
    see ``lfrig capture --help``) as attributes, e.g. an :class:`argparse.Namespace`.
    """
    spec = args.camera
    if spec == "fake":
        from rig.fakecam import FakeCamera, FakeRig

        base = {"default": FakeRig, "ideal": FakeRig.ideal, "misaligned": FakeRig.misaligned}[args.fake_rig]
        rig = base(ref_mm=tuple(centre_mm))  # the scene is centred on the grid's centre view
        binning = 2 if args.binning is None else args.binning  # --binning is shared with aravis (None: the camera's)
        if devices.controller is not None:
            position, moving = devices.controller.physical_position, devices.controller.is_moving
        else:
            position, moving = devices.stage.position, None
        try:
            camera = FakeCamera(position, rig=rig, binning=binning, roi=tuple(args.roi) if args.roi else None,
                                supersample=args.supersample, noise_sigma=args.noise, bit_depth=args.bit_depth,
                                is_moving=moving)
        except ValueError as error:
            raise RigError(f"--camera fake: {error}") from None
        request = {"device": "fake", "rig": args.fake_rig, "binning": binning,
                   "roi": list(args.roi) if args.roi else None, "supersample": args.supersample,
                   "noise_sigma": args.noise, "bit_depth": args.bit_depth}
        return camera, request
    if spec.startswith("opencv:"):
        from rig.camera import OpenCVCamera, parse_source

        source = parse_source(spec[len("opencv:"):])
        trigger = devices.stage.set_output if args.hw_trigger else None
        camera = OpenCVCamera(source, width=args.width, height=args.height, exposure=args.exposure, gain=args.gain,
                              drop_frames=args.drop_frames, hardware_trigger=trigger, clock=devices.clock)
        request = {"device": spec, "width": args.width, "height": args.height, "exposure": args.exposure,
                   "gain": args.gain, "hw_trigger": bool(args.hw_trigger)}
        return camera, request
    if spec.startswith("aravis:"):
        from rig.aravis import open_aravis

        if args.hw_trigger and args.trigger in ("software", "free"):
            raise RigError("--hw-trigger needs --trigger LINE: the camera input wired to the stage's M8 (e.g. Line1)")
        return open_aravis(
            spec, pixel_format=args.pixel_format, roi=tuple(args.roi) if args.roi else None, binning=args.binning,
            exposure_us=args.exposure_us, gain_db=args.gain_db, trigger=args.trigger,
            hardware_trigger=devices.stage.set_output if args.hw_trigger else None,
            timeout_s=args.frame_timeout_s, clock=devices.clock,
        )
    raise RigError(f"--camera {spec!r}: expected 'fake', 'opencv:INDEX' (e.g. opencv:0), 'opencv:/dev/videoN', "
                   "'aravis:' (first GenICam camera) or 'aravis:DEVICE_ID'")
