"""Benchmark: batch throughput on a local Dask cluster with 1 and 2 workers (captures per minute),
and how far a tiled result is from the untiled one.

    .venv/bin/python bench/batch.py [--captures 8] [--size 160] [--grid 9] [--method baseline]
                                    [--workers 1 2] [--export mesh]
    .venv/bin/python bench/batch.py --tiles 64 32 [--method entropy] [--scene boxes] [--size 128]

Renders ``--captures`` synthetic captures (lfrig's capture layout, ``size x size`` grey views on a
``grid x grid`` grid, different seeds) into a temporary folder, then for each worker count starts a
local cluster the way ``lfrig batch reconstruct`` does (processes, one task thread each, numba
threads = cores // workers), runs the whole batch (reconstruct + export, shared filesystem) into a
fresh output folder and reports the wall time of the batch (cluster start-up reported apart) and the
throughput. The first task in each worker process also pays for loading numba's cached kernels, as
a real batch does (kernels are compiled once beforehand, so no run pays for compiling them).

With ``--tiles``, instead: one scene (``square``: :func:`recon.synthetic.occluding_square_scene`, or
a scene name of ``recon.entropy.scenes``) with its true disparity range, reconstructed untiled and
tiled (in this process) for each tile size; prints the share of pixels that differ, that differ by
more than 0.07, how many of those lie within 8 px of a seam, and the scores of both against the truth.
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def render_captures(root: Path, *, count: int, size: int, grid: int) -> list[Path]:
    import numpy as np

    from recon.lf.lightfield import LightField
    from recon.synthetic import occluding_square_scene
    from recon.lf.capture import write_lightfield

    paths = []
    for i in range(count):
        grey, _ = occluding_square_scene(size, seed=100 + i, grid=(grid, grid))
        views = np.clip(np.round(grey.views * 255), 0, 255).astype(np.uint8)
        lf = LightField(views=views, pitch_mm=0.5, focal_px=1000.0, disparity_range=grey.disparity_range)
        path = root / f"capture_{i:02d}"
        write_lightfield(path, lf)
        paths.append(path)
    return paths


def warm_up(capture: Path, method: str) -> None:
    """Run the method once here so numba's on-disk cache holds every kernel: the workers then load
    them instead of compiling inside the first timed task (which would favour whichever run is second)."""
    from recon.lf import read_lightfield
    from recon.methods import run_method

    run_method(method, read_lightfield(capture))


def run(captures: list[Path], out: Path, *, workers: int, method: str, export: str | None) -> dict:
    from recon.scale.batch import BatchRequest, prepare_batch, run_batch
    from recon.scale.cluster import connect

    request = BatchRequest(method=method, options={}, export=export)
    plan = prepare_batch(captures, out, request=request)
    t0 = time.perf_counter()
    with connect(workers=workers, dashboard_address=None) as connection:
        t1 = time.perf_counter()
        outcomes = run_batch(connection.client, plan, threads=connection.task_threads)
        t2 = time.perf_counter()
        threads = connection.task_threads
    failed = [o for o in outcomes if o.status != "ok"]
    if failed:
        raise SystemExit(f"{len(failed)} capture(s) failed, e.g. {failed[0].name}: {failed[0].error}")
    task_s = sorted(o.seconds for o in outcomes)
    return {"workers": workers, "numba_threads": threads, "startup_s": t1 - t0, "batch_s": t2 - t1,
            "per_min": 60 * len(captures) / (t2 - t1), "task_median_s": task_s[len(task_s) // 2]}


def tile_agreement(*, method: str, scene: str, size: int, grid: int, tiles: list[int]) -> None:
    import numpy as np

    from recon.evaluate import score
    from recon.methods import run_method
    from recon.scale.tiles import tiled_disparity

    if scene == "square":
        from recon.synthetic import occluding_square_scene

        lf, truth = occluding_square_scene(size, seed=5, grid=(grid, grid))
    else:
        from recon.entropy.scenes import make_scene

        made = make_scene(scene, size=size, seed=0)
        lf, truth = made.lf, made.truth
    options = {"disparity_range": lf.disparity_range}
    t0 = time.perf_counter()
    full = run_method(method, lf, **options).disparity
    untiled_s = time.perf_counter() - t0
    s_full = score(full, truth)
    print(f"{method} on {scene} {size}x{size} px, {grid}x{grid} views, range {lf.disparity_range}; untiled "
          f"{untiled_s:.1f} s, BadPix 0.07 {s_full['badpix_0.07']:.2f} %, MSE x100 {s_full['mse_x100']:.3f}")
    print(f"{'tile':>5}  {'halo':>4}  {'tiles':>5}  {'time s':>6}  {'differ %':>8}  {'> 0.07 %':>8}  "
          f"{'of which at seams %':>18}  {'max px':>6}  {'BadPix 0.07':>11}  {'MSE x100':>8}")
    for tile in tiles:
        t0 = time.perf_counter()
        result = tiled_disparity(lf, method=method, options=options, tile=tile)
        seconds = time.perf_counter() - t0
        diff = np.abs(result.disparity - full)
        near = np.zeros(diff.shape, bool)
        height, width = diff.shape
        for t in result.tiles:
            top, bottom, left, right = t.core
            for edge in (top, bottom):
                if 0 < edge < height:
                    near[max(edge - 8, 0):edge + 8, left:right] = True
            for edge in (left, right):
                if 0 < edge < width:
                    near[top:bottom, max(edge - 8, 0):edge + 8] = True
        big = diff > 0.07
        s_tiled = score(result.disparity, truth)
        print(f"{tile:>5}  {result.halo:>4}  {len(result.tiles):>5}  {seconds:>6.1f}  {100 * np.mean(diff > 1e-6):>8.2f}  "
              f"{100 * big.mean():>8.2f}  {100 * (big & near).sum() / max(big.sum(), 1):>18.1f}  {diff.max():>6.3f}  "
              f"{s_tiled['badpix_0.07']:>11.2f}  {s_tiled['mse_x100']:>8.3f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--captures", type=int, default=8)
    parser.add_argument("--size", type=int, default=160)
    parser.add_argument("--grid", type=int, default=9)
    parser.add_argument("--method", default="baseline")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--export", choices=("mesh", "points", "none"), default="mesh")
    parser.add_argument("--tiles", type=int, nargs="+", metavar="SIZE",
                        help="measure tiled against untiled for these tile sizes instead")
    parser.add_argument("--scene", default="square", help="with --tiles: 'square' or a recon.entropy.scenes name")
    args = parser.parse_args()
    if args.tiles:
        tile_agreement(method=args.method, scene=args.scene, size=args.size, grid=args.grid, tiles=args.tiles)
        return
    from recon.scale.cluster import machine_cores

    with tempfile.TemporaryDirectory(prefix="lfrig-bench-batch-") as tmp:
        captures = render_captures(Path(tmp) / "captures", count=args.captures, size=args.size, grid=args.grid)
        warm_up(captures[0], args.method)
        print(f"{args.captures} captures, {args.size}x{args.size} px, {args.grid}x{args.grid} views, "
              f"method {args.method}, export {args.export}; {machine_cores()} cores, {platform.processor() or platform.machine()}")
        print(f"{'workers':>7}  {'numba thr':>9}  {'start s':>7}  {'batch s':>7}  {'task median s':>13}  {'captures/min':>12}")
        for workers in args.workers:
            r = run(captures, Path(tmp) / f"out_{workers}", workers=workers, method=args.method,
                    export=None if args.export == "none" else args.export)
            print(f"{r['workers']:>7}  {r['numba_threads']:>9}  {r['startup_s']:>7.1f}  {r['batch_s']:>7.1f}  "
                  f"{r['task_median_s']:>13.2f}  {r['per_min']:>12.1f}", flush=True)


if __name__ == "__main__":
    main()
