"""Benchmark: a full-size 9x9 capture (1280x980 detector, binning 1) through lfrig's real path.

    .venv/bin/python bench/capture_speed.py [--work DIR] [--methods entropy baseline] [--runs 3]
        [--threads 2] [--remake]

The capture is the one ``lfrig demo --binning 1`` makes (``rig/demo.py``: the simulated rig and
scene, board calibration with mrcal, the 81 views on the simulated stage, undistorted and rectified
with one map), made once into ``--work`` (default ``runs/capture-speed``, kept between runs; the
demo's own reconstruction there uses the quick baseline) and reused. Each run is a fresh process,
as in ``bench/reconstruct.py``: it reads ``rectified/``, estimates the centre view's disparity and
prints the estimate's wall seconds (median over the runs; one warm-up run first fills numba's
cache), its CPU seconds (user + sys of the process during the estimate, a proxy that the load
other users put on the machine inflates less than wall time), the peak RSS of the whole process
(reading included) and the scores against the simulated scene's truth (BadPix 0.07 % / MSE x100,
15-px border).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, resource, sys, time
import numpy as np
folder, method = sys.argv[1], sys.argv[2]
from recon.evaluate import score
from recon.lf import read_lightfield
from recon.lf.pfm import read_pfm
from recon.methods import run_method
from recon.camera import Camera
lf = read_lightfield(folder + "/rectified")
summary = json.load(open(folder + "/summary.json"))
camera = Camera(focal_px=summary["rectification"]["focal_px"], pitch_mm=summary["rectification"]["pitch_mm"])
truth = camera.disparity_px(read_pfm(folder + "/result/truth_depth.pfm")).astype(np.float32)
r0 = resource.getrusage(resource.RUSAGE_SELF)
t0 = time.perf_counter()
disparity = run_method(method, lf).disparity
t1 = time.perf_counter()
r1 = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"estimate_s": t1 - t0,
                  "cpu_s": (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime),
                  "peak_mib": r1.ru_maxrss / 1024, "size": list(disparity.shape),
                  "scores": score(disparity, truth)}))
"""


def make_capture(work: Path) -> None:
    """The demo's session at binning 1 into ``work`` (its reconstruction with the baseline)."""
    from rig.demo import run_demo

    print(f"making the 1280x980 capture in {work} (once; the simulated session takes a few minutes)",
          flush=True)
    run_demo(work, binning=1, method="baseline", quiet=True)


def run_once(work: Path, method: str, threads: int) -> dict:
    env = dict(os.environ, NUMBA_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads))
    out = subprocess.run([sys.executable, "-c", CHILD, str(work), method], cwd=ROOT,
                         capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise SystemExit(f"{method} on {work / 'rectified'} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=ROOT / "runs" / "capture-speed",
                        help="folder of the capture (made by the simulated session when missing)")
    parser.add_argument("--methods", nargs="+", default=["entropy"])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2, help="numba threads per run (default 2)")
    parser.add_argument("--remake", action="store_true", help="make the capture afresh")
    args = parser.parse_args()
    if args.runs < 1:
        raise SystemExit(f"--runs {args.runs}: give at least 1")
    work = args.work.resolve()
    if args.remake or not (work / "summary.json").is_file():
        make_capture(work)
    load = os.getloadavg()[0]
    print(f"{work / 'rectified'}; {args.threads} threads; median of {args.runs} runs; load {load:.1f} at start")
    print(f"{'method':<10} {'size':>9} {'wall s':>7} {'cpu s':>7} {'peak MiB':>9} {'BP0.07':>7} {'MSEx100':>8}")
    for method in args.methods:
        run_once(work, method, args.threads)  # warm-up: numba compiles into its cache
        runs = [run_once(work, method, args.threads) for _ in range(args.runs)]
        s = runs[-1]["scores"]
        h, w = runs[-1]["size"]
        print(f"{method:<10} {f'{w}x{h}':>9} {statistics.median(r['estimate_s'] for r in runs):7.2f} "
              f"{statistics.median(r['cpu_s'] for r in runs):7.2f} {max(r['peak_mib'] for r in runs):9.0f} "
              f"{s['badpix_0.07']:7.2f} {s['mse_x100']:8.3f}", flush=True)


if __name__ == "__main__":
    main()
