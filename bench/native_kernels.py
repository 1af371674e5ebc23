"""Benchmark: each kernel compiled ahead of time (``recon/native``) against its numba twin.

    .venv/bin/python bench/native_kernels.py [--scene ../shared/data/hci/stratified/backgammon]
        [--runs 5] [--threads N]

In one warm process (both kernels loaded, one untimed run each first), the baseline's plane sweep
(:func:`recon.sweep.sweep_least_cost`: 7x7 window, the baseline's 0.02 px/view step over the scene's
range, in the baseline's calls of at most ``baseline.SWEEP_CHUNK`` candidates) runs with the C
kernel and with numba's, alternating run for run (C, numba, numba, C, ...) so that the machine's
drift touches both alike; it prints the median wall and CPU seconds of each, their ratio, the
machine and the load, and checks that the two gave the same bits. ``--threads`` sets both kernels'
threads (numba's ``set_num_threads``; default numba's).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, default=ROOT.parent / "shared" / "data" / "hci" / "stratified" / "backgammon")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--threads", type=int)
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs must be at least 1")

    import numba
    import numpy as np

    from recon.baseline import DEFAULT_DISPARITY_RANGE, SWEEP_CHUNK, disparity_candidates
    from recon.lf import read_lightfield
    from recon.native import unavailable
    from recon.sweep import native_library, sweep_least_cost, view_offsets

    if native_library() is None:
        print(f"the C sweep is not available here: {unavailable('sweep')}", file=sys.stderr)
        return 1
    if args.threads is not None:
        numba.set_num_threads(args.threads)
    lf = read_lightfield(args.scene, grey=True)
    gray = np.ascontiguousarray(lf.gray(), np.float32)
    candidates = disparity_candidates(lf.disparity_range or DEFAULT_DISPARITY_RANGE, 0.02)
    offsets = view_offsets(lf.grid_shape)
    indices = (offsets + np.array(lf.centre_index)).astype(np.int64)
    calls = -(-len(candidates) // SWEEP_CHUNK)
    bounds = [len(candidates) * i // calls for i in range(calls + 1)]

    def sweep(kernel: str) -> dict:
        state = None
        for first, stop in zip(bounds, bounds[1:]):
            state = sweep_least_cost(gray, candidates[first:stop], offsets=offsets, indices=indices, window=7,
                                     state=state, first=first, kernel=kernel)
        return state

    results = {kernel: sweep(kernel) for kernel in ("native", "numba")}  # loaded, untimed
    same = all(np.array_equal(results["native"][k].view(np.uint8), results["numba"][k].view(np.uint8))
               for k in results["native"])
    times: dict[str, list[tuple[float, float]]] = {"native": [], "numba": []}
    load_before = os.getloadavg()
    order = ("native", "numba")
    for run in range(args.runs):
        for kernel in order if run % 2 == 0 else order[::-1]:
            wall, cpu = time.perf_counter(), time.process_time()
            sweep(kernel)
            times[kernel].append((time.perf_counter() - wall, time.process_time() - cpu))
    load_after = os.getloadavg()
    cpu_name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as info:
            cpu_name = next(line.split(":", 1)[1].strip() for line in info if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    print(f"{args.scene.name}: {len(candidates)} candidates, {gray.shape[3]}x{gray.shape[2]}, "
          f"{numba.get_num_threads()} threads; {cpu_name}, {os.cpu_count()} CPUs; "
          f"load {load_before[0]:.1f}-{load_after[0]:.1f}; median of {args.runs}, alternating")
    medians = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in times.items()}
    for kernel, label in (("native", "C (recon/native/sweep.c)"), ("numba", "numba (costvolume._sweep_kernel)")):
        print(f"  {label:<34} {medians[kernel][0]:6.3f} s wall {medians[kernel][1]:6.3f} s CPU")
    print(f"  C / numba wall {medians['native'][0] / medians['numba'][0]:.3f}; the same bits: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
