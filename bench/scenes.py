"""Benchmark on rendered scenes that imitate the HCI scenes not in ../shared (``recon.entropy.scenes``).

    .venv/bin/python bench/scenes.py [--size 192] [--scenes dots bars] [--set joint=false ...]

For every scene: the 7x7 baseline (all views, step 0.02, the scene's known range) against the
matching-entropy estimator with its defaults (``--set name=value`` overrides one option, value as
JSON, e.g. ``--set window_sizes=[3,5,7]``), BadPix 0.07 % / MSE x100 over the image without a
15-px border, overall and per region kind (``recon.entropy.scenes.region_masks``: edge, flat,
slant, plane), and the entropy estimator's own initial (nine-view) estimate. Wall seconds of the
estimation only; numba compiles once before the first scene.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _fmt(s: dict) -> str:
    if s["pixels"] == 0:
        return f"{'-':>12}"
    return f"{s['badpix_0.07']:5.1f}/{s['mse_x100']:6.2f}"


def main() -> None:
    import numpy as np

    from recon.baseline import estimate_baseline
    from recon.entropy import estimate_disparity
    from recon.entropy.scenes import REGION_KINDS, SCENES, make_scene, region_masks
    from recon.evaluate import score

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=192)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE")
    parser.add_argument("--no-baseline", action="store_true")
    parser.add_argument("--json", type=Path, help="also write the scores here")
    args = parser.parse_args()
    overrides = {}
    for item in args.set:
        name, _, value = item.partition("=")
        value = json.loads(value)
        overrides[name] = tuple(value) if isinstance(value, list) else value

    warm = make_scene("bars", size=48)  # compile numba kernels outside the timings
    estimate_disparity(warm.lf, **overrides)

    print(f"size {args.size}x{args.size}, 9x9 views; BadPix0.07 % / MSE x100 (border 15); overrides {overrides}")
    head = (f"{'scene':<9} {'method':<9} {'all':>12} " + " ".join(f"{k:>12}" for k in REGION_KINDS)
            + f" {'wall s':>6}")
    print(head)
    print("-" * len(head))
    record = {}
    totals = {"baseline": [], "initial": [], "entropy": []}
    for name in args.scenes:
        scene = make_scene(name, size=args.size, seed=args.seed)
        masks = region_masks(scene.truth, scene.clean_centre)
        rows = {}
        if not args.no_baseline:
            t = time.perf_counter()
            base = estimate_baseline(scene.lf, window=7, step=0.02).disparity
            rows["baseline"] = (base, time.perf_counter() - t)
        t = time.perf_counter()
        res = estimate_disparity(scene.lf, **overrides)
        wall = time.perf_counter() - t
        rows["initial"] = (res.initial_disparity, float("nan"))
        rows["entropy"] = (res.disparity, wall)
        record[name] = {}
        for method, (disp, secs) in rows.items():
            s_all = score(disp, scene.truth)
            per = {k: score(disp, scene.truth, mask=m) for k, m in masks.items()}
            record[name][method] = {"all": s_all, **per, "wall_s": secs}
            totals[method].append((s_all["badpix_0.07"], s_all["mse_x100"]))
            frac = "" if method != "baseline" else ""
            print(f"{name:<9} {method:<9} {_fmt(s_all):>12} " + " ".join(f"{_fmt(per[k]):>12}" for k in REGION_KINDS)
                  + f" {secs:6.1f}{frac}", flush=True)
        fr = {k: float(np.mean(m[15:-15, 15:-15])) for k, m in masks.items()}
        print(f"{'':<9} {'(share)':<9} {'':>12} " + " ".join(f"{fr[k]:>12.3f}" for k in REGION_KINDS))
    print("-" * len(head))
    for method, vals in totals.items():
        if vals:
            a = np.array(vals)
            print(f"{'mean':<9} {method:<9} {a[:, 0].mean():5.1f}/{a[:, 1].mean():6.2f}")
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
