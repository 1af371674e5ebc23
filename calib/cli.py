"""``lfrig calibrate intrinsics``, ``lfrig calibrate stage`` and ``lfrig rectify``: parse, call the
library (``calib.intrinsics``, ``calib.stage``, ``calib.rectify``), write files."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from recon.cliargs import CommandReport, add_json_argument, output_file, output_folder, positive_float


def _board_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", required=True, metavar="COLSxROWS",
                   help="inner corners per row x per column, e.g. 10x7 for a board of 11x8 squares")
    p.add_argument("--square-mm", type=positive_float, required=True, metavar="S", help="side of one square, mm")
    p.add_argument("--charuco", metavar="DICT",
                   help="the board is a ChArUco board with this ArUco dictionary (e.g. DICT_5X5_100)")
    p.add_argument("--marker-mm", type=positive_float, help="ChArUco marker side, mm (default 0.7 squares)")


def register(subparsers: argparse._SubParsersAction) -> None:
    cal = subparsers.add_parser(
        "calibrate",
        help="calibrate the camera (intrinsics) or the stage geometry",
        description="Camera and stage calibration; see docs/calibration.md for the lab procedure.",
    )
    sub = cal.add_subparsers(dest="calibrate_command", metavar="WHAT", required=True)

    intr = sub.add_parser(
        "intrinsics",
        help="camera model from images of a calibration board (mrcal)",
        description=(
            "Find the board's corners in every image (OpenCV; images without a board are listed and skipped), "
            "solve the camera model with mrcal (staged, with outlier rejection) and write an mrcal .cameramodel. "
            "Prints the RMS reprojection error, the outliers and the projection uncertainty at the working "
            "distance, and writes a residual picture next to the model."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    intr.add_argument("images", nargs="+", type=Path, metavar="IMAGES", help="board images (PNG, JPEG, TIFF)")
    _board_args(intr)
    intr.add_argument("-o", "--output", type=output_file, required=True, metavar="CAM.cameramodel")
    intr.add_argument("--lensmodel", default="LENSMODEL_OPENCV8",
                      help="mrcal lens model (LENSMODEL_OPENCV4/5/8, LENSMODEL_SPLINED_STEREOGRAPHIC_...)")
    intr.add_argument("--focal-px", type=positive_float, help="seed for the focal length (default: estimated)")
    intr.add_argument("--working-distance-mm", type=positive_float, default=1000.0,
                      help="distance at which the projection uncertainty is reported")
    intr.add_argument("--residuals", type=output_file, metavar="PNG",
                      help="residual picture (default: next to the model, .residuals.png)")
    intr.add_argument("--quiet", action="store_true", help="no progress output")
    add_json_argument(intr)
    intr.set_defaults(handler=_intrinsics)

    st = sub.add_parser(
        "stage",
        help="true pitch, skew and rotation of the stage from a capture of a board",
        description=(
            "From a capture (lfrig capture) of a board that is whole in every view, fit one camera rotation, "
            "the board's position and the two step vectors of the grid jointly (least squares on the "
            "reprojection error through the camera model). Writes the stage calibration as JSON."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    st.add_argument("capture", type=Path, metavar="CAPTURE_DIR")
    st.add_argument("--model", type=Path, required=True, metavar="CAM.cameramodel")
    _board_args(st)
    st.add_argument("-o", "--output", type=output_file, required=True, metavar="STAGE.json")
    st.add_argument("--quiet", action="store_true", help="no progress output")
    add_json_argument(st)
    st.add_argument("--no-verify", dest="verify", action="store_false",
                    help="do not check the capture's views against the checksums in its journal")
    st.set_defaults(handler=_stage)

    rect = subparsers.add_parser(
        "rectify",
        help="undistort and rectify a capture into a pure-translation light field",
        description=(
            "Resample every view of CAPTURE_DIR with one map built from the camera model and the stage "
            "calibration, so that a scene point moves by exactly (u-u0)*d, (v-v0)*d between views. The output "
            "is a capture folder whose parameters record the rectified focal length (px), principal point and the "
            "true pitch (mm). The views are cropped to the rectangle whose pixels all come from inside the camera "
            "image (no black borders); --no-crop keeps the camera's image size."
        ),
    )
    rect.add_argument("capture", type=Path, metavar="CAPTURE_DIR")
    rect.add_argument("--model", type=Path, required=True, metavar="CAM.cameramodel")
    rect.add_argument("--stage", type=Path, required=True, metavar="STAGE.json")
    rect.add_argument("-o", "--output", type=output_folder, required=True, metavar="RECT_DIR")
    rect.add_argument("--focal-px", type=positive_float, help="focal length of the rectified views (default: the camera's)")
    rect.add_argument("--no-crop", dest="crop", action="store_false",
                      help="keep the camera's image size, with black where no camera pixel maps")
    rect.add_argument("--no-verify", dest="verify", action="store_false",
                      help="do not check the capture's views against the checksums in its journal")
    rect.add_argument("--quiet", action="store_true", help="no progress output")
    add_json_argument(rect)
    rect.set_defaults(handler=_rectify)


def _board(args: argparse.Namespace):
    from calib.intrinsics import parse_board

    return parse_board(args.board, square_mm=args.square_mm, charuco=args.charuco, marker_mm=args.marker_mm)


def _intrinsics(args: argparse.Namespace) -> int:
    from calib.errors import CalibError
    from calib.intrinsics import calibrate_intrinsics_from_images, write_residual_picture
    from recon.progress import Progress

    from recon.paths import writable_file

    board = _board(args)
    if not args.output.parent.is_dir():
        raise CalibError(f"{args.output.parent}: no such folder for the camera model")
    picture = args.residuals or args.output.with_suffix(".residuals.png")
    writable_file(args.output, what="camera model")  # before the solve, not after it
    writable_file(picture, what="residual picture")
    with Progress("finding corners", quiet=args.quiet) as bar:
        result = calibrate_intrinsics_from_images(args.images, board=board, lensmodel=args.lensmodel,
                                                  focal_estimate_px=args.focal_px,
                                                  working_distance_mm=args.working_distance_mm, progress=bar)
    note = "lfrig calibrate intrinsics\n" + result.report()
    from recon.lf.imageio import atomic_output

    # Through a temporary name and a rename, as every file lfrig writes: a crash or a full disk
    # leaves the previous model (or none), never half of one.
    with atomic_output(args.output, what="camera model") as tmp:
        result.model.write(str(tmp), note=note)
    with atomic_output(picture, what="residual picture") as tmp:
        write_residual_picture(result, tmp)
    out = CommandReport(as_json=args.json)
    if args.json:
        lensmodel, intrinsics = result.model.intrinsics()
        out.line("", lensmodel=lensmodel, intrinsics=[float(v) for v in intrinsics],
                 imager=[int(v) for v in result.model.imagersize()], rms_px=float(result.rms_px),
                 worst_px=float(result.worst_px), images_used=list(result.used), images_skipped=list(result.skipped),
                 outliers=len(result.outliers), corners=int(result.n_corners),
                 uncertainty_px={k: float(v) for k, v in result.uncertainty_px.items()})
    else:
        out.line(result.report())
    out.line(f"wrote {args.output} and {picture}", output=args.output, residuals=picture)
    out.finish()
    return 0


def _stage(args: argparse.Namespace) -> int:
    from calib.stage import calibrate_stage_from_capture, load_model
    from recon.progress import Progress

    from recon.paths import writable_file

    model = load_model(args.model)
    board = _board(args)
    writable_file(args.output, what="stage calibration")
    with Progress("finding corners", quiet=args.quiet) as bar:
        stage, _ = calibrate_stage_from_capture(args.capture, model=model, board=board, progress=bar,
                                                verify=args.verify)
    stage.save(args.output)
    out = CommandReport(as_json=args.json)
    out.line(stage.report(), stage=stage.to_json())
    out.line(f"wrote {args.output}", output=args.output)
    out.finish()
    return 0


def _rectify(args: argparse.Namespace) -> int:
    from calib.rectify import rectify_capture
    from recon.progress import Progress
    from recon.paths import writable_folder

    writable_folder(args.output, what="rectified capture")  # read-only, full, a file: before the work

    with Progress("rectify", quiet=args.quiet) as bar:
        rect = rectify_capture(args.capture, args.output, model_path=args.model, stage_path=args.stage,
                               focal_px=args.focal_px, crop=args.crop, verify=args.verify, progress=bar)
    w, h = rect.image_size
    cx, cy = float(rect.K_rect[0, 2]), float(rect.K_rect[1, 2])
    out = CommandReport(as_json=args.json)
    out.line(f"wrote {args.output}: rectified views {w}x{h} px, focal {rect.focal_px:.2f} px, principal point "
             f"({cx:.1f}, {cy:.1f}) px, pitch {rect.pitch_mm:.5f} mm",
             output=args.output, focal_px=rect.focal_px, pitch_mm=rect.pitch_mm, image_size=[w, h],
             principal_point_px=[cx, cy])
    out.finish()
    return 0
