"""``lfrig demo``: a whole lab session, simulated, from calibration to PLY and a report.

The simulated rig is the paper's (1280x980 detector binned 2x2 to 640x490, 35 mm lens, 9x9 grid at
0.5 mm, objects 0.9-1.0 m away) with the imperfections of a real one: lens distortion, stage axes
rotated and skewed against the camera, a pitch error. Every step runs the code a lab runs, on the
simulated stage (GRBL's wire protocol on a virtual clock) and camera:

1. ``boards/``: pictures of a chessboard in many poses -> ``camera.cameramodel`` (mrcal);
2. ``stage_capture/``: a 9x9 capture of a board -> ``stage.json`` (one rotation, two step vectors);
3. ``capture/``: the 9x9 capture of the scene;
4. ``rectified/``: the capture undistorted and rectified with one map;
5. ``result/``: disparity by the matching-entropy method, depth, PLY mesh and point cloud;
6. ``report/index.html``: the figures and scores against the simulated scene's truth.

``summary.json`` holds every number the session reports. The folder is made afresh on each run.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    import numpy as np

from rig.devices import FAKE_BINNING

MARKER = "summary.json"

#: Boards: intrinsics board 10x7 squares of 8 mm (inner corners 9x6), stage board 11x8 of 10 mm.
INTRINSICS_BOARD = (9, 6, 8.0)
STAGE_BOARD = (10, 7, 10.0)
#: Coarsest detector binning at which the boards still fit the image; fewest board pictures mrcal needs.
MAX_BINNING = 4
MIN_BOARDS = 3


def register(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser(
        "demo",
        help="run a whole simulated lab session: calibrate, capture, rectify, reconstruct, export, report",
        description=__doc__.split("\n\n")[0] + " " + __doc__.split("\n\n")[1],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    from recon.cliargs import add_json_argument, float_range, int_range, output_folder
    from recon.methods import METHODS

    demo.add_argument("-o", "--output", type=output_folder, default=Path("runs/demo"), metavar="DIR",
                      help="folder for everything the session writes (made afresh)")
    demo.add_argument("--binning", type=int_range(1, MAX_BINNING), default=FAKE_BINNING,
                      help="detector binning (1 = full 1280x980; slower)")
    demo.add_argument("--boards", type=int_range(MIN_BOARDS, 200), default=12, help="board pictures for the intrinsics")
    demo.add_argument("--noise", type=float_range(0.0, 0.5), default=0.002, help="camera noise, standard deviation in full scale")
    demo.add_argument("--method", choices=list(METHODS), default="entropy", help="reconstruction method (see lfrig reconstruct --help)")
    demo.add_argument("--quiet", action="store_true", help="no progress bars")
    add_json_argument(demo)
    demo.set_defaults(handler=_demo)


@dataclass
class Steps:
    """Prints one line per step with its time (on ``stream``, default stdout), and keeps the times for
    the summary."""

    name: str = ""
    started: float = 0.0
    times: dict[str, float] = field(default_factory=dict)
    stream: TextIO | None = None

    def begin(self, name: str, text: str) -> None:
        self.name = name
        self.started = time.perf_counter()
        print(f"[{len(self.times) + 1}/6] {text}", file=self.stream or sys.stdout, flush=True)

    def end(self, text: str) -> None:
        seconds = time.perf_counter() - self.started
        self.times[self.name] = round(seconds, 2)
        print(f"      {text} ({seconds:.1f} s)", file=self.stream or sys.stdout, flush=True)


def _prepare(folder: Path) -> None:
    """Make ``folder`` empty: remove an earlier demo's output, refuse to touch anything else."""
    from recon.errors import LfrigError

    if folder.exists():
        if not folder.is_dir():
            raise LfrigError(f"{folder}: exists and is not a folder; pass another -o")
        if any(folder.iterdir()) and not (folder / MARKER).is_file():
            raise LfrigError(f"{folder}: folder is not empty and was not written by lfrig demo; pass another -o")
        shutil.rmtree(folder)
    folder.mkdir(parents=True)


def _demo(args: argparse.Namespace) -> int:
    from recon.cliargs import CommandReport

    summary = run_demo(args.output, binning=args.binning, boards=args.boards, noise=args.noise,
                       method=args.method, quiet=args.quiet, step_stream=sys.stderr if args.json else None)
    d = summary["depth_error"]["textured"]
    c = summary["exported_cloud"]
    out = CommandReport(as_json=args.json)
    out.line(f"\nmedian depth error on textured surfaces: {d['median_abs_rel_pct']:.3f} % of the distance "
             f"({d['within_pct']:.1f} % of pixels within 0.5 %)\n"
             f"exported cloud: {c['kept_pct']:.1f} % of pixels kept, mean depth error {c['mean_abs_rel_pct']:.3f} %, "
             f"{c['points_outside_range_5pct']} points outside the true depth range +-5 %\n"
             f"report: {summary['report']}\n"
             f"PLY:    {summary['ply']['mesh']['path']}\n"
             f"        {summary['ply']['points']['path']}", **summary)  # summary.json's content
    out.finish()
    return 0


def run_demo(folder: Path, *, binning: int = FAKE_BINNING, boards: int = 12, noise: float = 0.002, method: str = "entropy",
             quiet: bool = False, step_stream: TextIO | None = None) -> dict[str, Any]:
    """Run the simulated session into ``folder``; returns (and writes) the summary. The step lines go to
    ``step_stream`` (default stdout), the progress bars to stderr."""
    import numpy as np

    from calib.intrinsics import Board, calibrate_intrinsics_from_images, write_residual_picture
    from calib.rectify import rectify_capture
    from calib.stage import calibrate_stage_from_capture
    from recon.camera import Camera
    from recon.depth import depth_error_scores, write_depth
    from recon.entropy.labels import TEXTURE
    from recon.evaluate import score
    from recon.export import MIN_CONFIDENCE, export_result, trusted_pixels
    from recon.lf.imageio import atomic_output, read_image, write_bytes_atomic, write_png
    from recon.lf.pfm import read_pfm, write_pfm
    from recon.pipeline import reconstruct_to_folder
    from recon.progress import Progress
    from recon.report import write_report
    from recon.report.model import read_ply
    from recon.result import CENTRE_VIEW_PNG, DISPARITY_PFM, REGIONS_NPY, WINDOW_SIZE_NPY, read_result
    from rig.fakecam import FakeCamera, FakeRig, calibration_poses
    from rig.render import chessboard_scene, default_scene

    from recon.errors import LfrigError
    from recon.methods import METHODS

    if isinstance(binning, bool) or not isinstance(binning, int) or not 1 <= binning <= MAX_BINNING:
        raise LfrigError(f"binning = {binning!r}: give an integer from 1 to {MAX_BINNING}")
    if isinstance(boards, bool) or not isinstance(boards, int) or boards < MIN_BOARDS:
        raise LfrigError(f"boards = {boards!r}: mrcal needs at least {MIN_BOARDS} board pictures")
    if not (isinstance(noise, (int, float)) and 0 <= noise <= 0.5):
        raise LfrigError(f"noise = {noise!r}: give a standard deviation from 0 to 0.5 of full scale")
    if method not in METHODS:
        raise LfrigError(f"method = {method!r}: choose one of {', '.join(METHODS)}")
    folder = Path(folder)
    _prepare(folder)
    steps = Steps(stream=step_stream)
    centre_mm = _fake_centre_mm()
    rig = FakeRig.misaligned(ref_mm=centre_mm)
    summary: dict[str, Any] = {"folder": str(folder.resolve()), "rig": _rig_summary(rig, binning)}
    camera_options = dict(rig=rig, binning=binning, noise_sigma=noise)

    # 1. Intrinsics from board pictures.
    steps.begin("intrinsics", f"calibrating the camera from {boards} board pictures (mrcal)")
    board = Board(*INTRINSICS_BOARD)
    still = FakeCamera(rig=rig, binning=binning, noise_sigma=noise, colour=False, supersample=1)
    (folder / "boards").mkdir()
    paths = []
    poses = calibration_poses(still, count=boards, inner=(board.cols, board.rows), square_mm=board.square_mm,
                              distance_mm=(650.0, 1050.0), tilt_deg=30.0, seed=1)
    with Progress("rendering boards", quiet=quiet) as bar:
        for i, (centre, rotation) in enumerate(poses):
            scene = chessboard_scene(inner=(board.cols, board.rows), square_mm=board.square_mm,
                                     centre_mm=centre, rotation_deg=rotation)
            path = folder / "boards" / f"board{i:02d}.png"
            write_png(path, still.frame(rig.ref_mm, scene=scene))
            paths.append(path)
            bar((i + 1) / len(poses), path.name)
    with Progress("finding corners", quiet=quiet) as bar:
        intrinsics = calibrate_intrinsics_from_images(paths, board=board, working_distance_mm=950.0, progress=bar)
    with atomic_output(folder / "camera.cameramodel", what="camera model") as tmp:
        intrinsics.model.write(str(tmp), note="lfrig demo\n" + intrinsics.report())
    with atomic_output(folder / "camera.residuals.png", what="residual picture") as tmp:
        write_residual_picture(intrinsics, tmp)
    summary["intrinsics"] = _intrinsics_summary(intrinsics, still)
    steps.end(f"RMS reprojection error {summary['intrinsics']['rms_px']:.3f} px; against the truth: projection "
              f"{summary['intrinsics']['truth_error_px']:.3f} px RMS, focal {summary['intrinsics']['focal_error_pct']:+.3f} %")

    # 2. Stage geometry from a capture of a board.
    steps.begin("stage", "calibrating the stage from a 9x9 capture of a board")
    stage_board = Board(*STAGE_BOARD)
    board_scene = chessboard_scene(inner=(stage_board.cols, stage_board.rows), square_mm=stage_board.square_mm,
                                   centre_mm=(0.0, 0.0, 950.0))
    _capture(folder / "stage_capture", camera_options | {"scene": board_scene, "colour": False, "supersample": 1},
             centre_mm, quiet)
    with Progress("finding corners", quiet=quiet) as bar:
        stage, _ = calibrate_stage_from_capture(folder / "stage_capture", model=intrinsics.model, board=stage_board,
                                                progress=bar)
    stage.save(folder / "stage.json")
    summary["stage"] = _stage_summary(stage, rig)
    st = summary["stage"]
    steps.end(f"steps {st['pitch_u_mm']:.5f} / {st['pitch_v_mm']:.5f} mm (true {st['true_pitch_u_mm']:.5f} / "
              f"{st['true_pitch_v_mm']:.5f}), skew {st['skew_deg']:.3f} deg, residual {st['rms_px']:.3f} px RMS")

    # 3. The scene.
    steps.begin("capture", "capturing the scene: 81 views on the simulated GRBL stage")
    scene_camera = _capture(folder / "capture", camera_options | {"scene": default_scene()}, centre_mm, quiet)
    steps.end(f"{folder / 'capture'}")

    # 4. Rectification.
    steps.begin("rectify", "undistorting and rectifying the 81 views with one map")
    with Progress("rectify", quiet=quiet) as bar:
        rect = rectify_capture(folder / "capture", folder / "rectified", model_path=folder / "camera.cameramodel",
                               stage_path=folder / "stage.json", progress=bar)
    summary["rectification"] = {"focal_px": rect.focal_px, "pitch_mm": rect.pitch_mm,
                                "image_size": list(rect.image_size)}
    steps.end(f"focal {rect.focal_px:.1f} px, step {rect.pitch_mm:.5f} mm")

    # 5. Disparity, depth, PLY.
    steps.begin("reconstruct", f"estimating disparity ({method}), depth and 3D models")
    result_dir = folder / "result"
    with Progress(method, quiet=quiet) as bar:
        done = reconstruct_to_folder(folder / "rectified", result_dir, method=method, progress=bar)
    disparity = read_pfm(result_dir / DISPARITY_PFM)
    camera = Camera(focal_px=rect.focal_px, pitch_mm=rect.pitch_mm)
    depth = camera.depth_mm(disparity)
    for suffix in ("pfm", "png", "npy"):
        write_depth(result_dir / f"depth.{suffix}", depth)
    ply = {kind: export_result(result_dir, folder / f"model_{kind}.ply", kind=kind).as_dict()
           for kind in ("mesh", "points")}
    summary["ply"] = ply
    summary["method"] = {"name": method, "seconds": done.record.seconds}
    steps.end(f"{ply['mesh']['points']} vertices, {ply['mesh']['triangles']} triangles; "
              f"{ply['points']['points']} points")

    # 6. Truth, scores, report.
    steps.begin("report", "scoring against the simulated scene's truth and writing the report")
    truth_depth = scene_camera.depth_in_rectified(rect.K_rect, rect.R_rect_cam, rect.image_size, centre_mm)
    write_pfm(folder / "result" / "truth_depth.pfm", truth_depth.astype(np.float32))
    labels = _load_optional(result_dir / REGIONS_NPY)
    textured = labels == TEXTURE if labels is not None else None
    summary["depth_error"] = {
        "all": depth_error_scores(depth, truth_depth, border_px=15),
        "textured": depth_error_scores(depth, truth_depth, mask=textured, border_px=15),
    }
    truth_disparity = camera.disparity_px(truth_depth)
    summary["disparity_scores"] = score(disparity, truth_disparity.astype(np.float32))
    folder_result = read_result(result_dir)
    summary["exported_cloud"] = exported_cloud_scores(depth, truth_depth, trusted_pixels(
        disparity, confidence=folder_result.confidence, search_range=folder_result.search_range))
    report = write_report(
        folder / "report", centre_view=read_image(result_dir / CENTRE_VIEW_PNG), disparity_px=disparity,
        title="lfrig demo: simulated lab session", subtitle=str(folder / "rectified"),
        truth_depth_mm=truth_depth, camera=camera,
        region_map=labels, window_size_px=_load_optional(result_dir / WINDOW_SIZE_NPY),
        confidence=folder_result.confidence,
        min_confidence=MIN_CONFIDENCE if folder_result.confidence is not None else None,
        scores=summary["disparity_scores"], info={"steps (s)": steps.times},
        model=read_ply(folder / "model_mesh.ply"),
        provenance=getattr(folder_result.record, "provenance", None) or folder_result.record.extra.get("provenance"),
    )
    summary["report"] = str(report)
    steps.end(f"median depth error {summary['depth_error']['all']['median_abs_rel_pct']:.3f} % (all pixels)")

    summary["seconds"] = steps.times
    write_bytes_atomic(folder / MARKER, (json.dumps(summary, indent=2, default=str) + "\n").encode("utf-8"))
    return summary


def exported_cloud_scores(depth_mm: np.ndarray, truth_depth_mm: np.ndarray, kept: np.ndarray) -> dict[str, Any]:
    """How the exported cloud (the ``kept`` pixels, as ``lfrig export`` chooses them) compares with the
    truth: the share of pixels kept, the points outside the true depth range widened by 5 %, and the
    mean and largest absolute depth error relative to the truth over the kept pixels."""
    import numpy as np

    truth = np.asarray(truth_depth_mm, np.float64)
    depth = np.asarray(depth_mm, np.float64)
    kept = np.asarray(kept, bool) & np.isfinite(depth) & (depth > 0)
    scored = kept & np.isfinite(truth) & (truth > 0)
    low, high = float(np.nanmin(truth)), float(np.nanmax(truth))
    outside = kept & ((depth < 0.95 * low) | (depth > 1.05 * high))
    rel = np.abs(depth[scored] - truth[scored]) / truth[scored]
    return {"kept_pct": 100.0 * float(kept.mean()), "points": int(kept.sum()),
            "truth_range_mm": [low, high], "points_outside_range_5pct": int(outside.sum()),
            "depth_range_mm": [float(depth[kept].min()), float(depth[kept].max())] if kept.any() else None,
            "mean_abs_rel_pct": 100.0 * float(rel.mean()) if rel.size else None,
            "max_abs_rel_pct": 100.0 * float(rel.max()) if rel.size else None}


def _fake_centre_mm() -> tuple[float, float, float]:
    from rig.devices import FAKE_CENTRE_MM

    return tuple(float(c) for c in FAKE_CENTRE_MM)


def _capture(path: Path, camera_options: dict[str, Any], centre_mm: tuple[float, float, float], quiet: bool) -> Any:
    """A 9x9 capture at 0.5 mm with the simulated GRBL stage and camera, through the real session."""
    from recon.progress import Progress
    from rig.devices import open_stage
    from rig.fakecam import FakeCamera
    from rig.grid import GridSpec
    from rig.session import run_capture

    devices = open_stage("fake")
    try:
        camera = FakeCamera(devices.controller.physical_position, is_moving=devices.controller.is_moving,
                            **camera_options)
        grid = GridSpec(rows=9, cols=9, pitch_mm=0.5, centre_mm=centre_mm)
        with Progress("capture", quiet=quiet) as bar:
            result = run_capture(path, stage=devices.stage, camera=camera, grid=grid, clock=devices.clock,
                                 progress=bar, handle_sigint=False,
                                 camera_request={"device": "fake", "binning": camera.binning})
        if not result.complete:
            from rig.errors import RigError

            raise RigError(f"{path}: the simulated capture stopped early")
        return camera
    finally:
        devices.close()


def _load_optional(path: Path) -> np.ndarray | None:
    import numpy as np

    return np.load(path) if path.is_file() else None


def _rig_summary(rig: Any, binning: int) -> dict[str, Any]:
    return {"sensor_px": list(rig.sensor_size_px), "binning": binning, "centre_mm": list(rig.ref_mm), "focal_mm": rig.focal_mm,
            "pixel_um": rig.pixel_size_um, "rotation_deg": list(rig.rotation_deg),
            "scale_error": list(rig.scale_error), "skew_deg": rig.skew_deg, "lensmodel": rig.lensmodel}


def _intrinsics_summary(result: Any, camera: Any) -> dict[str, Any]:
    """RMS, and how far the recovered model projects from the true one over the imager at the
    working distance (up to the camera frame's orientation, which no calibration can see)."""
    import numpy as np

    from calib.intrinsics import projection_difference

    diff = projection_difference(result.model, camera.model, distance_mm=950.0, gridn_width=32)
    fx, fy = result.model.intrinsics()[1][:2]
    return {"rms_px": float(result.rms_px), "truth_error_px": float(np.sqrt(np.mean(diff**2))),
            "focal_error_pct": float(100 * (np.sqrt(fx * fy) / camera.focal_px - 1)),
            "uncertainty_px": result.uncertainty_px}


def _stage_summary(stage: Any, rig: Any) -> dict[str, Any]:
    """Recovered step lengths against the true ones (grid columns move stage x, rows stage y)."""
    import numpy as np

    true_v, true_u = (float(np.linalg.norm(rig.stage_matrix[:, i])) * stage.pitch_mm for i in (0, 1))
    return {"pitch_u_mm": stage.pitch_u_mm, "pitch_v_mm": stage.pitch_v_mm, "true_pitch_u_mm": true_u,
            "true_pitch_v_mm": true_v, "skew_deg": stage.skew_deg, "true_skew_deg": rig.skew_deg,
            "pitch_error_pct": 100 * max(abs(stage.pitch_u_mm / true_u - 1), abs(stage.pitch_v_mm / true_v - 1)),
            "rms_px": float(stage.rms_px)}
