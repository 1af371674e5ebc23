"""Benchmark: run reconstruction methods on every benchmark scene found and print one table.

    .venv/bin/python bench/reconstruct.py [--methods baseline entropy] [--runs 3] [--data ../shared/data]

Each run is a fresh process (so peak memory is that run's own) that loads the scene, estimates the
centre view's disparity and scores it against gt_disp_lowres.pfm. One warm-up run per method fills
numba's compilation cache first and is not counted. Wall seconds are the median over the runs, of
the estimation alone (loading is reported separately).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, resource, sys, time
from recon.lf import read_lightfield, read_ground_truth
from recon.evaluate import score
from recon.methods import run_method
method, scene = sys.argv[1], sys.argv[2]
t0 = time.perf_counter()
lf = read_lightfield(scene)
t1 = time.perf_counter()
disparity = run_method(method, lf).disparity
t2 = time.perf_counter()
gt = read_ground_truth(lf)
print(json.dumps({"load_s": t1 - t0, "estimate_s": t2 - t1,
                  "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "scores": score(disparity, gt) if gt is not None else None}))
"""


def scenes(data: Path) -> list[Path]:
    return sorted(p.parent for p in data.glob("**/gt_disp_lowres.pfm") if (p.parent / "input_Cam000.png").is_file())


def run_once(method: str, scene: Path) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, method, str(scene)], cwd=ROOT, capture_output=True,
                         text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"{method} on {scene} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", nargs="+", default=["baseline"])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    args = parser.parse_args()
    found = scenes(args.data)
    if not found:
        raise SystemExit(f"no benchmark scenes (input_Cam000.png + gt_disp_lowres.pfm) under {args.data}")
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")),
               platform.processor()) if Path("/proc/cpuinfo").exists() else platform.processor()
    print(f"machine: {cpu}, {os.cpu_count()} cores; python {platform.python_version()}; median of {args.runs} runs")
    header = f"{'method':<10} {'scene':<12} {'wall s':>7} {'load s':>7} {'peak MiB':>9} {'MSEx100':>8} {'BP0.07':>7} {'BP0.03':>7} {'BP0.01':>7}"
    print(header)
    print("-" * len(header))
    for method in args.methods:
        for scene in found:
            run_once(method, scene)  # warm-up: numba compiles into its cache
            runs = [run_once(method, scene) for _ in range(args.runs)]
            s = runs[-1]["scores"]
            print(f"{method:<10} {scene.name:<12} {statistics.median(r['estimate_s'] for r in runs):7.2f} "
                  f"{statistics.median(r['load_s'] for r in runs):7.2f} {max(r['peak_mib'] for r in runs):9.0f} "
                  f"{s['mse_x100']:8.3f} {s['badpix_0.07']:7.2f} {s['badpix_0.03']:7.2f} {s['badpix_0.01']:7.2f}",
                  flush=True)


if __name__ == "__main__":
    main()
