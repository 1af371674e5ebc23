"""Benchmark: what checking every view's SHA-256 costs when a capture is read.

    .venv/bin/python bench/verify_capture.py [--grid 9] [--width 640] [--height 490] [--repeat 7]

Writes one ``grid x grid`` capture of random-textured RGB views (``width x height``, 8-bit; PNG
compresses noise badly, so the files are about as large as real views get) into a temporary folder,
then reads it with :func:`recon.lf.capture.read_capture` with and without ``verify`` (alternating,
``--repeat`` times each, after one warm-up read of each so the page cache holds the files) and
prints the median and spread of each, the difference, and the hashing alone. Timings on a shared
machine vary with its load: report the load with the figures.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=int, default=9)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=490)
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()

    import numpy as np

    from recon.lf.capture import read_capture, write_lightfield
    from recon.lf.lightfield import LightField

    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (args.height + args.grid, args.width + args.grid, 3), dtype=np.uint8)
    views = np.stack([np.stack([base[u:u + args.height, v:v + args.width] for v in range(args.grid)])
                      for u in range(args.grid)])
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch) / "cap"
        write_lightfield(folder, LightField(views=views, pitch_mm=0.5, focal_px=1000.0))
        files = sorted((folder / "views").glob("*.png"))
        size_mb = sum(f.stat().st_size for f in files) / 1e6
        times: dict[bool, list[float]] = {True: [], False: []}
        for verify in (True, False):
            read_capture(folder, verify=verify)  # warm-up: page cache, thread pool, imports
        for _ in range(args.repeat):
            for verify in (True, False):
                started = time.perf_counter()
                read_capture(folder, verify=verify)
                times[verify].append(time.perf_counter() - started)
        hashing = []
        for _ in range(args.repeat):
            started = time.perf_counter()
            for f in files:
                hashlib.sha256(f.read_bytes()).hexdigest()
            hashing.append(time.perf_counter() - started)

    def show(label: str, values: list[float]) -> str:
        return f"{label:<28} median {statistics.median(values):.3f} s  (min {min(values):.3f}, max {max(values):.3f})"

    print(f"{args.grid}x{args.grid} views of {args.width}x{args.height} RGB, {size_mb:.1f} MB of PNG; "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    print(show("read_capture(verify=True)", times[True]))
    print(show("read_capture(verify=False)", times[False]))
    print(f"{'difference of the medians':<28} {statistics.median(times[True]) - statistics.median(times[False]):+.3f} s")
    print(show("sha256 of all files, 1 thread", hashing))


if __name__ == "__main__":
    main()
