"""Benchmark: each kernel compiled ahead of time (``recon/native``) against its numba twin.

    .venv/bin/python bench/native_kernels.py [--scene ../shared/data/hci/stratified/backgammon]
        [--runs 5] [--threads N]

In one warm process (both kernels loaded, one untimed run each first), each piece of work runs
with the C kernels and with numba's, alternating run for run (C, numba, numba, C, ...) so that the
machine's drift touches both alike:

- ``sweep``: the baseline's plane sweep (:func:`recon.sweep.sweep_least_cost`: 7x7 window, the
  baseline's 0.02 px/view step over the scene's range, in the baseline's calls of at most
  ``baseline.SWEEP_CHUNK`` candidates);
- ``initial``: the entropy method's nine-view search with its defaults (the square and the eight
  shaped 5x5 windows, 0.05 px/view over the scene's range widened by a step each side, in groups of
  ``cost.min_window_group`` candidates: :func:`recon.entropy.cost.min_window_costs`), then the
  sub-step arg-min and the ambiguity count of its cost volume;
- ``estimate``: the whole default estimate (:func:`recon.entropy.estimate_disparity`, the scene's
  range), every kernel C or every kernel numba's (:func:`recon.native.preferring`), with each
  step's median wall seconds beside the totals.

It prints the median wall and CPU seconds of each, their ratio, the machine and the load, and checks
that the two gave the same bits. ``--threads`` sets both kernels' threads (numba's
``set_num_threads``; default numba's).
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
    from recon.native import SIGNATURES, library, unavailable
    from recon.sweep import sweep_least_cost, view_offsets

    for name in SIGNATURES:
        if library(name) is None:
            print(f"the C kernels of {name}.c are not available here: {unavailable(name)}", file=sys.stderr)
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

    from recon.entropy.cost import cost_ambiguity, min_window_costs, min_window_group, set_view_counts
    from recon.entropy.initial import initial_view_mask
    from recon.entropy.matching import disparity_candidates as search_candidates, subpixel_argmin
    from recon.entropy.options import DEFAULTS
    from recon.entropy.windows import window_rect

    low, high = lf.disparity_range or DEFAULT_DISPARITY_RANGE
    nine = search_candidates(low - DEFAULTS.initial_step, high + DEFAULTS.initial_step, DEFAULTS.initial_step)
    mask = initial_view_mask(lf.grid_shape)
    set_counts = set_view_counts(lf.grid_shape, mask)
    shapes = range(9)
    rects = np.array([window_rect(shape, DEFAULTS.initial_window) for shape in shapes], np.int64)
    inputs = dict(sets=np.arange(9), window_set=np.arange(9, dtype=np.int64), rects=rects,
                  counts=set_counts[np.arange(9)].astype(np.float64), allowed=np.ones((9, 1, 1), np.bool_),
                  view_mask=mask)
    group = min_window_group(gray.shape[3], n_sets=9, n_windows=9, rects=rects)

    def initial(kernel: str) -> tuple:
        costs = np.empty((len(nine), *gray.shape[2:]), np.float32)
        for i in range(0, len(nine), group):
            min_window_costs(gray, nine[i:i + group], **inputs, out=costs[i:i + group], kernel=kernel)
        return (costs, *subpixel_argmin(costs, nine, kernel=kernel), cost_ambiguity(costs, 0.002, kernel=kernel))

    from recon.entropy import estimate_disparity
    from recon.native import preferring

    steps: dict[str, list[dict[str, float]]] = {}

    def estimate(kernel: str) -> list:
        with preferring(kernel):
            result = estimate_disparity(lf)
        steps.setdefault(kernel, []).append(result.timings)
        return [value for value in vars(result).values() if isinstance(value, np.ndarray)]

    work = {"sweep": (sweep, lambda r: list(r.values()), "recon/native/sweep.c", "costvolume._sweep_kernel"),
            "initial": (initial, list, "recon/native/initial.c", "cost._min_window_costs_kernel ..."),
            "estimate": (estimate, list, "every recon/native kernel", "every numba twin")}
    same = {}
    for name, (run_it, arrays, _, _) in work.items():  # loaded, untimed
        a, b = arrays(run_it("native")), arrays(run_it("numba"))
        same[name] = all(np.array_equal(x.view(np.uint8), y.view(np.uint8)) for x, y in zip(a, b))
    times: dict[tuple[str, str], list[tuple[float, float]]] = {}
    load_before = os.getloadavg()
    order = ("native", "numba")
    for run in range(args.runs):
        for name, (run_it, _, _, _) in work.items():
            for kernel in order if run % 2 == 0 else order[::-1]:
                wall, cpu = time.perf_counter(), time.process_time()
                run_it(kernel)
                times.setdefault((name, kernel), []).append((time.perf_counter() - wall, time.process_time() - cpu))
    load_after = os.getloadavg()
    cpu_name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as info:
            cpu_name = next(line.split(":", 1)[1].strip() for line in info if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    print(f"{args.scene.name}, {gray.shape[3]}x{gray.shape[2]}: sweep {len(candidates)} candidates, initial "
          f"{len(nine)}; {numba.get_num_threads()} threads; {cpu_name}, {os.cpu_count()} CPUs; "
          f"load {load_before[0]:.1f}-{load_after[0]:.1f}; median of {args.runs}, alternating")
    medians = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in times.items()}
    for name, (_, _, source, twin) in work.items():
        print(f"{name}:")
        for kernel, label in (("native", f"C ({source})"), ("numba", f"numba ({twin})")):
            print(f"  {label:<42} {medians[name, kernel][0]:6.3f} s wall {medians[name, kernel][1]:6.3f} s CPU")
        ratio = medians[name, "native"][0] / medians[name, "numba"][0]
        print(f"  C / numba wall {ratio:.3f}; the same bits: {same[name]}")
    for kernel, label in (("native", "C"), ("numba", "numba")):
        timed = steps[kernel][1:]  # the untimed run's steps left out
        print(f"estimate's steps, {label}, median wall s: "
              + " ".join(f"{step} {statistics.median(t[step] for t in timed):.3f}" for step in timed[0]))
    return 0 if all(same.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
