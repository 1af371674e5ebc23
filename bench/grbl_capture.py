"""Benchmark: a full 9x9 capture (`lfrig capture`, fake camera) against the real GRBL 1.1h firmware.

    .venv/bin/python bench/grbl_capture.py [--runs 3] [--binning 8] [--settle-s 0.02] [--slow]

Builds ``../shared/grbl-sim`` into a temporary folder (the firmware is GPL test equipment and is
never copied into the project), runs it on a pseudo-terminal with the test suite's small, fast stage
(``tests/grbl_devices.FAST``: 20 x 20 x 10 mm, 3000 mm/min, 500 mm/s^2) or, with ``--slow``, GRBL's
own default rates and accelerations (500 mm/min, 10 mm/s^2), and times ``lfrig capture`` as a user
runs it (a fresh process: start-up, connect, homing, 81 views, 33 backlash take-up moves) ``--runs``
times, each into a new folder. Prints every run's wall time and the median. Motion is real time, so
the figure is dominated by the stage's moves, the serial round trips and the camera's rendering.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the firmware harness lives with the tests


def main() -> int:
    from grbl_devices import FAST, Firmware, build_firmware

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--binning", type=int, default=8)
    parser.add_argument("--settle-s", type=float, default=0.02)
    parser.add_argument("--slow", action="store_true", help="GRBL's default rates and accelerations")
    args = parser.parse_args()
    settings = dict(FAST)
    if args.slow:
        settings.update({110: 500, 111: 500, 112: 500, 120: 10, 121: 10, 122: 10, 25: 500, 24: 100})
    with tempfile.TemporaryDirectory(prefix="lfrig-grbl-bench-") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        exe = build_firmware(root / "build")
        print(f"built the firmware in {time.perf_counter() - t0:.1f} s")
        device = Firmware(exe, root / "eeprom", settings=settings)
        times = []
        try:
            for run in range(args.runs):
                out = root / f"cap{run}"
                command = [sys.executable, "-m", "rig.main", "capture", str(out), "--stage", device.url,
                           "--centre-mm", "-10", "-10", "-5", "--camera", "fake", "--binning", str(args.binning),
                           "--supersample", "1", "--settle-s", str(args.settle_s), "--quiet"]
                start = time.perf_counter()
                done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
                elapsed = time.perf_counter() - start
                if done.returncode != 0:
                    print(done.stderr, file=sys.stderr)
                    return 1
                times.append(elapsed)
                print(f"run {run + 1}: {elapsed:.1f} s wall ({done.stdout.strip()})")
        finally:
            device.close()
    load = os.getloadavg()
    print(f"81-view capture against GRBL 1.1h ({'default' if args.slow else 'fast test'} stage settings): "
          f"median {statistics.median(times):.1f} s of {len(times)} runs "
          f"[{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {load[0]:.1f}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
