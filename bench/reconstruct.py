"""Benchmark: every scene under ../shared/data and lfrig's rendered suite, every method, one table.

    .venv/bin/python bench/reconstruct.py [--methods baseline entropy entropy:paper] [--runs 3]
        [--data ../shared/data] [--suite dots pyramids ...] [--suite-size 192] [--scenes NAME ...]
        [--threads 2] [--set name=value ...] [--json out.json]

Scenes: every folder under ``--data`` with ``input_Cam000.png`` and ``gt_disp_lowres.pfm``
(backgammon, the four blender-dev scenes) and the scenes of ``recon.entropy.scenes`` (named
``suite/NAME``, rendered at ``--suite-size``, exact truth). Methods: ``baseline`` (7x7 SAD),
``entropy`` (defaults) and ``entropy:PRESET`` (a key of ``recon.entropy.estimate.PRESETS``, e.g.
``entropy:paper``, the paper's literal configuration); ``--set`` overrides entropy options
(value as JSON).

Each run is a fresh process (so peak memory is that run's own: loading or rendering the scene
included, as a user would see it) that estimates the centre view's disparity and scores it
(BadPix0.07 % / MSE x100, 15-px border, a non-finite estimate counts as wrong) and, for a method
with a confidence map, how well it works as a probability of being right (``ECE``: expected
calibration error over 10 equal bins; ``BP>=.5``: BadPix0.07 % of the pixels at confidence >= 0.5;
``kept ok``: the share of the scene's right pixels among them). One warm-up run
per method fills numba's compilation cache first and is not counted. Wall seconds are the median
over the runs of the estimation alone. Runs of one scene alternate between methods (A/B/A/B...)
so that the load other users put on the machine touches every method alike.
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
spec, method, scene, size, overrides = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), json.loads(sys.argv[5])
from recon.evaluate import score
from recon.methods import run_method
t0 = time.perf_counter()
if scene.startswith("suite/"):
    from recon.entropy.scenes import make_scene
    rendered = make_scene(scene.split("/", 1)[1], size=size)
    lf, gt = rendered.lf, rendered.truth
else:
    from recon.lf import read_lightfield, read_ground_truth
    lf = read_lightfield(scene)
    gt = read_ground_truth(lf)
t1 = time.perf_counter()
options = {}
if method.startswith("entropy"):
    options = dict(overrides)
    if ":" in method:
        options["preset"] = method.split(":", 1)[1]
result = run_method(method.split(":", 1)[0], lf, **options)
disparity = result.disparity
t2 = time.perf_counter()
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
calibration = None
confidence = getattr(result.extras, "confidence", None)
if confidence is not None:
    import numpy as np
    from recon.entropy.calibration import TOLERANCE_PX, calibration_scores
    inner = (slice(15, -15), slice(15, -15))
    calibration = calibration_scores(confidence[inner], (np.abs(disparity - gt) <= TOLERANCE_PX)[inner])
print(json.dumps({"load_s": t1 - t0, "estimate_s": t2 - t1, "peak_mib": peak,
                  "scores": score(disparity, gt), "calibration": calibration}))
"""


def data_scenes(data: Path) -> list[str]:
    return [str(p.parent) for p in sorted(data.glob("**/gt_disp_lowres.pfm"))
            if (p.parent / "input_Cam000.png").is_file()]


def run_once(method: str, scene: str, *, size: int, overrides: dict, threads: int) -> dict:
    env = dict(os.environ, NUMBA_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads))
    out = subprocess.run([sys.executable, "-c", CHILD, "run", method, scene, str(size), json.dumps(overrides)],
                         cwd=ROOT, capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise SystemExit(f"{method} on {scene} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    from recon.entropy.scenes import SCENES

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", nargs="+", default=["baseline", "entropy", "entropy:paper"])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--suite", nargs="*", default=list(SCENES), help="suite scenes (none: --suite)")
    parser.add_argument("--suite-size", type=int, default=192)
    parser.add_argument("--scenes", nargs="*", help="only scenes whose name contains one of these")
    parser.add_argument("--threads", type=int, default=2, help="numba threads per run (default 2)")
    parser.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE")
    parser.add_argument("--json", type=Path, help="also write every run's numbers here")
    args = parser.parse_args()
    overrides = {}
    for item in args.set:
        name, _, value = item.partition("=")
        overrides[name] = json.loads(value)
    found = data_scenes(args.data) + [f"suite/{name}" for name in args.suite]
    if args.scenes:
        found = [s for s in found if any(k in s for k in args.scenes)]
    if not found:
        raise SystemExit(f"no scenes: nothing under {args.data} has input_Cam000.png + gt_disp_lowres.pfm, "
                         "and no suite scene was chosen")
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")),
               platform.processor()) if Path("/proc/cpuinfo").exists() else platform.processor()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"machine: {cpu}, {os.cpu_count()} cores, load {load:.1f} at start; python {platform.python_version()}; "
          f"{args.threads} threads; median of {args.runs} runs; overrides {overrides}")
    header = (f"{'scene':<22} {'method':<14} {'BP0.07':>7} {'MSEx100':>8} {'wall s':>7} {'peak MiB':>9} "
              f"{'BP0.03':>7} {'BP0.01':>7} {'ECE':>6} {'BP>=.5':>7} {'kept ok':>7}")
    print(header)
    print("-" * len(header))
    kw = {"size": args.suite_size, "overrides": overrides, "threads": args.threads}
    for method in args.methods:  # warm-up: numba compiles into its cache
        run_once(method, "suite/bars", **{**kw, "size": 48})
    record = []
    for scene in found:
        runs: dict[str, list[dict]] = {m: [] for m in args.methods}
        for _ in range(args.runs):
            for method in args.methods:
                runs[method].append(run_once(method, scene, **kw))
        name = scene if scene.startswith("suite/") else Path(scene).name
        for method in args.methods:
            rs = runs[method]
            s = rs[-1]["scores"]
            wall = statistics.median(r["estimate_s"] for r in rs)
            peak = max(r["peak_mib"] for r in rs)
            c = rs[-1].get("calibration")
            record.append({"scene": name, "method": method, "wall_s": wall, "peak_mib": peak, "scores": s,
                           "walls_s": [r["estimate_s"] for r in rs], "calibration": c})
            cal = "" if c is None else f" {c['ece']:6.3f} {c['bad_kept']:7.2f} {c['right_kept']:7.3f}"
            print(f"{name:<22} {method:<14} {s['badpix_0.07']:7.2f} {s['mse_x100']:8.3f} {wall:7.2f} {peak:9.0f} "
                  f"{s['badpix_0.03']:7.2f} {s['badpix_0.01']:7.2f}{cal}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
