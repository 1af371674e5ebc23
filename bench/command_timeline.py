"""Benchmark: when each part of ``lfrig reconstruct`` begins and ends in a fresh process.

    .venv/bin/python bench/command_timeline.py [FOLDER] [--runs 3] [-- EXTRA LFRIG FLAGS ...]

    e.g.  .venv/bin/python bench/command_timeline.py -- --method baseline

Runs ``lfrig reconstruct FOLDER -o OUT --quiet`` (default FOLDER: backgammon in ``../shared``) in a
fresh interpreter per run, with the entry points of its parts timed from the interpreter's first
line (seconds): the imports, the reading of the views, the method's warm-up (its thread started,
and ready: :class:`recon.methods.Warming`), the estimate and the writing of the result folder, up to
the end of ``main``. The estimate cannot begin before both the views are read and the warm-up is
ready; which of the two ends later is the command's critical path before the estimate (the warm-up
holds numba's start-up, which shares the interpreter's lock with the decoding). Prints the median
of each mark over ``--runs`` runs, and the child's whole wall time measured from outside. The timing
wraps the functions; it changes no result.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BACKGAMMON = ROOT.parent / "shared" / "data" / "hci" / "stratified" / "backgammon"

#: The child: the marks of one ``lfrig reconstruct`` run, as JSON on its last line of stderr.
CHILD = r"""
import json, sys, threading, time
T0 = time.perf_counter()
marks = {}
def mark(name):
    marks.setdefault(name, time.perf_counter() - T0)
import recon.lf, recon.methods, recon.pipeline, rig.main
mark("imports done")

def timed(module, name, begin, end):
    inner = getattr(module, name)
    def wrapper(*args, **kwargs):
        mark(begin)
        try:
            return inner(*args, **kwargs)
        finally:
            mark(end)
    setattr(module, name, wrapper)

timed(recon.pipeline, "reconstruct_to_folder", "command starts", "result folder written")
timed(recon.lf, "read_lightfield", "reading starts", "views read")
timed(recon.pipeline, "run_in_process", "estimate starts", "estimate done")
start_warm = recon.pipeline.warm_in_background
def warm_in_background(method):
    mark("warm-up starts")
    warming = start_warm(method)
    if warming is not None:
        threading.Thread(target=lambda: (warming.ready.wait(), mark("warm-up ready")), daemon=True).start()
    return warming
recon.pipeline.warm_in_background = warm_in_background
sys.argv = ["lfrig", *sys.argv[1:]]
try:
    status = rig.main.main()
finally:
    mark("main returned")
    print(json.dumps(marks), file=sys.stderr)
sys.exit(status)
"""

#: The marks in the order they are printed.
ORDER = ("imports done", "command starts", "warm-up starts", "reading starts", "views read", "warm-up ready",
         "estimate starts", "estimate done", "result folder written", "main returned")


def run_once(folder: Path, extra: list[str], out: Path) -> tuple[dict[str, float], float]:
    """One child's marks and its wall seconds from outside."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    started = time.perf_counter()
    run = subprocess.run([sys.executable, "-c", CHILD, "reconstruct", str(folder), "-o", str(out), "--quiet", *extra],
                         cwd=ROOT, capture_output=True, text=True, env=env, timeout=600)
    wall = time.perf_counter() - started
    lines = run.stderr.strip().splitlines()
    if run.returncode != 0 or not lines:
        raise SystemExit(f"lfrig reconstruct failed (status {run.returncode}):\n{run.stderr.strip()}")
    return json.loads(lines[-1]), wall


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path, nargs="?", default=BACKGAMMON, help="a light field (default: backgammon)")
    parser.add_argument("--runs", type=int, default=3, help="runs after one untimed warm-up run (default 3)")
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1:] if "--" in argv else []  # after --: more flags for lfrig reconstruct
    args = parser.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    if not args.folder.is_dir():
        parser.error(f"{args.folder}: no such light-field folder")
    with tempfile.TemporaryDirectory(prefix="lfrig-timeline-") as work:
        run_once(args.folder, extra, Path(work) / "out")  # numba's cache, the disk's cache
        runs = [run_once(args.folder, extra, Path(work) / "out") for _ in range(args.runs)]
    load = os.getloadavg()[0]
    print(f"lfrig reconstruct {args.folder.name} {' '.join(extra)}".rstrip()
          + f": median of {args.runs} fresh processes, {os.cpu_count()} CPUs, load {load:.1f} after")
    print(f"  {'mark':<22} {'s':>6}")
    for name in ORDER:
        values = [marks[name] for marks, _ in runs if name in marks]
        if values:
            print(f"  {name:<22} {statistics.median(values):6.3f}")
    print(f"  {'process, from outside':<22} {statistics.median(w for _, w in runs):6.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
