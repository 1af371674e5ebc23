"""``lfrig capture``, ``lfrig stage`` and ``lfrig camera``: parse, open the devices (:mod:`rig.devices`,
which lists the ``--stage`` and ``--camera`` specs), call :mod:`rig.session`, :mod:`rig.snap`,
:mod:`rig.preview`, :mod:`rig.jog` or :mod:`rig.v4l2`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from recon.cliargs import (CommandReport, add_json_argument, finite_float, float_range, int_range, nonnegative_float,
                           nonnegative_int, output_folder, positive_float, positive_int)
from recon.lf.params import MAX_GRID_SIDE
from rig.devices import FAKE_BINNING, FAKE_CENTRE_MM, CameraOptions, Devices, is_fake_stage, open_camera, open_stage
from rig.errors import RigError

def register(subparsers: argparse._SubParsersAction) -> None:
    cap = subparsers.add_parser(
        "capture",
        help="capture a light field on the translation stage (resumable)",
        description=(
            "Home the stage, move the camera through the grid (serpentine, each view approached from the same "
            "direction), take one frame per view and write OUT_DIR in lfrig's capture layout. Run the same command "
            "again to resume an interrupted capture. First Ctrl-C: finish the current view and stop; second: stop "
            "the stage at once (feed hold + reset)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    cap.add_argument("out_dir", type=output_folder, metavar="OUT_DIR", help="capture folder (created, or resumed)")
    _stage_argument(cap)
    cap.add_argument("--camera", default="fake", metavar="SPEC",
                     help="fake, opencv:INDEX|PATH, or aravis:[DEVICE_ID] (a GenICam camera; lfrig camera list)")
    cap.add_argument("--dry-run", action="store_true", help="print the moves and check them against the travel; move nothing")
    grid = cap.add_argument_group("grid")
    grid.add_argument("--rows", type=int_range(1, MAX_GRID_SIDE), default=9, help="views per column (u)")
    grid.add_argument("--cols", type=int_range(1, MAX_GRID_SIDE), default=9, help="views per row (v)")
    grid.add_argument("--pitch-mm", type=positive_float, default=0.5, help="distance between neighbouring views")
    grid.add_argument("--centre-mm", type=finite_float, nargs=3, metavar=("X", "Y", "Z"),
                      help=f"machine position of the centre view (required for a real stage; fake: {FAKE_CENTRE_MM})")
    grid.add_argument("--row-axis", default="+y", help="stage axis along which u (the row) grows")
    grid.add_argument("--col-axis", default="+x", help="stage axis along which v (the column) grows")
    grid.add_argument("--order", choices=("serpentine", "raster"), default="serpentine", help="visiting order")
    grid.add_argument("--backlash-mm", type=nonnegative_float, default=0.2,
                      help="overshoot so every view is approached moving in + direction (0: off)")
    motion = cap.add_argument_group("motion")
    motion.add_argument("--settle-s", type=nonnegative_float, default=0.2, help="wait after the stage stops, before the frame")
    motion.add_argument("--feed-mm-min", type=positive_float, help="feed for G1 moves (default: rapid G0 moves)")
    motion.add_argument("--tolerance-mm", type=positive_float, default=0.005, help="accepted distance from the target")
    motion.add_argument("--no-home", action="store_true",
                        help="do not run the homing cycle first: the capture is taken in GRBL's frame as found")
    motion.add_argument("--retake-all", action="store_true",
                        help="resuming a capture whose machine frame cannot be proven: take every view again in the "
                             "present frame")
    motion.add_argument("--limits-mm", type=finite_float, nargs=6, metavar=("XMIN", "XMAX", "YMIN", "YMAX", "ZMIN", "ZMAX"),
                        help="travel to check against (default: from the controller's $130-$132 settings)")
    camera_options(cap, hw_trigger=True)
    cap.add_argument("--quiet", action="store_true", help="no progress bar")
    add_json_argument(cap)
    cap.set_defaults(handler=_capture)

    stage = subparsers.add_parser(
        "stage",
        help="home, jog or query the stage",
        description=(
            "Talk to the stage by hand: home it, move it to an absolute machine position, or show its status. "
            "Ctrl-C stops a move (feed hold, then soft reset) or a homing cycle (soft reset: home again) and "
            "prints where the stage is; status only looks and stops nothing."
        ),
    )
    actions = stage.add_subparsers(dest="action", metavar="ACTION", required=True)
    home = actions.add_parser("home", help="run the homing cycle ($H)")
    _stage_argument(home)
    move = actions.add_parser("move", help="move to an absolute machine position (mm) and wait")
    for axis in "xyz":  # three positionals: argparse cannot print a tuple metavar of a positional
        move.add_argument(axis, type=finite_float, metavar=axis.upper(), help=f"machine {axis.upper()} in mm")
    move.add_argument("--feed-mm-min", type=positive_float, help="feed (default: rapid)")
    move.add_argument("--home", action="store_true", help="home first")
    _stage_argument(move)
    status = actions.add_parser("status", help="print the controller's state and position")
    _stage_argument(status)
    unlock = actions.add_parser("unlock", help="clear an alarm lock without homing ($X)")
    _stage_argument(unlock)
    for parser in (home, move, status, unlock):
        add_json_argument(parser)
        parser.set_defaults(handler=_stage)
    jog = actions.add_parser(
        "jog", help="move the stage from the keyboard; c prints the --centre-mm for lfrig capture",
        description="Keyboard jogging in the terminal (GRBL 1.1 $J= jogs): arrow keys move X/Y, Page Up/Down Z, "
                    "+/- change the step, f/s the feed, c waits until the stage stands still and prints the "
                    "--centre-mm X Y Z to use with lfrig capture, space stops, q or Ctrl-C stops and quits. The "
                    "position shown is the controller's report. The fake stage runs in real time here.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    jog.add_argument("--step-mm", type=positive_float, default=0.1,
                     help="first step (the nearest of 0.001 0.01 0.05 0.1 0.5 1 5 10)")
    jog.add_argument("--feed-mm-min", type=positive_float, default=500.0,
                     help="first feed (the nearest of 10 50 100 200 500 1000 2000)")
    jog.add_argument("--home", action="store_true", help="home first")
    _stage_argument(jog)
    jog.set_defaults(handler=_stage_jog)
    _register_camera(subparsers)


def camera_options(parser: argparse.ArgumentParser, *, hw_trigger: bool) -> None:
    """The camera options of ``lfrig capture`` (read by :func:`rig.devices.open_camera`); ``camera snap`` and
    ``camera preview`` take the same ones, without ``--hw-trigger`` (they run without a stage)."""
    camera = parser.add_argument_group("camera (opencv)")
    camera.add_argument("--width", type=positive_int, help="requested frame width in pixels")
    camera.add_argument("--height", type=positive_int, help="requested frame height in pixels")
    camera.add_argument("--exposure", type=positive_float, help="exposure in the backend's units (V4L2: 100 us)")
    camera.add_argument("--gain", type=nonnegative_float, help="gain in the backend's units")
    camera.add_argument("--drop-frames", type=nonnegative_int, help="buffered frames dropped per trigger (default 4)")
    if hw_trigger:
        camera.add_argument("--hw-trigger", action="store_true", help="pulse the stage's M8 output to trigger each frame")
    else:
        parser.set_defaults(hw_trigger=False)
    gen = parser.add_argument_group("camera (aravis)")
    gen.add_argument("--pixel-format", help="GenICam pixel format, e.g. Mono8, Mono12, BayerRG8 (None: keep the camera's)")
    gen.add_argument("--exposure-us", type=positive_float, help="exposure time in microseconds (auto exposure off)")
    gen.add_argument("--gain-db", type=finite_float, help="gain in dB (auto gain off)")
    gen.add_argument("--trigger", default="software", metavar="MODE",
                     help="software, free (free-running), or a trigger line such as Line1 (with --hw-trigger: the stage's M8)")
    gen.add_argument("--frame-timeout-s", type=positive_float, default=5.0, help="longest wait for a frame after the trigger")
    fake = parser.add_argument_group("camera (fake; --binning and --roi also for aravis)")
    fake.add_argument("--binning", type=positive_int, help=f"detector binning (fake: default {FAKE_BINNING}; 1: 1280x980, 2: 640x490, ...)")
    fake.add_argument("--roi", type=nonnegative_int, nargs=4, metavar=("X0", "Y0", "W", "H"), help="region of the binned detector")
    fake.add_argument("--supersample", type=int_range(1, 16), default=2, help="samples per pixel along each axis")
    fake.add_argument("--noise", type=float_range(0.0, 1.0), default=0.0, help="Gaussian noise sigma, fraction of full scale")
    fake.add_argument("--bit-depth", type=int, choices=(8, 16), default=8)
    fake.add_argument("--fake-rig", choices=("default", "ideal", "misaligned"), default="default",
                      help="true geometry of the simulated camera and stage")


def _stage_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--stage", default="fake", metavar="SPEC",
                        help="fake[?clock=real|virtual&fault=KIND&after=N], grbl://DEVICE, a device path or a pyserial URL")
    parser.add_argument("--baud", type=positive_int, default=115200, help="serial baud rate")


# --------------------------------------------------------------------------------------------------
# Handlers


def _grid_from_args(args: argparse.Namespace):
    from rig.grid import GridSpec, parse_axis

    if args.centre_mm is not None:
        centre = tuple(args.centre_mm)
    elif is_fake_stage(args.stage):
        centre = FAKE_CENTRE_MM
    else:
        raise RigError("give --centre-mm X Y Z: the machine position (mm) of the centre view on this stage")
    return GridSpec(
        rows=args.rows, cols=args.cols, pitch_mm=args.pitch_mm, centre_mm=centre,  # type: ignore[arg-type]
        row_axis=parse_axis(args.row_axis), col_axis=parse_axis(args.col_axis),
        order=args.order, backlash_mm=args.backlash_mm,
    )


def _limits_from_args(args: argparse.Namespace):
    if args.limits_mm is None:
        return None
    v = args.limits_mm
    return ((v[0], v[1]), (v[2], v[3]), (v[4], v[5]))


def _camera_options(args: argparse.Namespace) -> CameraOptions:
    return CameraOptions(
        spec=args.camera, binning=args.binning, roi=tuple(args.roi) if args.roi else None, fake_rig=args.fake_rig,
        supersample=args.supersample, noise_sigma=args.noise, bit_depth=args.bit_depth, width=args.width,
        height=args.height, exposure=args.exposure, gain=args.gain, drop_frames=args.drop_frames,
        hw_trigger=args.hw_trigger, pixel_format=args.pixel_format, exposure_us=args.exposure_us,
        gain_db=args.gain_db, trigger=args.trigger, frame_timeout_s=args.frame_timeout_s,
    )


def _capture(args: argparse.Namespace) -> int:
    from rig.grid import check_limits, format_plan, grid_extent_mm, plan_moves
    from recon.progress import Progress
    from rig.session import CaptureInterrupted, plan_summary, run_capture

    grid = _grid_from_args(args)
    limits = _limits_from_args(args)
    out = CommandReport(as_json=args.json)
    if args.dry_run:
        moves = plan_moves(grid)
        out.line(format_plan(moves), moves=[{"target_mm": m.target_mm, "view": m.view} for m in moves])
        summary = plan_summary(moves)
        out.line(summary, summary=summary)
        extent = grid_extent_mm(moves)
        out.line("extent: " + ", ".join(f"{a} [{lo:.3f}, {hi:.3f}]" for a, (lo, hi) in zip("xyz", extent)) + " mm",
                 extent_mm=extent)
        off_grid: list[str] = []
        if limits is None:
            devices = open_stage(args.stage, baud=args.baud, tolerance_mm=args.tolerance_mm)
            try:
                limits = devices.stage.limits_mm()
                off_grid = devices.stage.off_step_grid([m.target_mm for m in moves])
            finally:
                devices.close()
        for problem in off_grid[:3]:
            print(f"lfrig: warning: {problem}; a capture with this plan is refused", file=sys.stderr)
        if len(off_grid) > 3:
            print(f"lfrig: warning: {len(off_grid) - 3} more targets lie between motor steps", file=sys.stderr)
        if limits is None:
            out.line("travel limits unknown (soft limits off on the controller): not checked; pass --limits-mm",
                     limits_mm=None, off_step_grid=off_grid)
        else:
            check_limits(moves, limits)
            out.line("all moves within the travel " + ", ".join(f"{a} [{lo:.3f}, {hi:.3f}]" for a, (lo, hi) in zip("xyz", limits)) + " mm",
                     limits_mm=limits, off_step_grid=off_grid)
        out.finish()
        return 0

    from recon.lf.capture import is_capture
    from recon.lf.lock import FolderLock
    from rig.protocols import FrameAware

    # Lock the folder before opening anything: a second capture must not touch the stage or camera
    # (opening a GRBL's serial port resets it) while the first one drives them.
    lock = FolderLock(args.out_dir, what="capture")
    fresh = not is_capture(args.out_dir)  # (not "the folder exists": the lock above has just created it)
    devices = Devices()
    try:
        open_stage(args.stage, baud=args.baud, tolerance_mm=args.tolerance_mm, devices=devices)
        devices.camera, request = open_camera(_camera_options(args), devices, centre_mm=grid.centre_mm)
        doubt = devices.stage.machine_frame_doubt() if isinstance(devices.stage, FrameAware) else None
        if args.no_home and doubt and fresh:  # a resume is checked by the session
            print(f"lfrig: warning: {doubt}; without homing this capture is taken in GRBL's present frame, and a "
                  "resume without homing will be refused after any reset", file=sys.stderr)
        try:
            with Progress("capture", quiet=args.quiet) as bar:
                result = run_capture(
                    args.out_dir, stage=devices.stage, camera=devices.camera, grid=grid, settle_s=args.settle_s,
                    feed_mm_min=args.feed_mm_min, home=not args.no_home, limits_mm=limits,
                    tolerance_mm=args.tolerance_mm, camera_request=request, clock=devices.clock,
                    progress=bar, header_extra={"lfrig": {"stage": args.stage, "camera": args.camera}},
                    lock=lock, retake_all=args.retake_all,
                )
        except CaptureInterrupted as error:
            print(f"lfrig: {error}", file=sys.stderr)
            return 130
    finally:
        try:
            devices.close()
        finally:
            # a capture refused before its first view leaves nothing: no journal, no lock, no folder
            lock.release(discard=fresh and not is_capture(args.out_dir))
    if result.interrupted:
        print(
            f"lfrig: stopped with {result.completed} of {result.total} views in {result.path}; "
            "run the same command again to resume",
            file=sys.stderr,
        )
        return 130
    out.line(f"{result.path}: {result.completed} of {result.total} views ({result.taken} taken now), complete",
             path=result.path, views=result.completed, total=result.total, taken=result.taken, complete=True)
    out.finish()
    return 0


def _stage(args: argparse.Namespace) -> int:
    # `status` only looks: no soft reset (it would abort a homing cycle with ALARM:6 or a move with ALARM:3)
    devices = open_stage(args.stage, baud=args.baud, read_only=args.action == "status")
    stage = devices.stage
    try:
        try:
            if args.action == "home":
                print("lfrig: homing: each axis runs to its switch and pulls off (Ctrl-C stops it)", file=sys.stderr,
                      flush=True)
                stage.home()
            elif args.action == "unlock":
                stage.unlock()
                doubt = stage.machine_frame_doubt()
                if doubt:
                    from rig.frames import witness

                    seen = witness(stage)
                    kept = f" (kept in {seen.record.file})" if seen is not None and seen.record is not None else ""
                    print(f"lfrig: warning: unlocked without homing: {doubt}. Positions are GRBL's present frame, and "
                          f"a capture begun before cannot be resumed with --no-home{kept}: home it (`lfrig stage home`) "
                          "or retake its views", file=sys.stderr)
            elif args.action == "move":
                _home_or_prepare(stage, home=args.home, frame="X Y Z are taken in GRBL's present frame, which need "
                                                              "not be the machine frame of earlier sessions")
                stage.check_step_grid([(args.x, args.y, args.z)])
                print(f"lfrig: moving to X={args.x:.3f}, Y={args.y:.3f}, Z={args.z:.3f} mm (Ctrl-C stops it)",
                      file=sys.stderr, flush=True)
                stage.move_to((args.x, args.y, args.z), feed_mm_min=args.feed_mm_min)
                stage.wait_until_idle()
        except KeyboardInterrupt:
            return _stop_on_ctrl_c(stage)
        out = CommandReport(as_json=args.json)
        line, fields = _status_report(stage)
        out.line(line, **fields)
        out.finish()
    finally:
        devices.close()
    return 0


def _home_or_prepare(stage, *, home: bool, frame: str) -> None:
    """Home (``--home``), or warn with ``frame`` when the machine frame is in doubt and set the modes."""
    if home:
        stage.home()
        return
    doubt = stage.machine_frame_doubt()
    if doubt:
        print(f"lfrig: warning: {doubt}; {frame} (use --home for positions from the switches)", file=sys.stderr)
    stage.prepare()


def _stage_jog(args: argparse.Namespace) -> int:
    from rig.jog import HELP, JogSettings, centre_option, keyboard, run_jog

    fd = sys.stdin.fileno()
    with keyboard(fd):  # refuses a non-terminal before the stage is opened
        spec = args.stage
        if is_fake_stage(spec) and "clock=" not in spec:  # an interactive fake moves in real time
            spec = spec + ("&" if "?" in spec else "?") + "clock=real"
        devices = open_stage(spec, baud=args.baud)
        stage = devices.stage
        try:
            _home_or_prepare(stage, home=args.home, frame="the positions shown are in GRBL's present frame")
            print(f"jogging {stage.url} (GRBL {stage.version}); {HELP}", flush=True)

            def write(text: str) -> None:
                sys.stdout.write(text)
                sys.stdout.flush()

            centre = run_jog(stage, fd=fd, write=write,
                             settings=JogSettings.nearest(step_mm=args.step_mm, feed_mm_min=args.feed_mm_min))
        finally:
            devices.close()
    if centre is not None:
        print(f"grid centre for lfrig capture: {centre_option(centre)}")
    return 0


def _status_report(stage) -> tuple[str, dict]:
    """The controller's status as one readable line and as fields (``url``, ``version``, the status dict)."""
    status = stage.status()
    position = status.get("mpos_mm")
    where = "unknown" if position is None else ", ".join(f"{a}={c:.3f}" for a, c in zip("XYZ", position))
    state = status["state"] + (f":{status['substate']}" if status.get("substate") is not None else "")
    line = f"{state}  MPos {where} mm  ({stage.url}, GRBL {stage.version or '(version not read)'})"
    return line, {"url": stage.url, "version": stage.version, **status}


def _status_line(stage) -> str:
    return _status_report(stage)[0]


def _stop_on_ctrl_c(stage) -> int:
    """Ctrl-C during `stage home` or `stage move`: stop the stage (homing by a soft reset, a move by a
    feed hold and then a reset) and say where it is. Further Ctrl-Cs wait for the stop."""
    import signal

    def wait(signum, frame):
        print("lfrig: already stopping the stage, please wait", file=sys.stderr)

    previous = signal.signal(signal.SIGINT, wait)
    try:
        print("lfrig: Ctrl-C: stopping the stage", file=sys.stderr)
        try:
            done = stage.interrupt()
            where = _status_line(stage)
        except RigError as error:
            print(f"lfrig: error: Ctrl-C: stopping the stage failed: {error}", file=sys.stderr)
            return 130
    finally:
        signal.signal(signal.SIGINT, previous)
    advice = "; home it before moving (`lfrig stage home`)" if stage.homing_required else ""
    print(f"lfrig: interrupted: {done}{advice}; the stage now reports {where}", file=sys.stderr)
    return 130


def _register_camera(subparsers: argparse._SubParsersAction) -> None:
    camera = subparsers.add_parser(
        "camera",
        help="list cameras, show one's features, take one frame, or serve a live view",
        description="The cameras lfrig drives: GigE Vision / USB3 Vision cameras through Aravis and V4L2 devices "
                    "(/dev/video*) through OpenCV; one frame (snap) or a live view in a browser (preview).",
    )
    actions = camera.add_subparsers(dest="action", metavar="ACTION", required=True)
    listing = actions.add_parser("list", help="the cameras found (Aravis and /dev/video*), with the specs --camera takes")
    listing.add_argument("--fake", action="store_true", help="include Aravis's simulated camera Fake_1")
    listing.add_argument("--dev-dir", type=Path, default=Path("/dev"), metavar="DIR",
                         help="where to look for video* device nodes")
    add_json_argument(listing)
    listing.set_defaults(handler=_camera_list)
    info = actions.add_parser("info", help="identity, sensor, pixel formats, ROI/binning/exposure/gain ranges, triggers")
    info.add_argument("spec", metavar="SPEC",
                      help="aravis: (first camera), aravis:DEVICE_ID (e.g. aravis:Fake_1), or opencv:INDEX|PATH")
    info.add_argument("--all", action="store_true", help="also every GenICam feature and its current value (aravis)")
    add_json_argument(info)
    info.set_defaults(handler=_camera_info)
    snap = actions.add_parser(
        "snap", help="take one frame and write it as PNG, with its size, range and clipping",
        description="Take one frame with the camera options of lfrig capture and write it atomically as PNG "
                    "(16-bit when the camera gives more than 8 bits); print its size, min/max and clipped fraction.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    snap.add_argument("camera", metavar="CAMERA", help="fake, opencv:INDEX|PATH, aravis: or aravis:DEVICE_ID")
    snap.add_argument("-o", "--output", required=True, type=Path, metavar="FILE", help="the PNG to write")
    add_json_argument(snap)
    camera_options(snap, hw_trigger=False)
    snap.set_defaults(handler=_camera_snap)
    preview = actions.add_parser(
        "preview", help="a live view in the browser: focus measure, clipping overlay, histogram",
        description="Serve a live view of the camera on http://127.0.0.1:PORT/ (over SSH: ssh -L PORT:127.0.0.1:PORT "
                    "HOST, then open that address on your machine): the image with clipped pixels painted (red: at "
                    "the top of the range, blue: at 0), the focus measure (variance of the Laplacian) on a region "
                    "dragged on the image or given as --focus-roi, min/max, clipped fractions and the histogram. "
                    "Ctrl-C stops it.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    preview.add_argument("camera", metavar="CAMERA", help="fake, opencv:INDEX|PATH, aravis: or aravis:DEVICE_ID")
    preview.add_argument("--port", type=int_range(0, 65535), default=8000, help="TCP port (0: a free one)")
    preview.add_argument("--host", default="127.0.0.1",
                         help="address to listen on; other than 127.0.0.1/localhost/::1 only with --allow-remote")
    preview.add_argument("--allow-remote", action="store_true",
                         help="listen on --host even if other machines can reach it (the page has no password)")
    preview.add_argument("--focus-roi", type=nonnegative_int, nargs=4, metavar=("X0", "Y0", "W", "H"),
                         help="region of the frame (px) for the focus measure (default: the whole frame)")
    preview.add_argument("--fps-max", type=positive_float, default=10.0, help="highest frame rate grabbed")
    preview.add_argument("--view-max-px", type=int_range(64, 16384), default=1024,
                         help="longest side of the displayed image (shrunk by an integer factor)")
    camera_options(preview, hw_trigger=False)
    preview.set_defaults(handler=_camera_preview)


def _camera_list(args: argparse.Namespace) -> int:
    from rig.aravis import list_devices
    from rig.v4l2 import describe_line, list_opencv_devices

    if not args.dev_dir.is_dir():
        raise RigError(f"--dev-dir {args.dev_dir}: not a folder; give the folder holding the video* device nodes")
    genicam = list_devices(include_fake=args.fake)
    video = list_opencv_devices(dev_dir=args.dev_dir)
    out = CommandReport(as_json=args.json)
    out.line("\n".join([f"aravis:{d['id']}  {d['vendor']} {d['model']}  serial {d['serial']}  {d['protocol']}"
                        + (f"  {d['address']}" if d.get("address") else "") for d in genicam])
             or "no GenICam camera found (GigE: check the network and the camera's IP; USB3: check the cable and "
                "udev permissions; --fake lists Aravis's simulated camera)", aravis=genicam)
    out.line("\n".join(describe_line(entry) for entry in video)
             or f"no video device found ({args.dev_dir}/video*: a USB camera needs its cable and the uvcvideo driver; "
                "inside a container, pass the device through)", opencv=video)
    out.finish()
    return 0


def _camera_info(args: argparse.Namespace) -> int:
    out = CommandReport(as_json=args.json)
    if args.spec.startswith("opencv:"):
        from rig.camera import parse_source
        from rig.v4l2 import describe_line, probe

        source = parse_source(args.spec[len("opencv:"):])
        if source == "":
            raise RigError(f"camera {args.spec!r}: give a device index or path, e.g. opencv:0 or opencv:/dev/video0")
        reading = probe(source)
        if not reading["opens"]:
            raise RigError(f"camera {args.spec!r}: OpenCV cannot open it; check the index or path "
                           "(lfrig camera list) and that no other program uses it")
        out.line(describe_line(reading), **reading)
        out.finish()
        return 0

    if not args.spec.startswith("aravis:"):
        raise RigError(f"camera {args.spec!r}: expected aravis:, aravis:DEVICE_ID or opencv:INDEX|PATH "
                       "(lfrig camera list shows them)")
    from rig.aravis import AravisCamera, describe, parse_spec

    with AravisCamera(parse_spec(args.spec), acquire=False) as camera:
        info = describe(camera, all_features=args.all)

    def rng(value: list[float] | None, unit: str = "") -> str:
        return "n/a" if value is None else f"{value[0]:g} .. {value[1]:g}{unit}"

    current = info["current"]
    lines = [
        f"{args.spec}: {info['vendor']} {info['model']}, serial {info['serial']} ({info['protocol']})",
        f"  sensor         {info['sensor_px'][0]} x {info['sensor_px'][1]} px" if info["sensor_px"] else "  sensor         unknown",
        f"  pixel formats  {', '.join(info['pixel_formats'])} (lfrig decodes: {', '.join(info['pixel_formats_lfrig_decodes']) or 'none'})",
        f"  ROI            width {rng(info['width_px'], ' px')}, height {rng(info['height_px'], ' px')}; now {current['roi']}",
        f"  binning        {rng(info['binning_x'])} x {rng(info['binning_y'])}; now {current['binning']}",
        f"  exposure       {rng(info['exposure_us'], ' us')}; now {current['exposure_us']} us",
        f"  gain           {rng(info['gain'], ' ' + info['gain_unit'])}; now {current['gain']} {info['gain_unit']}",
        f"  triggers       {', '.join(info['triggers']) or 'none'}; sources {', '.join(info['trigger_sources']) or 'none'}"
        f"; software trigger {'yes' if info['software_trigger'] else 'no'}",
        f"  format now     {current['pixel_format']}, frame rate {current['frame_rate_hz']} Hz",
    ]
    if args.all:
        def show(tree: dict, depth: int) -> None:
            for key, value in tree.items():
                if isinstance(value, dict):
                    lines.append("  " * depth + f"{key}/")
                    show(value, depth + 1)
                else:
                    lines.append("  " * depth + f"{key} = {value}")
        show(info.get("features", {}), 1)
    out.line("\n".join(lines), **info)
    out.finish()
    return 0


def _open_bench_camera(args: argparse.Namespace) -> Devices:
    """The camera named by ``args.camera`` without a stage (the fake camera sees the scene from its centre)."""
    devices = Devices()
    devices.camera, _ = open_camera(_camera_options(args), devices, centre_mm=FAKE_CENTRE_MM)
    return devices


def _camera_snap(args: argparse.Namespace) -> int:
    from rig.snap import check_snap_path, snap

    path = check_snap_path(args.output)
    devices = _open_bench_camera(args)
    try:
        stats = snap(devices.camera, path)
    finally:
        devices.close()
    from dataclasses import asdict

    out = CommandReport(as_json=args.json)
    out.line(f"{path}: {stats.line()}", path=path, **asdict(stats))
    out.finish()
    return 0


def _camera_preview(args: argparse.Namespace) -> int:
    from rig.preview import LOCAL_HOSTS, Preview

    if args.host not in LOCAL_HOSTS and not args.allow_remote:
        raise RigError(f"--host {args.host}: the preview has no password, so it listens on 127.0.0.1 only; "
                       "forward the port over SSH (ssh -L PORT:127.0.0.1:PORT HOST), or add --allow-remote")
    if args.focus_roi is not None and (args.focus_roi[2] < 3 or args.focus_roi[3] < 3):
        raise RigError(f"--focus-roi {' '.join(map(str, args.focus_roi))}: width and height must be at least 3 px")
    devices = _open_bench_camera(args)
    try:
        preview = Preview(devices.camera, roi=tuple(args.focus_roi) if args.focus_roi else None,
                          fps_max=args.fps_max, view_max_px=args.view_max_px, any_host=args.allow_remote)
        server = preview.bind(host=args.host, port=args.port)
        if args.host not in LOCAL_HOSTS:
            print(f"lfrig: warning: listening on {args.host}: anyone who reaches this address sees the camera",
                  file=sys.stderr)
        try:
            preview.serve(server, on_ready=lambda url: print(f"preview of {args.camera} on {url} (Ctrl-C stops it)",
                                                             flush=True))
        except KeyboardInterrupt:
            interrupted = True
        else:
            interrupted = False
    finally:
        devices.close()
    if interrupted:
        print(f"lfrig: preview stopped (Ctrl-C); camera closed, port {server.server_address[1]} freed", file=sys.stderr)
        return 130
    return 0
