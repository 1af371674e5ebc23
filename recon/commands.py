"""``lfrig info``, ``lfrig reconstruct`` and ``lfrig evaluate``: parse, call the library, write files."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from recon.methods import DEFAULT_METHOD, METHODS


def register(subparsers: argparse._SubParsersAction) -> None:
    info = subparsers.add_parser(
        "info",
        help="describe a light field (folder) or a disparity map (.pfm)",
        description="Print what a light-field folder (benchmark or capture layout) or a PFM file holds.",
    )
    info.add_argument("path", type=Path, help="light-field folder or .pfm file")
    info.add_argument("--json", action="store_true", help="print the description as JSON")
    info.set_defaults(handler=_info)

    rec = subparsers.add_parser(
        "reconstruct",
        help="estimate the centre view's disparity",
        description=(
            "Estimate the disparity of the centre view (pixels per view step, the benchmark's sign) and write "
            "OUT_DIR/disparity.pfm, a colour-mapped disparity.png and result.json. When the light field has "
            "ground truth (gt_disp_lowres.pfm), the scores are printed and recorded too."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    rec.add_argument("lf_dir", type=Path, metavar="LF_DIR", help="light-field folder (benchmark or capture layout)")
    rec.add_argument("-o", "--output", type=Path, required=True, metavar="OUT_DIR", help="folder for the results")
    rec.add_argument("--method", choices=list(METHODS), default=DEFAULT_METHOD,
                     help="; ".join(f"{k}: {v[1]}" for k, v in METHODS.items()) + f" (default {DEFAULT_METHOD})")
    rec.add_argument("--disparity-range", type=float, nargs=2, metavar=("MIN", "MAX"),
                     help="disparities to search, pixels per view step (default: the light field's; else "
                          "entropy finds it from its initial estimate and baseline searches -4 4)")
    rec.add_argument("--step", type=float, default=None,
                     help="spacing of candidate disparities, refined to sub-step by a parabola (default 0.02)")
    base = rec.add_argument_group("baseline method")
    base.add_argument("--window", type=int, default=None, help="square window side in pixels (default 7)")
    _add_entropy_options(rec.add_argument_group(
        "entropy method (defaults: the paper's values; see docs/entropy-method.md)"))
    rec.add_argument("--ply", type=Path, metavar="OUT.ply",
                     help="also export a PLY mesh (or point cloud with --points) of the metric depth")
    rec.add_argument("--points", action="store_true", help="with --ply: a point cloud instead of a mesh")
    rec.add_argument("--quiet", action="store_true", help="no progress output")
    rec.set_defaults(handler=_reconstruct)

    ev = subparsers.add_parser(
        "evaluate",
        help="score a disparity map against ground truth",
        description=(
            "Score ESTIMATE.pfm against GT.pfm as the 4D Light Field Benchmark does: a border of 15 pixels is "
            "left out; MSE x100 and BadPix 0.07 / 0.03 / 0.01 in percent."
        ),
    )
    ev.add_argument("estimate", type=Path, metavar="ESTIMATE.pfm")
    ev.add_argument("gt", type=Path, metavar="GT.pfm")
    ev.add_argument("--border", type=int, default=15, help="pixels left out on every side (default 15)")
    ev.add_argument("--json", action="store_true", help="print the scores as JSON")
    ev.set_defaults(handler=_evaluate)


#: Entropy options that have a shared flag above, or are not useful from the command line.
_SHARED_OPTIONS = {"disparity_range", "step"}


def _add_entropy_options(group: argparse._ArgumentGroup) -> None:
    """One flag per field of :class:`recon.entropy.EntropyOptions`, from its type, default and help.

    Flags default to ``None``, so only what the user sets overrides the estimator's own defaults.
    """
    import dataclasses

    from recon.entropy.estimate import DEFAULTS, EntropyOptions

    for f in dataclasses.fields(EntropyOptions):
        if f.name in _SHARED_OPTIONS:
            continue
        default = getattr(DEFAULTS, f.name)
        flag = "--" + f.name.replace("_", "-")
        text = f"{f.metadata.get('help', '')} (default {default})".replace("%", "%%")
        if isinstance(default, bool):
            group.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=text)
        elif isinstance(default, tuple):
            kind = type(default[0]) if default else float
            group.add_argument(flag, type=kind, nargs="+", default=None, metavar="N", help=text)
        else:
            group.add_argument(flag, type=type(default), default=None, help=text)


def _method_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options the user set for the chosen method (others keep the method's defaults)."""
    import dataclasses

    from recon.errors import ReconError

    chosen: dict[str, Any] = {}
    if args.disparity_range is not None:
        if not args.disparity_range[0] < args.disparity_range[1]:
            raise ReconError(f"--disparity-range {args.disparity_range[0]} {args.disparity_range[1]}: "
                             "MIN must be less than MAX")
        chosen["disparity_range"] = tuple(args.disparity_range)
    if args.step is not None:
        if not args.step > 0:
            raise ReconError(f"--step {args.step}: give a positive spacing, e.g. 0.02")
        chosen["step"] = args.step
    if args.method == "baseline":
        if args.window is not None:
            chosen["window"] = args.window
        return chosen
    from recon.entropy.estimate import EntropyOptions

    for f in dataclasses.fields(EntropyOptions):
        value = getattr(args, f.name, None)
        if f.name not in _SHARED_OPTIONS and value is not None:
            chosen[f.name] = tuple(value) if isinstance(value, list) else value
    if args.window is not None:
        raise ReconError("--window belongs to the baseline method; the entropy method chooses its windows "
                         "(see --window-sizes)")
    return chosen


def describe(path: Path) -> dict[str, Any]:
    """What ``lfrig info`` prints, as a dict."""
    import numpy as np

    from recon.errors import LightFieldFormatError
    from recon.io import read_lightfield
    from recon.pfm import read_pfm

    if path.is_file():
        if path.suffix.lower() != ".pfm":
            raise LightFieldFormatError(f"{path}: lfrig info reads light-field folders and .pfm files")
        data = read_pfm(path)
        finite = data[np.isfinite(data)]
        return {
            "path": str(path), "kind": "pfm", "width": data.shape[1], "height": data.shape[0],
            "channels": 1 if data.ndim == 2 else data.shape[2],
            "finite_pixels": int(finite.size),
            "min": float(finite.min()) if finite.size else None,
            "max": float(finite.max()) if finite.size else None,
        }
    lf = read_lightfield(path)
    rows, cols = lf.grid_shape
    height, width = lf.image_shape
    out: dict[str, Any] = {
        "path": str(path), "kind": "lightfield", "layout": lf.metadata.get("layout"),
        "grid": [rows, cols], "image": [width, height],
        "colour": "RGB" if lf.is_colour else "grey", "bits": lf.views.dtype.itemsize * 8,
        "pitch_mm": lf.pitch_mm, "focal_px": lf.focal_px,
        "disparity_range": list(lf.disparity_range) if lf.disparity_range else None,
        "disparity_offset": lf.disparity_offset,
        "ground_truth": lf.metadata.get("ground_truth"),
    }
    header = lf.metadata.get("header")
    if header:
        out["created"] = header.get("created")
        out["camera"] = header.get("camera")
    return out


def _info(args: argparse.Namespace) -> None:
    info = describe(args.path)
    if args.json:
        print(json.dumps(info, indent=2))
        return
    if info["kind"] == "pfm":
        print(f"{info['path']}: PFM, {info['width']}x{info['height']}, {info['channels']} channel(s)")
        print(f"  finite pixels: {info['finite_pixels']}, range: {info['min']} .. {info['max']}")
        return
    print(f"{info['path']}: light field ({info['layout']} layout)")
    print(f"  grid:        {info['grid'][0]} x {info['grid'][1]} views (rows x columns)")
    print(f"  views:       {info['image'][0]} x {info['image'][1]} px, {info['colour']}, {info['bits']}-bit")
    print(f"  pitch:       {_or_unknown(info['pitch_mm'], '{:.4g} mm')}")
    print(f"  focal:       {_or_unknown(info['focal_px'], '{:.6g} px')}")
    rng = info["disparity_range"]
    print(f"  disparity:   {'unknown' if rng is None else f'{rng[0]:g} .. {rng[1]:g} px per view step'}"
          f" (offset d0 = {info['disparity_offset']:.4g})")
    print(f"  ground truth: {info['ground_truth'] or 'none'}")
    if info.get("created"):
        print(f"  captured:    {info['created']}")


def _or_unknown(value: float | None, fmt: str) -> str:
    return "unknown" if value is None else fmt.format(value)


def _reconstruct(args: argparse.Namespace) -> None:
    from recon.colour import colourise
    from recon.errors import ReconError
    from recon.evaluate import score
    from recon.imageio import write_png
    from recon.io import read_ground_truth, read_lightfield
    from recon.methods import run_method
    from recon.pfm import write_pfm
    from recon.progress import Progress

    options = _method_options(args)
    lf = read_lightfield(args.lf_dir)
    args.output.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    try:
        with Progress(args.method, 1, quiet=args.quiet) as bar:
            method = run_method(args.method, lf, progress=bar, **options)
    except ValueError as error:  # an option value the method cannot use
        raise ReconError(f"{args.method}: {error}") from None
    disparity = method.disparity
    seconds = time.perf_counter() - started
    write_pfm(args.output / "disparity.pfm", disparity)
    picture, shown = colourise(disparity, value_range=lf.disparity_range)
    write_png(args.output / "disparity.png", picture)
    write_png(args.output / "centre_view.png", lf.centre_view())
    if method.write_extras is not None:
        method.write_extras(args.output)
    result: dict[str, Any] = {
        "method": args.method, "options": _jsonable(method.options), "source": str(lf.source.resolve()) if lf.source else None,
        "image": [lf.image_shape[1], lf.image_shape[0]], "grid": list(lf.grid_shape),
        "focal_px": lf.focal_px, "pitch_mm": lf.pitch_mm, "disparity_offset": lf.disparity_offset,
        "disparity_png_range": list(shown), "seconds": round(seconds, 3),
    }
    gt = read_ground_truth(lf)
    if gt is not None:
        result["scores"] = score(disparity, gt)
    (args.output / "result.json").write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {args.output / 'disparity.pfm'} and disparity.png in {seconds:.1f} s")
    if "scores" in result:
        print(_format_scores(result["scores"]))
    if args.ply is not None:
        from recon.export import export_result

        print(f"wrote {export_result(args.output, args.ply, kind='points' if args.points else 'mesh')}")


def _jsonable(options: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(options, default=str))


def _format_scores(scores: dict[str, float]) -> str:
    return (f"MSE x100 {scores['mse_x100']:.3f}   BadPix 0.07 {scores['badpix_0.07']:.2f} %   "
            f"0.03 {scores['badpix_0.03']:.2f} %   0.01 {scores['badpix_0.01']:.2f} %   ({scores['pixels']} px)")


def _evaluate(args: argparse.Namespace) -> None:
    from recon.evaluate import score
    from recon.pfm import read_pfm

    estimate = read_pfm(args.estimate)
    gt = read_pfm(args.gt)
    if estimate.ndim != 2 or gt.ndim != 2:
        from recon.errors import ReconError

        bad = args.estimate if estimate.ndim != 2 else args.gt
        raise ReconError(f"{bad}: a disparity map has one channel; this PFM has three")
    scores = score(estimate, gt, border=args.border)
    if args.json:
        print(json.dumps(scores, indent=2))
    else:
        print(_format_scores(scores))
