"""Benchmark: a capture with Aravis's simulated GenICam camera on the simulated stage, and `lfrig import`.

    .venv/bin/python bench/capture_import.py [--grid 9] [--size 512] [--runs 3]

1. ``capture``: ``lfrig capture --camera aravis:Fake_1 --stage fake`` of a ``grid x grid`` grid with
   ``size x size`` Mono8 frames (software trigger, fresh-frame rule on). The simulated camera streams
   at 25 Hz whatever the trigger, so a view costs about one frame period plus writing the PNG; the
   stage runs on a virtual clock (no motion time).
2. ``import``: the capture's views written as plain TIFFs (``img_{v:02d}-{u:02d}.tif``) imported back
   with ``lfrig import`` (read, check, write PNGs, journal, atomic rename).

Prints the median and every run's wall time (seconds) and per-view times. Needs Aravis (``./setup.sh``).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=int, default=9)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()

    import cv2

    from recon.lf import read_lightfield
    from rig.main import main as lfrig

    views = args.grid * args.grid
    capture_s, import_s = [], []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for run in range(args.runs):
            cap = root / f"cap{run}"
            started = time.perf_counter()
            status = lfrig(["capture", str(cap), "--camera", "aravis:Fake_1", "--rows", str(args.grid), "--cols",
                            str(args.grid), "--roi", "0", "0", str(args.size), str(args.size), "--quiet"])
            capture_s.append(time.perf_counter() - started)
            if status != 0:
                return status
        lf = read_lightfield(root / "cap0")
        plain = root / "plain"
        plain.mkdir()
        for u in range(args.grid):
            for v in range(args.grid):
                cv2.imwrite(str(plain / f"img_{v:02d}-{u:02d}.tif"), lf.views[u, v])
        for run in range(args.runs):
            started = time.perf_counter()
            status = lfrig(["import", str(plain), "-o", str(root / f"imp{run}"), "--pattern", "img_{v:02d}-{u:02d}.tif",
                            "--rows", str(args.grid), "--cols", str(args.grid), "--pitch-mm", "0.5", "--quiet"])
            import_s.append(time.perf_counter() - started)
            if status != 0:
                return status
    print(f"{platform.node()}: {views} views of {args.size}x{args.size}, {args.runs} runs")
    for name, times in (("capture (aravis:Fake_1, fake stage)", capture_s), ("import (TIFF -> capture)", import_s)):
        median = statistics.median(times)
        print(f"{name}: median {median:.2f} s ({1000 * median / views:.0f} ms/view); runs "
              + ", ".join(f"{t:.2f}" for t in times))
    return 0


if __name__ == "__main__":
    sys.exit(main())
