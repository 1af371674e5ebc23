"""Benchmark: peak memory of the matching-entropy estimator, step by step, on one light field.

    .venv/bin/python bench/memory_steps.py FOLDER [--preset paper]

Reads ``FOLDER`` (any light field ``lfrig`` reads, e.g. ``runs/capture-speed/rectified``) as
``lfrig reconstruct`` does (the views as grey, ``read_lightfield(grey=True)``, let go after the
boundary step, ``LightField.views_once``), then
runs the steps of :data:`recon.entropy.plan.PLAN` one by one on the whole image as the plan runs
them (:func:`recon.entropy.plan.run_step`: each followed by the heap's trim) and prints, per
step, the process's resident memory after it and its peak within it (MiB; Linux: the peak,
``VmHWM`` of ``/proc/self/status``, is reset before each step by writing 5 to
``/proc/self/clear_refs``) and the step's wall seconds. Memory figures hold under load; times do
not.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def memory_mib() -> tuple[float, float]:
    """``(resident, peak since the last reset)`` of this process in MiB."""
    values = {}
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(("VmRSS:", "VmHWM:")):
                key, value = line.split(":")
                values[key] = int(value.split()[0]) / 1024
    return values["VmRSS"], values["VmHWM"]


def reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as refs:
        refs.write("5")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path, help="a light field folder")
    parser.add_argument("--preset", help="an options preset of the estimator (default: the defaults)")
    args = parser.parse_args()

    from recon.entropy.options import make_options
    from recon.entropy.plan import PLAN, run_step, start
    from recon.errors import LfrigError
    from recon.lf import read_lightfield

    rows = []

    def row(name: str, seconds: float) -> None:
        rss, peak = memory_mib()
        rows.append((name, rss, peak, seconds))
        print(f"{name:<14} {rss:8.0f} {peak:8.0f} {seconds:8.2f}", flush=True)

    print(f"{'step':<14} {'RSS MiB':>8} {'peak MiB':>8} {'wall s':>8}")
    row("(imports)", 0.0)
    reset_peak()
    t = time.perf_counter()
    try:
        lf = read_lightfield(args.folder, grey=True)
        lf.views_once = True  # as lfrig reconstruct hands them to its one estimate
        options = make_options(None, preset=args.preset)
    except (LfrigError, ValueError) as error:
        parser.exit(2, f"memory_steps.py: error: {error}\n")
    row("read", time.perf_counter() - t)
    reset_peak()
    t = time.perf_counter()
    state = start(lf, options)
    row("start", time.perf_counter() - t)
    for phase in PLAN:
        for step in phase.steps:
            reset_peak()
            t = time.perf_counter()
            run_step(state, step)
            row(step.name, time.perf_counter() - t)
    name, _, peak, _ = max(rows, key=lambda r: r[2])
    print(f"{lf.image_shape[1]}x{lf.image_shape[0]}, {lf.grid_shape[0]}x{lf.grid_shape[1]} views: "
          f"peak {peak:.0f} MiB in {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
