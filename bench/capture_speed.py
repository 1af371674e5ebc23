"""Benchmark: a full-size 9x9 capture (1280x980 detector, binning 1) through lfrig's real path.

    .venv/bin/python bench/capture_speed.py [--work DIR] [--methods entropy baseline] [--runs 3]
        [--threads 2] [--remake] [--sizes 2000x1500 ...] [--no-demo] [--tile SIZE]

The capture is the one ``lfrig demo --binning 1`` makes (``rig/demo.py``: the simulated rig and
scene, board calibration with mrcal, the 81 views on the simulated stage, undistorted and rectified
with one map), made once into ``--work`` (default ``runs/capture-speed``, kept between runs; the
demo's own reconstruction there uses the quick baseline) and reused. Each run is a fresh process,
as in ``bench/reconstruct.py``: it reads ``rectified/`` (as grey, as ``lfrig reconstruct`` does;
as stored with ``--tile``), estimates the centre view's disparity and
prints the estimate's wall seconds (median over the runs; one warm-up run first fills numba's
cache), its CPU seconds (user + sys of the process during the estimate, a proxy that the load
other users put on the machine inflates less than wall time), the peak RSS of the whole process
(reading included) and the scores against the simulated scene's truth (BadPix 0.07 % / MSE x100,
15-px border).

``--sizes WxH ...`` measures view sets of other sizes the same way: a synthetic 9x9 capture of that
size (:func:`make_synthetic`: textured planes and boxes over -1.6..1.8 px/view, a faint wall,
sensor noise, rendered by :func:`recon.synthetic.render` and written as 8-bit RGB views like a
rectified capture), made once into ``WORK-synthetic-WxH`` beside ``--work`` and scored against
its rendered truth. ``--tile SIZE`` runs every estimate tiled (:mod:`recon.scale.tiles`, one
process, tiles one after another).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, os, resource, sys, time
import recon  # before numpy, as in lfrig: its settings for numpy (no huge pages) are read at numpy's import
import numpy as np
folder, method, tile = sys.argv[1], sys.argv[2], int(sys.argv[3])
from recon.evaluate import score
from recon.lf import read_lightfield
from recon.lf.pfm import read_pfm
from recon.methods import run_method
from recon.camera import Camera
lf = read_lightfield(folder + "/rectified", grey=not tile)  # as lfrig reconstruct and lfrig batch --tile read it
if os.path.isfile(folder + "/truth_disparity.pfm"):
    truth = read_pfm(folder + "/truth_disparity.pfm").astype(np.float32)
else:
    summary = json.load(open(folder + "/summary.json"))
    camera = Camera(focal_px=summary["rectification"]["focal_px"], pitch_mm=summary["rectification"]["pitch_mm"])
    truth = camera.disparity_px(read_pfm(folder + "/result/truth_depth.pfm")).astype(np.float32)
r0 = resource.getrusage(resource.RUSAGE_SELF)
t0 = time.perf_counter()
if tile:
    from recon.scale.tiles import tiled_disparity
    disparity = tiled_disparity(lf, method=method, tile=tile).disparity
else:
    disparity = run_method(method, lf).disparity
t1 = time.perf_counter()
r1 = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"estimate_s": t1 - t0,
                  "cpu_s": (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime),
                  "peak_mib": r1.ru_maxrss / 1024, "size": list(disparity.shape),
                  "scores": score(disparity, truth)}))
"""


def make_capture(work: Path) -> None:
    """The demo's session at binning 1 into ``work`` (its reconstruction with the baseline)."""
    from rig.demo import run_demo

    print(f"making the 1280x980 capture in {work} (once; the simulated session takes a few minutes)",
          flush=True)
    run_demo(work, binning=1, method="baseline", quiet=True)


def make_synthetic(folder: Path, width: int, height: int) -> None:
    """A synthetic 9x9 capture of ``width`` x ``height`` pixels into ``folder``: ``rectified/`` (8-bit
    RGB views, as a rectified capture) and ``truth_disparity.pfm`` (px/view). Back to front: a
    plain wall (a faint texture, 1 % of the grey range) at -1.6 px/view, a textured floor plane
    sloping from -1.2 to +1.0 over the lower half, and twelve textured boxes between -0.8 and
    +1.8; every view gets Gaussian noise of sigma 0.8 grey levels before rounding."""
    import numpy as np

    from recon.lf.capture import write_lightfield
    from recon.lf.lightfield import LightField
    from recon.lf.pfm import write_pfm
    from recon.synthetic import Layer, noise_texture, render

    print(f"making a synthetic {width}x{height} capture in {folder} (once)", flush=True)
    shape = (height, width)
    wall = 0.55 + 0.01 * (noise_texture(shape, seed=1, scale=3.0) - 0.5)
    half = height / 2

    def lower_half(y, x):
        return y >= half

    layers = [Layer(wall.astype(np.float32), -1.6),
              Layer(noise_texture(shape, seed=2, scale=1.5), -1.2, slope=(2.2 / half, 0.0),
                    centre=(half, 0.0), mask=lower_half)]
    rng = np.random.default_rng(3)
    for i in range(12):
        side = int(rng.uniform(0.08, 0.2) * min(shape))
        y0, x0 = rng.uniform(0, height - side), rng.uniform(0, width - side)

        def box(y, x, y0=y0, x0=x0, side=side):
            return (y >= y0) & (y < y0 + side) & (x >= x0) & (x < x0 + side)

        layers.append(Layer(noise_texture(shape, seed=10 + i, scale=rng.uniform(1.0, 3.0)),
                            float(rng.uniform(-0.8, 1.8)), mask=box))
    lf, truth = render(layers)
    views = lf.views
    del lf
    for u in range(views.shape[0]):  # sensor noise, rounded to 8 bits, view by view
        for v in range(views.shape[1]):
            views[u, v] += rng.normal(0, 0.8 / 255, shape).astype(np.float32)
    grey = np.clip(np.floor(views * 255 + 0.5), 0, 255).astype(np.uint8)
    del views
    write_lightfield(folder / "rectified", LightField(views=np.repeat(grey[..., None], 3, axis=-1), pitch_mm=0.5))
    write_pfm(folder / "truth_disparity.pfm", truth)


def run_once(work: Path, method: str, threads: int, tile: int = 0) -> dict:
    env = dict(os.environ, NUMBA_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads))
    out = subprocess.run([sys.executable, "-c", CHILD, str(work), method, str(tile)], cwd=ROOT,
                         capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise SystemExit(f"{method} on {work / 'rectified'} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _made(folder: Path) -> bool:
    """Whether ``folder`` holds a made capture: the demo's (``summary.json``) or a synthetic one."""
    return (folder / "summary.json").is_file() or (folder / "truth_disparity.pfm").is_file()


def make_missing(work: Path, args: argparse.Namespace) -> None:
    """Make the captures ``args`` asks for that are missing (all of them with ``--remake``)."""
    if not args.no_demo and (args.remake or not _made(work)):
        make_capture(work)
    for width, height in args.sizes:
        folder = work.parent / f"{work.name}-synthetic-{width}x{height}"
        if args.remake or not _made(folder):
            if folder.exists():
                shutil.rmtree(folder)
            make_synthetic(folder, width, height)


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give a size as WIDTHxHEIGHT, e.g. 2000x1500") from None
    if width < 32 or height < 32:
        raise argparse.ArgumentTypeError(f"{text!r}: give at least 32x32 pixels")
    return width, height


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=ROOT / "runs" / "capture-speed",
                        help="folder of the capture (made by the simulated session when missing)")
    parser.add_argument("--methods", nargs="+", default=["entropy"])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2, help="numba threads per run (default 2)")
    parser.add_argument("--remake", action="store_true", help="make the capture afresh")
    parser.add_argument("--sizes", nargs="+", type=_size, default=[], metavar="WxH",
                        help="also synthetic captures of these sizes (e.g. 2000x1500)")
    parser.add_argument("--no-demo", action="store_true", help="leave out the demo capture")
    parser.add_argument("--make-only", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--tile", type=int, default=0, metavar="SIZE",
                        help="run each estimate tiled with SIZE x SIZE tiles (default: whole)")
    args = parser.parse_args()
    if args.runs < 1:
        raise SystemExit(f"--runs {args.runs}: give at least 1")
    work = args.work.resolve()
    folders = ([] if args.no_demo else [work]) + [work.parent / f"{work.name}-synthetic-{w}x{h}"
                                                  for w, h in args.sizes]
    if args.make_only:
        make_missing(work, args)
        return
    if args.remake or any(not _made(folder) for folder in folders):
        # in a child process: Linux counts each measured child's peak RSS from this process's size
        # at the fork, and making a capture takes gigabytes
        subprocess.run([sys.executable, *sys.argv, "--make-only"], check=True)
    load = os.getloadavg()[0]
    print(f"{args.threads} threads; median of {args.runs} runs; {'tiles of ' + str(args.tile) if args.tile else 'whole'}; "
          f"load {load:.1f} at start")
    print(f"{'method':<10} {'size':>9} {'wall s':>7} {'cpu s':>7} {'peak MiB':>9} {'BP0.07':>7} {'MSEx100':>8}  folder")
    for folder in folders:
        for method in args.methods:
            run_once(folder, method, args.threads, args.tile)  # warm-up: numba compiles into its cache
            runs = [run_once(folder, method, args.threads, args.tile) for _ in range(args.runs)]
            s = runs[-1]["scores"]
            h, w = runs[-1]["size"]
            print(f"{method:<10} {f'{w}x{h}':>9} {statistics.median(r['estimate_s'] for r in runs):7.2f} "
                  f"{statistics.median(r['cpu_s'] for r in runs):7.2f} {max(r['peak_mib'] for r in runs):9.0f} "
                  f"{s['badpix_0.07']:7.2f} {s['mse_x100']:8.3f}  {folder / 'rectified'}", flush=True)


if __name__ == "__main__":
    main()
