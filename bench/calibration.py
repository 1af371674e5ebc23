"""Benchmark: lfrig's intrinsics calibration against plain OpenCV's, both scored against the truth.

    .venv/bin/python bench/calibration.py [--cases issue near ...] [--realizations 5] [--ablate]
                                          [--cache DIR] [--json FILE]

Each case renders board images through a known lens with the simulated camera
(``rig/fakecam.py``, ``rig/render.py``: the truth *is* an mrcal camera model; blur, noise, 2x2
supersampling at the board's outline, 8-bit quantisation), then calibrates them twice:

- **lfrig**: ``calib.intrinsics.calibrate_intrinsics_from_images`` (what ``lfrig calibrate
  intrinsics`` runs), lens model ``LENSMODEL_OPENCV8``;
- **OpenCV**: the textbook pipeline, ``findChessboardCorners`` + ``cornerSubPix`` (11x11 window)
  + ``calibrateCamera`` with ``CALIB_RATIONAL_MODEL`` (the same 8 distortion coefficients as
  mrcal's ``LENSMODEL_OPENCV8``, in the same order).

Both results become ``mrcal.cameramodel`` s and are scored the same way against the true model:
``calib.intrinsics.projection_difference`` (``mrcal.projection_diff`` at the middle of the
case's board distances, the implied transformation fitted over the whole imager, best of four
seeded starts), a 40 x 31 grid over the imager; the table gives its median and max in pixels.

``--ablate`` also runs the pieces crossed, to tell the detector from the solve: each detector's
corner error against the true corner positions, and each solver on each detector's corners
(and on the true corners plus nothing, the floor of the model's fit).

Each case's boards are rendered once and saved with ``--realizations`` independent draws of the
noise (default 5); the table gives the median over the draws of each figure, and in brackets the
worst max. Images are cached in ``--cache`` (default ``.cache/bench-calibration``) keyed by every
parameter of the case, so re-runs skip the rendering (about 1-3 s per 1280x980 frame on one core).
Everything is seeded.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PIXEL_UM = 4.8


@dataclass(frozen=True)
class Case:
    """One rendered calibration session: the true lens and the boards."""

    name: str
    focal_px: float = 7000.0
    distortion: tuple[float, ...] = (-0.35, 0.9, 2.0e-4, -1.5e-4, 0.0, 0.0, 0.0, 0.0)
    image_size: tuple[int, int] = (1280, 980)
    inner: tuple[int, int] = (10, 7)          # inner corners (cols, rows): an 11x8-square board
    square_mm: float = 10.0
    distance_mm: tuple[float, float] = (800.0, 1100.0)
    tilt_deg: float = 30.0
    frames: int = 25
    blur_px: float = 0.6
    noise_grey: float = 2.0                   # standard deviation in 8-bit grey levels
    supersample: int = 2
    exposure: float = 1.0                     # brightness scale (0.3: a dim, low-contrast board)
    seed: int = 0
    description: str = ""

    @property
    def working_distance_mm(self) -> float:
        return 0.5 * (self.distance_mm[0] + self.distance_mm[1])

    def key(self) -> str:
        return hashlib.sha256(json.dumps(asdict(self) | {"description": "", "name": ""},
                                         sort_keys=True).encode()).hexdigest()[:16]


CASES = {
    "issue": Case("issue", description="the issue's setup: f 7000 px, OPENCV8 (~3 px barrel in the corners), 0.8-1.1 m"),
    "near": Case("near", square_mm=5.0, distance_mm=(420.0, 600.0), seed=1,
                 description="same lens, 5 mm squares at 0.42-0.6 m"),
    "far": Case("far", square_mm=15.0, distance_mm=(1300.0, 1800.0), tilt_deg=35.0, seed=2,
                description="same lens, 15 mm squares at 1.3-1.8 m"),
    "wide": Case("wide", focal_px=2000.0, distortion=(-0.25, 0.08, 3.0e-4, -2.0e-4, -0.01, 0.0, 0.0, 0.0),
                 square_mm=15.0, distance_mm=(450.0, 750.0), tilt_deg=35.0, seed=3,
                 description="f 2000 px, ~35 px barrel in the corners, 15 mm squares at 0.45-0.75 m"),
    "rational": Case("rational", focal_px=4000.0, distortion=(0.15, -0.6, -3.0e-4, 4.0e-4, 0.3, 0.05, -0.2, 0.4),
                     square_mm=10.0, distance_mm=(550.0, 800.0), seed=4,
                     description="f 4000 px, pincushion with all 8 rational terms, 10 mm squares at 0.55-0.8 m"),
    "small": Case("small", inner=(11, 8), distance_mm=(1500.0, 2400.0), tilt_deg=35.0, seed=6,
                  description="the issue's lens, 11x8 inner corners of 10 mm at 1.5-2.4 m (squares of 29-47 px)"),
    "tiny": Case("tiny", square_mm=3.0, distance_mm=(750.0, 1000.0), seed=9,
                 description="the issue's lens, 3 mm squares at 0.75-1 m (squares of 21-28 px)"),
    "steep": Case("steep", tilt_deg=55.0, seed=7, description="the issue's setup with boards tilted up to 55 deg"),
    "dim": Case("dim", exposure=0.3, seed=8, description="the issue's setup at 30 % exposure (board 2-28 % grey)"),
    "sharp": Case("sharp", blur_px=0.3, noise_grey=1.0, seed=5,
                  description="the issue's lens, less blur (0.3 px) and noise (1 grey level)"),
}


# ----------------------------------------------------------------------------------------------
# Rendering (rig/fakecam.py, rig/render.py) and the truth
# ----------------------------------------------------------------------------------------------

def make_camera(case: Case):
    from rig.fakecam import FakeCamera, FakeRig

    rig = FakeRig(sensor_size_px=case.image_size, pixel_size_um=PIXEL_UM, focal_mm=case.focal_px * PIXEL_UM * 1e-3,
                  lensmodel="LENSMODEL_OPENCV8", distortion=case.distortion, rotation_deg=(0.0, 0.0, 0.0))
    return FakeCamera(rig=rig, colour=False, supersample=case.supersample, blur_px=case.blur_px,
                      noise_sigma=case.noise_grey / 255.0, seed=case.seed, exposure_us=10000.0 * case.exposure)


def render_case(case: Case, cache: Path, *, realizations: int) -> tuple[list[list[Path]], np.ndarray, object]:
    """Render the case's boards once and write ``realizations`` noisy 8-bit copies of each.

    Returns ``(paths, true_corners, true_model)``: ``paths[j][k]`` is board ``k`` with noise
    realization ``j`` (PNG), ``true_corners`` ``(N, rows, cols, 2)`` the true corner pixels (mrcal's
    board layout, first corner at the board's negative ``a``/``b``), and the true mrcal model.
    """
    import cv2

    from rig.fakecam import calibration_poses
    from rig.render import board_corners_world, chessboard_scene

    camera = make_camera(case)
    folder = cache / f"{case.name}-{case.key()}"
    paths = [[folder / f"r{j}" / f"board{k:02d}.png" for k in range(case.frames)] for j in range(realizations)]
    truth_file = folder / "corners.npy"
    if truth_file.exists() and all(p.exists() for row in paths for p in row):
        return paths, np.load(truth_file), camera.model
    poses = calibration_poses(camera, count=case.frames, inner=case.inner, square_mm=case.square_mm,
                              distance_mm=case.distance_mm, tilt_deg=case.tilt_deg, seed=case.seed)
    corners = []
    for k, (centre, rot) in enumerate(poses):
        scene = chessboard_scene(inner=case.inner, square_mm=case.square_mm, centre_mm=centre, rotation_deg=rot)
        frame_camera = camera.with_scene(scene)
        clean = frame_camera.render(camera.rig.ref_mm)
        # FakeCamera.frame adds the seeded noise and quantises; render once, then take fresh noise
        # per realization and frame (every frame is at the same stage position, so the seed varies).
        frame_camera.render = lambda *args, clean=clean, **kwargs: clean
        for j in range(realizations):
            frame_camera.seed = (case.seed * 1000 + j) * 1000 + k
            paths[j][k].parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(paths[j][k]), frame_camera.frame(camera.rig.ref_mm))
        corners.append(camera.project(board_corners_world(scene), camera.rig.ref_mm))
    corners = np.stack(corners)
    np.save(truth_file, corners)
    return paths, corners, camera.model


# ----------------------------------------------------------------------------------------------
# The two pipelines
# ----------------------------------------------------------------------------------------------

def opencv_corners(gray: np.ndarray, inner: tuple[int, int]) -> np.ndarray | None:
    """``(rows, cols, 2)`` corners by ``findChessboardCorners`` + ``cornerSubPix`` (OpenCV's
    calibration tutorial: 11x11 window, 30 iterations or 0.001 px), or ``None``."""
    import cv2

    found, corners = cv2.findChessboardCorners(gray, inner, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)
    return corners.reshape(inner[1], inner[0], 2).astype(float)


def opencv_solve(corners: list[np.ndarray], *, inner: tuple[int, int], square_mm: float,
                 image_size: tuple[int, int]):
    """``calibrateCamera`` with ``CALIB_RATIONAL_MODEL`` on ``(rows, cols, 2)`` corner grids, as an
    mrcal ``LENSMODEL_OPENCV8`` camera model (``(k1, k2, p1, p2, k3, k4, k5, k6)`` in both)."""
    import cv2
    import mrcal

    x, y = np.meshgrid(np.arange(inner[0]) * square_mm, np.arange(inner[1]) * square_mm)
    obj = np.stack([x, y, np.zeros_like(x)], axis=-1).reshape(-1, 3).astype(np.float32)
    rms, K, dist, _, _ = cv2.calibrateCamera([obj] * len(corners),
                                             [c.reshape(-1, 1, 2).astype(np.float32) for c in corners],
                                             tuple(image_size), None, None, flags=cv2.CALIB_RATIONAL_MODEL)
    dist = np.asarray(dist, dtype=float).ravel()[:8]
    intrinsics = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist])
    model = mrcal.cameramodel(intrinsics=("LENSMODEL_OPENCV8", intrinsics), imagersize=np.array(image_size),
                              rt_cam_ref=np.zeros(6))
    return model, float(rms)


def lfrig_solve(corners: list[np.ndarray], *, case: Case):
    """lfrig's solve (``calib.intrinsics.calibrate_intrinsics``) on ``(rows, cols, 2)`` grids."""
    from calib.intrinsics import Board, calibrate_intrinsics

    board = Board(case.inner[0], case.inner[1], case.square_mm)
    obs = np.stack([np.concatenate([c, np.ones(c.shape[:2] + (1,))], axis=-1) for c in corners])
    return calibrate_intrinsics(obs, board=board, image_size=case.image_size,
                                working_distance_mm=case.working_distance_mm).model


def score(model, truth, *, distance_mm: float) -> dict[str, float]:
    """Median and max (px) of the projection difference to the truth over the imager."""
    from calib.intrinsics import projection_difference

    diff = projection_difference(model, truth, distance_mm=distance_mm)
    return {"median_px": float(np.median(diff)), "max_px": float(np.max(diff))}


def match_truth(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The true corners ``(rows, cols, 2)`` in the order of ``found`` (a board's half-turn)."""
    direct = np.linalg.norm(found - truth, axis=-1).mean()
    flipped = np.linalg.norm(found - truth[::-1, ::-1], axis=-1).mean()
    return truth if direct <= flipped else truth[::-1, ::-1]


def corner_error(found: list[np.ndarray | None], truth: np.ndarray) -> dict[str, float]:
    errs = [np.linalg.norm(f - match_truth(f, t), axis=-1).ravel() for f, t in zip(found, truth) if f is not None]
    if not errs:
        return {"rms_px": float("nan"), "max_px": float("nan")}
    e = np.concatenate(errs)
    return {"rms_px": float(np.sqrt(np.mean(e**2))), "max_px": float(e.max())}


def run_once(case: Case, paths: list[Path], truth_corners: np.ndarray, truth, *, ablate: bool) -> dict:
    """Both pipelines on one noise realization of the case's boards."""
    import cv2

    from calib.intrinsics import Board, calibrate_intrinsics_from_images, detect_corners

    board = Board(case.inner[0], case.inner[1], case.square_mm)
    D = case.working_distance_mm
    out: dict = {}
    t0 = time.perf_counter()
    result = calibrate_intrinsics_from_images(paths, board=board, working_distance_mm=D)
    out["lfrig"] = score(result.model, truth, distance_mm=D) | {
        "used": len(result.used), "seconds": time.perf_counter() - t0,
        "uncertainty_median_px": result.uncertainty_px["median"], "rms_px": result.rms_px,
        "outliers": int(len(result.outliers))}
    t0 = time.perf_counter()
    images = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in paths]
    cv_found = [opencv_corners(img, case.inner) for img in images]
    cv_ok = [c for c in cv_found if c is not None]
    cv_model, cv_rms = opencv_solve(cv_ok, inner=case.inner, square_mm=case.square_mm, image_size=case.image_size)
    out["opencv"] = score(cv_model, truth, distance_mm=D) | {"used": len(cv_ok), "seconds": time.perf_counter() - t0,
                                                              "rms_px": cv_rms}
    if ablate:
        lf_found = []
        for img in images:
            c = detect_corners(img, board)
            lf_found.append(None if c is None else c[..., :2])
        lf_ok = [c for c in lf_found if c is not None]
        sq = dict(inner=case.inner, square_mm=case.square_mm, image_size=case.image_size)
        out["ablation"] = {
            "corners_lfrig": corner_error(lf_found, truth_corners) | {"found": len(lf_ok)},
            "corners_opencv": corner_error(cv_found, truth_corners) | {"found": len(cv_ok)},
            "mrcal_on_opencv_corners": score(lfrig_solve(cv_ok, case=case), truth, distance_mm=D),
            "opencv_on_lfrig_corners": score(opencv_solve(lf_ok, **sq)[0], truth, distance_mm=D),
            "mrcal_on_true_corners": score(lfrig_solve(list(truth_corners), case=case), truth, distance_mm=D),
            "opencv_on_true_corners": score(opencv_solve(list(truth_corners), **sq)[0], truth, distance_mm=D),
        }
    return out


def run_case(case: Case, *, cache: Path, realizations: int, ablate: bool) -> dict:
    """Every realization of a case, and the medians over them."""
    t0 = time.perf_counter()
    paths, truth_corners, truth = render_case(case, cache, realizations=realizations)
    runs = [run_once(case, row, truth_corners, truth, ablate=ablate) for row in paths]
    summary = {}
    for who in ("lfrig", "opencv"):
        summary[who] = {key: float(np.median([r[who][key] for r in runs])) for key in runs[0][who] if key != "used"}
        summary[who]["used_min"] = int(min(r[who]["used"] for r in runs))
        summary[who]["worst_max_px"] = float(max(r[who]["max_px"] for r in runs))
    if ablate:
        summary["ablation"] = {k: {kk: float(np.median([r["ablation"][k][kk] for r in runs])) for kk in v}
                               for k, v in runs[0]["ablation"].items()}
    return {"case": case.name, "description": case.description, "case_parameters": asdict(case),
            "seconds": time.perf_counter() - t0, "summary": summary, "runs": runs}


def machine() -> str:
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover
        load = float("nan")
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {load:.1f}, Python {platform.python_version()}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--realizations", type=int, default=5, help="noise realizations per case (default 5)")
    parser.add_argument("--ablate", action="store_true", help="also cross detectors and solvers")
    parser.add_argument("--cache", default=str(ROOT / ".cache" / "bench-calibration"),
                        help="folder for the rendered images")
    parser.add_argument("--json", help="write every figure to this file")
    args = parser.parse_args(argv)
    rows = []
    print(f"# {machine()}; medians over {args.realizations} noise realizations (worst max in brackets)")
    print("| case | lfrig median / max px | OpenCV median / max px | boards used lfrig / OpenCV "
          "| lfrig uncertainty median px |")
    print("|---|---|---|---|---|")
    for name in args.cases:
        case = CASES[name]
        r = run_case(case, cache=Path(args.cache), realizations=args.realizations, ablate=args.ablate)
        rows.append(r)
        lf, cv = r["summary"]["lfrig"], r["summary"]["opencv"]
        print(f"| {name} | {lf['median_px']:.3f} / {lf['max_px']:.3f} ({lf['worst_max_px']:.3f}) | "
              f"{cv['median_px']:.3f} / {cv['max_px']:.3f} ({cv['worst_max_px']:.3f}) | "
              f"{lf['used_min']} / {cv['used_min']} of {case.frames} | {lf['uncertainty_median_px']:.3f} |", flush=True)
        if args.ablate:
            for k, v in r["summary"]["ablation"].items():
                print(f"|   {k} | " + ", ".join(f"{kk} {vv:.4f}" for kk, vv in v.items()) + " ||||", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine(), "cases": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
