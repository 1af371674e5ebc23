"""A digest of every map the matching-entropy estimator makes, to prove that a change of code changes none.

    .venv/bin/python bench/maps_digest.py -o /tmp/before.json            # on the code before the change
    .venv/bin/python bench/maps_digest.py -o /tmp/after.json --compare /tmp/before.json

Runs the estimator with its defaults and with ``preset="paper"`` on the benchmark scene and the
rendered dev scenes beside the checkout (``../shared/data``: ``hci/stratified/backgammon``,
``blender-dev/*``, their views read as grey as ``lfrig reconstruct`` reads them) and on the scene
suite (:mod:`recon.entropy.scenes`, rendered at ``--size``), plus a tiled run
(:func:`recon.scale.tiles.tiled_disparity`, ``--tile`` core pixels) on the scenes named by
``--tiled``. For each run it records the SHA-256 of every array of the result (``disparity``,
``initial_disparity``, ``matched_disparity``, ``labels``, window maps, ``entropy``, ``cost``,
``confidence``) and of every array in its ``info``, and the disparity range searched; a tiled run
records the same of its stitched result (the confidence among them) and prints the maps in which
it differs from the untiled run with the defaults. ``--methods baseline`` (or ``entropy baseline``)
also runs the 7x7 baseline (:func:`recon.baseline.estimate_baseline`, its defaults) on every scene
and records its ``disparity``, ``cost`` and ``candidates``:

    .venv/bin/python bench/maps_digest.py -o /tmp/base.json --methods baseline --size 192

``--compare`` prints each digest that differs and exits 1 if any does (a digest the other file does
not have is listed as new, not as a difference). Digests are of the bytes: dtype, shape and every
bit count.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"


def _digest(array) -> str:
    import numpy as np

    a = np.ascontiguousarray(array)
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def result_digest(result) -> dict[str, str]:
    """``name -> sha256`` of every array of an :class:`recon.entropy.EntropyResult` and its ``info``."""
    import numpy as np

    out = {}
    for name in ("disparity", "initial_disparity", "matched_disparity", "labels", "window_size",
                 "window_shape", "view_set", "entropy", "cost", "confidence"):
        value = getattr(result, name)
        out[name] = None if value is None else _digest(value)
    for name, value in sorted((result.info or {}).items()):
        if isinstance(value, np.ndarray):
            out["info." + name] = _digest(value)
        elif value is None or isinstance(value, (int, float, bool)):
            out["info." + name] = repr(value)
    out["disparity_range"] = repr(tuple(float(v) for v in result.disparity_range))
    return out


def _scenes(args) -> dict:
    """``name -> zero-argument loader of a LightField``."""
    from recon.entropy.scenes import SCENES, make_scene
    from recon.lf import read_lightfield

    loaders = {}
    if not args.no_shared:
        data = args.data
        backgammon = data / "hci" / "stratified" / "backgammon"
        if backgammon.is_dir():
            loaders["backgammon"] = lambda p=backgammon: read_lightfield(p, grey=True)
        for folder in sorted((data / "blender-dev").glob("*")):
            if (folder / "parameters.cfg").is_file():
                loaders[folder.name] = lambda p=folder: read_lightfield(p, grey=True)
    for name in SCENES:
        loaders[f"suite/{name}"] = lambda n=name: make_scene(n, size=args.size).lf
    if args.scenes:
        loaders = {k: v for k, v in loaders.items() if k in args.scenes}
    return loaders


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", type=Path, required=True, help="JSON file for the digests")
    parser.add_argument("--compare", type=Path, help="a digest JSON to compare with")
    parser.add_argument("--size", type=int, default=96, help="side of the rendered suite scenes (default 96)")
    parser.add_argument("--scenes", nargs="+", help="only these (backgammon, glossy-v1, ..., suite/bars, ...)")
    parser.add_argument("--no-shared", action="store_true", help="leave out the scenes of ../shared/data")
    parser.add_argument("--data", type=Path, default=DATA, help=f"the shared data folder (default {DATA})")
    parser.add_argument("--methods", nargs="+", choices=["entropy", "baseline"], default=["entropy"],
                        help="the estimators to run (default entropy)")
    parser.add_argument("--presets", nargs="+", default=["default", "paper"], help="the entropy estimator's presets")
    parser.add_argument("--tiled", nargs="*", default=["suite/bars", "suite/thin"],
                        help="scenes also run tiled with the default options (default suite/bars suite/thin)")
    parser.add_argument("--tile", type=int, default=40, help="tile core side in pixels (default 40)")
    args = parser.parse_args()

    from recon.baseline import estimate_baseline
    from recon.entropy import estimate_disparity
    from recon.scale.tiles import tiled_disparity

    record: dict[str, dict] = {}
    for name, load in _scenes(args).items():
        lf = load()
        if "baseline" in args.methods:
            t = time.perf_counter()
            base = estimate_baseline(lf)
            record[f"{name} baseline"] = {key: _digest(getattr(base, key)) for key in ("disparity", "cost", "candidates")}
            print(f"{name} baseline: {time.perf_counter() - t:.1f} s", flush=True)
        if "entropy" not in args.methods:
            continue
        for preset in args.presets:
            t = time.perf_counter()
            result = estimate_disparity(lf, preset=preset)
            record[f"{name} {preset}"] = result_digest(result)
            print(f"{name} {preset}: {time.perf_counter() - t:.1f} s", flush=True)
        if name in args.tiled:
            t = time.perf_counter()
            tiled = tiled_disparity(lf, method="entropy", tile=args.tile)
            digests = result_digest(tiled.extras)
            digests.update({"disparity": _digest(tiled.disparity), "halo_px": repr(tiled.halo),
                            "disparity_range": repr(tiled.options["disparity_range"])})
            record[f"{name} tiled"] = digests
            untiled = record.get(f"{name} default", {})
            unlike = sorted(k for k in untiled if k in digests and digests[k] != untiled[k])
            print(f"{name} tiled ({len(tiled.tiles)} tiles, halo {tiled.halo}): "
                  f"{time.perf_counter() - t:.1f} s; "
                  + (f"differs from untiled in {', '.join(unlike)}" if unlike else
                     f"{len(untiled)} digests equal to untiled's" if untiled else "no untiled run to compare"),
                  flush=True)
    args.output.write_text(json.dumps(record, indent=1, sort_keys=True))
    if args.compare is None:
        return 0
    reference = json.loads(args.compare.read_text())
    differ = 0
    for run, digests in record.items():
        if run not in reference:
            print(f"{run}: not in {args.compare}")
            continue
        new = [key for key in digests if key not in reference[run]]
        if new:
            print(f"new in {run}: {', '.join(new)}")
        for key, value in digests.items():
            if key in reference[run] and reference[run][key] != value:
                differ += 1
                print(f"DIFFERS {run}: {key}")
    print(f"{differ} digest(s) differ over {len(record)} run(s)" if differ else
          f"all digests equal over {len(record)} run(s)")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
