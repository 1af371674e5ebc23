"""recon's commands: ``lfrig info``, ``reconstruct``, ``evaluate``, ``export``, ``batch reconstruct`` and ``import``.

Parse, call the library, write files. Heavy modules (numba kernels, open3d, Dask) are imported inside
the handlers so that ``lfrig --help`` stays fast. :func:`register` adds the subcommands.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from recon.cliargs import (ALL_INTERFACES, CommandReport, add_json_argument, finite_float, float_range, host_port,
                           int_range, nonnegative_int, output_file,
                           output_folder, positive_float, positive_int)
from recon.methods import DEFAULT_METHOD, METHODS


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add recon's subcommands to the ``lfrig`` parser."""
    _register_reconstruct(subparsers)
    _register_export(subparsers)
    _register_batch(subparsers)
    _register_import(subparsers)


def _add_verify_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-verify", dest="verify", action="store_false",
                        help="do not check a capture's views against the checksums in its journal")


def _register_reconstruct(subparsers: argparse._SubParsersAction) -> None:
    info = subparsers.add_parser(
        "info",
        help="describe a light field (folder) or a disparity map (.pfm)",
        description="Print what a light-field folder (benchmark or capture layout) or a PFM file holds. The "
                    "views' files are checked (a capture's checksums, each PNG's chunks and header); only the "
                    "first is decoded.",
    )
    info.add_argument("path", type=Path, help="light-field folder or .pfm file")
    add_json_argument(info)
    _add_verify_argument(info)
    info.set_defaults(handler=_info)

    rec = subparsers.add_parser(
        "reconstruct",
        help="estimate the centre view's disparity",
        description=(
            "Estimate the disparity of the centre view (pixels per view step, the benchmark's sign) and write "
            "OUT_DIR/disparity.pfm, a colour-mapped disparity.png, centre_view.png, the method's own maps "
            "(entropy: regions.png, window size and shape, initial/matched/refined disparity) and result.json. "
            "When the light field has ground truth (gt_disp_lowres.pfm), the scores are printed and recorded too."
        ),
    )
    rec.add_argument("lf_dir", type=Path, metavar="LF_DIR", help="light-field folder (benchmark or capture layout)")
    rec.add_argument("-o", "--output", type=output_folder, required=True, metavar="OUT_DIR", help="folder for the results")
    add_method_arguments(rec)
    rec.add_argument("--ply", type=output_file, metavar="OUT.ply",
                     help="also export a PLY mesh (or point cloud with --points) of the metric depth")
    rec.add_argument("--points", action="store_true", help="with --ply: a point cloud instead of a mesh")
    rec.add_argument("--quiet", action="store_true", help="no progress output")
    add_json_argument(rec)
    _add_verify_argument(rec)
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
    ev.add_argument("--border", type=nonnegative_int, default=15, help="pixels left out on every side (default 15)")
    add_json_argument(ev)
    ev.set_defaults(handler=_evaluate)


#: Entropy options that have an everyday flag of their own (``add_method_arguments``).
_SHARED_OPTIONS = {"disparity_range", "step"}


def add_method_arguments(parser: argparse.ArgumentParser) -> None:
    """The method flags shared by ``lfrig reconstruct`` and ``lfrig batch reconstruct``: ``--method``,
    ``--preset``, ``--disparity-range``, ``--step``, the baseline's ``--window``, and one flag per
    entropy option, listed by ``--help-tuning`` (grouped by step) rather than ``--help``.
    :func:`method_options` turns the parsed flags into the chosen method's options."""
    from recon.entropy.options import PRESETS

    parser.add_argument("--config", type=Path, metavar="FILE",
                        help="options from a TOML file of these flags' names (window_sizes = [3, 5]) or a result.json "
                             "(its method and options, to reproduce it); a flag given here wins over the file")
    parser.add_argument("--method", choices=list(METHODS), default=None,
                        help="; ".join(f"{k}: {v.description}" for k, v in METHODS.items()) + f" (default {DEFAULT_METHOD})")
    parser.add_argument("--preset", choices=list(PRESETS), default=None,
                        help="entropy: a named set of options applied before the tuning flags: 'paper' is the "
                             "paper's literal configuration (docs/entropy-method.md), 'default' lfrig's defaults")
    parser.add_argument("--disparity-range", type=finite_float, nargs=2, metavar=("MIN", "MAX"),
                        help="disparities to search, pixels per view step (default: the light field's; else "
                             "entropy finds it by a coarse search over -8 8 and its initial estimate; baseline searches -4 4)")
    parser.add_argument("--step", type=positive_float, default=None,
                        help="spacing of candidate disparities, refined to sub-step by a parabola (default: baseline 0.02, entropy 0.04)")
    parser.add_argument("--window", type=positive_int, default=None,
                        help="baseline: square window side in pixels (default 7)")
    parser.add_argument("--help-tuning", action=_TuningHelp,
                        help="list the entropy method's tuning flags, grouped by step, and exit")
    for action in _entropy_flags(parser):
        action.help = argparse.SUPPRESS


def _entropy_flags(parser) -> list[argparse.Action]:
    """One flag per field of :class:`recon.entropy.options.EntropyOptions` (but the everyday ones),
    from its type, default and help, grouped by step; each value is checked by its step's options
    group as it is parsed. Flags default to ``None``, so only what the user sets overrides the
    estimator's own defaults."""
    import dataclasses

    from recon.entropy.options import DEFAULTS, GROUPS, TITLES

    actions = []
    for step, group in GROUPS.items():
        section = parser.add_argument_group(f"{step} ({TITLES[step]})")
        for f in dataclasses.fields(group):
            if f.name in _SHARED_OPTIONS:
                continue
            default = getattr(DEFAULTS, f.name)
            flag = "--" + f.name.replace("_", "-")
            text = f"{f.metadata.get('help', '')} (default {default})".replace("%", "%%")
            if isinstance(default, bool):
                actions.append(section.add_argument(flag, action=argparse.BooleanOptionalAction, default=None,
                                                    help=text))
            elif isinstance(default, tuple):
                kind = type(default[0]) if default else float
                actions.append(section.add_argument(flag, type=_flag_type(kind), nargs="+", default=None,
                                                    metavar="N", action=_CheckedOption, help=text))
            else:
                actions.append(section.add_argument(flag, type=_flag_type(type(default)), default=None,
                                                    action=_CheckedOption, help=text))
    return actions


class _CheckedOption(argparse.Action):
    """Stores an entropy option's value once its step's options group accepts it
    (:func:`recon.entropy.options.check_value`); else a one-line usage error."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        from recon.entropy.options import check_value

        value = tuple(values) if isinstance(values, list) else values
        try:
            check_value(self.dest, value)
        except ValueError as error:
            raise argparse.ArgumentError(self, str(error)) from None
        setattr(namespace, self.dest, value)


class _TuningHelp(argparse.Action):
    """``--help-tuning``: the entropy method's tuning flags, grouped by step, then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        tuning = argparse.ArgumentParser(
            prog=parser.prog, add_help=False, usage=f"{parser.prog} LF_DIR -o OUT_DIR [TUNING FLAGS]",
            description="The entropy method's options, grouped by the step of the estimator that reads "
                        "them (docs/entropy-method.md). Each overrides the preset's value.")
        _entropy_flags(tuning)
        tuning.print_help()
        parser.exit()


def _flag_type(kind: type):
    """Floats must be finite (no ``nan``/``inf``); the options groups judge the rest."""
    return finite_float if kind is float else kind


class _ConfigParser(argparse.ArgumentParser):
    """Parses one option of an options file as its flag; a bad value is a :class:`recon.config.ConfigError`."""

    where = ""

    def error(self, message: str):
        from recon.config import ConfigError

        raise ConfigError(f"{self.where}: {message}")


def _apply_config(args: argparse.Namespace) -> None:
    """Set the method flags the command line left unset from ``--config FILE`` (:mod:`recon.config`):
    each option of the file is parsed as its flag would be, so it is checked the same way."""
    path = getattr(args, "config", None)
    if path is not None:
        from recon.config import config_tokens, read_config

        parser = _ConfigParser(add_help=False)
        add_method_arguments(parser)
        keys = set(vars(parser.parse_args([]))) - {"config"}
        for key, tokens in config_tokens(read_config(path, keys=keys), path=path):
            parser.where = f"{path}: option {key!r}"
            if getattr(args, key) is None:  # a flag on the command line wins
                setattr(args, key, getattr(parser.parse_args(tokens), key))
    if args.method is None:
        args.method = DEFAULT_METHOD


def method_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options the user set for the chosen method (others keep the method's defaults), from the
    flags and ``--config``."""
    import dataclasses

    from recon.errors import ReconError

    _apply_config(args)
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
        if getattr(args, "preset", None) is not None:
            raise ReconError("--preset belongs to the entropy method; drop it or use --method entropy")
        return chosen
    if getattr(args, "preset", None) is not None:
        chosen["preset"] = args.preset
    from recon.entropy.options import EntropyOptions

    for f in dataclasses.fields(EntropyOptions):
        value = getattr(args, f.name, None)
        if f.name not in _SHARED_OPTIONS and value is not None:
            chosen[f.name] = tuple(value) if isinstance(value, list) else value
    if args.window is not None:
        raise ReconError("--window belongs to the baseline method; the entropy method chooses its windows "
                         "(see --window-sizes)")
    return chosen


def describe(path: Path, *, verify: bool = True) -> dict[str, Any]:
    """What ``lfrig info`` prints, as a dict."""
    import numpy as np

    from recon.errors import LightFieldFormatError
    from recon.lf import read_lightfield
    from recon.lf.pfm import read_pfm

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
    lf = read_lightfield(path, verify=verify, decode=False)  # the sizes and dtype, no pixels
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
    info = describe(args.path, verify=args.verify)
    out = CommandReport(as_json=args.json)
    if info["kind"] == "pfm":
        lines = [f"{info['path']}: PFM, {info['width']}x{info['height']}, {info['channels']} channel(s)",
                 f"  finite pixels: {info['finite_pixels']}, range: {info['min']} .. {info['max']}"]
    else:
        rng = info["disparity_range"]
        lines = [
            f"{info['path']}: light field ({info['layout']} layout)",
            f"  grid:        {info['grid'][0]} x {info['grid'][1]} views (rows x columns)",
            f"  views:       {info['image'][0]} x {info['image'][1]} px, {info['colour']}, {info['bits']}-bit",
            f"  pitch:       {_or_unknown(info['pitch_mm'], '{:.4g} mm')}",
            f"  focal:       {_or_unknown(info['focal_px'], '{:.6g} px')}",
            f"  disparity:   {'unknown' if rng is None else f'{rng[0]:g} .. {rng[1]:g} px per view step'}"
            f" (offset d0 = {info['disparity_offset']:.4g})",
            f"  ground truth: {info['ground_truth'] or 'none'}",
        ]
        if info.get("created"):
            lines.append(f"  captured:    {info['created']}")
    out.line("\n".join(lines), **info)
    out.finish()


def _or_unknown(value: float | None, fmt: str) -> str:
    return "unknown" if value is None else fmt.format(value)


def _reconstruct(args: argparse.Namespace) -> None:
    from recon.pipeline import reconstruct_to_folder
    from recon.progress import Progress
    from recon.result import DISPARITY_PFM, DISPARITY_PNG

    options = method_options(args)
    with Progress(args.method, quiet=args.quiet) as bar:
        folder = reconstruct_to_folder(args.lf_dir, args.output, method=args.method, options=options, ply=args.ply,
                                       ply_kind="points" if args.points else "mesh", progress=bar,
                                       verify=args.verify)
    out = CommandReport(as_json=args.json)
    out.line(f"wrote {args.output / DISPARITY_PFM} and {DISPARITY_PNG} in {folder.record.seconds:.1f} s",
             output=args.output, method=args.method, seconds=folder.record.seconds,
             disparity=args.output / DISPARITY_PFM, options=folder.record.options)
    if folder.record.scores is not None:
        out.line(_format_scores(folder.record.scores), scores=folder.record.scores)
    if folder.export is not None:
        out.line(f"wrote {folder.export}", ply=folder.export)
    out.finish()


def _format_scores(scores: dict[str, float]) -> str:
    return (f"MSE x100 {scores['mse_x100']:.3f}   BadPix 0.07 {scores['badpix_0.07']:.2f} %   "
            f"0.03 {scores['badpix_0.03']:.2f} %   0.01 {scores['badpix_0.01']:.2f} %   ({scores['pixels']} px)")


def _evaluate(args: argparse.Namespace) -> None:
    from recon.evaluate import score_files

    scores = score_files(args.estimate, args.gt, border=args.border)
    out = CommandReport(as_json=args.json)
    out.line(_format_scores(scores), **scores)
    out.finish()


# --------------------------------------------------------------------------------------------------
# lfrig export


def _register_export(subparsers: argparse._SubParsersAction) -> None:
    export = subparsers.add_parser(
        "export",
        help="turn a reconstruction into metric depth, a PLY point cloud or mesh, a report or camera poses",
        description=(
            "Read RESULT_DIR (written by lfrig reconstruct: disparity.pfm and result.json with focal_px, "
            "pitch_mm, disparity_offset, source), convert disparity to depth in mm "
            "(Z = focal_px * pitch_mm / (d + disparity_offset)), and write what is asked for. Pixels without "
            "a trustworthy disparity are left out: not finite, confidence (confidence.pfm, the probability that "
            "the disparity is within 0.07 px of the truth) below --min-confidence, or outside the range the "
            "method searched (--keep-all keeps them), and the number kept is printed; the PLY carries each vertex's "
            "confidence as a float property. The mesh is cut where the disparity breaks against its local slope "
            "(--max-step) or depth jumps (--max-jump). Coordinates are mm (float32) in the centre camera's frame "
            "(x right, y down, z forward); the PLY header records units, frame, lfrig's version, the command "
            "and the source as comments."
        ),
    )
    export.add_argument("result_dir", type=Path, metavar="RESULT_DIR", help="output folder of lfrig reconstruct")
    export.add_argument("--ply", type=output_file, metavar="OUT.ply", help="write a PLY point cloud or mesh here")
    kind = export.add_mutually_exclusive_group()
    kind.add_argument("--mesh", dest="kind", action="store_const", const="mesh",
                      help="triangulate the depth grid, cut where the surface breaks (the default)")
    kind.add_argument("--points", dest="kind", action="store_const", const="points",
                      help="a coloured point cloud with normals")
    export.set_defaults(kind="mesh")
    export.add_argument("--ascii", action="store_true", help="ASCII PLY instead of binary")
    export.add_argument("--poisson", action="store_true",
                        help="mesh by screened Poisson reconstruction of the point cloud instead of the grid")
    export.add_argument("--max-step", type=positive_float, default=None, metavar="FOOTPRINTS",
                        help="mesh: neighbours whose disparity steps, beyond its local slope, by more than this many "
                             "pixel footprints (the width a pixel covers at that depth) are not joined (default 8)")
    export.add_argument("--max-jump", type=positive_float, default=None, metavar="FRACTION",
                        help="neighbours whose depths differ by more than this fraction are not joined "
                             "(default 0.05)")
    export.add_argument("--min-confidence", type=finite_float, default=None, metavar="C",
                        help="leave out pixels whose confidence (the probability of being within 0.07 px of "
                             "the truth) is below C, in [0, 1] (default 0.5)")
    export.add_argument("--keep-all", action="store_true",
                        help="keep every finite pixel, whatever its confidence or range")
    export.add_argument("--depth", type=output_file, action="append", default=[], metavar="DEPTH.{pfm,png,npy}",
                        help="also write the depth map in mm (16-bit PNG records its scale); may repeat")
    export.add_argument("--report", type=output_folder, metavar="REPORT_DIR",
                        help="also write an HTML report (index.html, PNG figures and an interactive 3D view of "
                             "the --ply model, or of the kept points) into this folder")
    export.add_argument("--poses", type=output_folder, metavar="POSES_DIR",
                        help="also write the views' cameras into this folder: a COLMAP text model (cameras.txt, "
                             "images.txt, points3D.txt) and a NeRF-style transforms.json, in mm in the centre "
                             "camera's frame")
    export.add_argument("--quiet", action="store_true", help="no progress output")
    add_json_argument(export)
    camera = export.add_argument_group("camera (override result.json, e.g. for a scene without parameters.cfg)")
    focal, pitch, offset = _camera_flag_types()
    camera.add_argument("--focal-px", type=focal, help="focal length of the rectified views in pixels")
    camera.add_argument("--pitch-mm", type=pitch, help="grid pitch (distance between neighbouring views) in mm")
    camera.add_argument("--disparity-offset", type=offset, help="refocusing shift d0 in pixels per view step")
    export.set_defaults(handler=_export)


def _camera_flag_types():
    """``--focal-px``, ``--pitch-mm``, ``--disparity-offset`` within lfrig's camera bounds
    (:func:`recon.lf.params.camera_problem`)."""
    from recon.lf.params import FOCAL_PX_RANGE, MAX_DISPARITY_OFFSET_PX, PITCH_MM_RANGE

    return (float_range(*FOCAL_PX_RANGE), float_range(*PITCH_MM_RANGE),
            float_range(-MAX_DISPARITY_OFFSET_PX, MAX_DISPARITY_OFFSET_PX))


def _export(args: argparse.Namespace) -> None:
    from recon.errors import ExportError

    if args.ply is None and not args.depth and args.report is None and args.poses is None:
        raise ExportError("nothing to do: give --ply OUT.ply, --depth DEPTH.pfm, --report REPORT_DIR and/or "
                          "--poses POSES_DIR")
    if args.poisson and args.kind == "points":
        raise ExportError("--poisson makes a mesh; drop --points")
    if args.max_step is not None and not args.max_step > 0:
        raise ExportError(f"--max-step {args.max_step}: give a positive number of pixel footprints, e.g. 8")
    if args.max_jump is not None and not args.max_jump > 0:
        raise ExportError(f"--max-jump {args.max_jump}: give a positive fraction of depth, e.g. 0.05")
    if args.min_confidence is not None and not 0 <= args.min_confidence <= 1:
        raise ExportError(f"--min-confidence {args.min_confidence}: give a value in [0, 1], e.g. 0.5")

    import numpy as np

    from recon.cloud import MAX_RELATIVE_JUMP, MAX_STEP_FOOTPRINTS
    from recon.depth import write_depth
    from recon.export import MIN_CONFIDENCE, export_ply, result_input, trusted_pixels
    from recon.provenance import provenance as make_provenance
    from recon.result import read_result

    min_confidence = MIN_CONFIDENCE if args.min_confidence is None else args.min_confidence

    import contextlib

    from recon.progress import step

    result = read_result(args.result_dir)
    out = CommandReport(as_json=args.json)
    if args.ply is not None or args.depth:
        kept = _kept_line(result, min_confidence=min_confidence, keep_all=args.keep_all)
        out.line(kept, kept=kept)
    overrides = {"focal_px": args.focal_px, "pitch_mm": args.pitch_mm, "disparity_offset": args.disparity_offset}
    try:
        camera = result.camera(**overrides)
    except ExportError:
        if args.ply or args.depth or args.poses:
            raise
        camera = None  # a report without metric depth

    if args.poses is not None:
        from recon.poses import result_grid

        result_grid(result)  # before any file is written
    if args.ply is not None:
        # Poisson is one long open3d call: a line when it starts and one when it ends. (Other PLYs take about a
        # second for 512x512 px, and a line before them would come before their one-line errors.)
        meshing = step("export", "meshing (Poisson, ~20 s for 512x512 px)", quiet=args.quiet) if args.poisson \
            else contextlib.nullcontext()
        with meshing:
            summary = export_ply(
                args.ply, disparity_px=result.disparity_px, image=result.image, camera=camera, mask=result.mask,
                kind=args.kind, poisson=args.poisson, ascii=args.ascii,
                max_relative_jump=MAX_RELATIVE_JUMP if args.max_jump is None else args.max_jump,
                max_step_footprints=MAX_STEP_FOOTPRINTS if args.max_step is None else args.max_step,
                provenance=make_provenance(input=result_input(result), timings_s={}),
                confidence=result.confidence, min_confidence=min_confidence, search_range=result.search_range,
                keep_all=args.keep_all,
            )
        out.line(f"wrote {summary}" + (f"; left out {summary.pixels_unreliable} unreliable pixels (--keep-all keeps them)"
                                       if summary.pixels_unreliable else ""),
                 ply=args.ply, ply_summary=str(summary), pixels_unreliable=summary.pixels_unreliable)
    if args.depth:
        depth = camera.depth_mm(result.disparity_px)
        if result.mask is not None:
            depth[~result.mask] = float("nan")
        if not args.keep_all:
            depth[~trusted_pixels(result.disparity_px, confidence=result.confidence, min_confidence=min_confidence,
                                  search_range=result.search_range)] = float("nan")
        if not np.isfinite(depth).any():
            raise ExportError(f"{args.result_dir}: no pixel has a depth (none is finite, positive and trusted), so "
                              "the depth map would be empty; nothing written (--keep-all or a lower --min-confidence "
                              "keep more pixels)")
        for path in args.depth:
            try:
                write_depth(path, depth)
            except ValueError as error:  # a user's path, not a bug
                raise ExportError(f"{path}: {error}") from None
            out.line(f"wrote {path} (depth in mm)", depth=[str(p) for p in args.depth])
    if args.poses is not None:
        from recon.poses import export_poses

        poses = export_poses(result, args.poses, camera=camera)
        out.line(f"wrote {poses}", poses=args.poses, poses_summary=str(poses))
    if args.report is not None:
        from recon.report import report_for_result

        page = report_for_result(result, args.report, camera=camera, ply=args.ply)
        out.line(f"wrote {page}", report=page)
    out.finish()


def _kept_line(result, *, min_confidence: float, keep_all: bool) -> str:
    """One line: how many of the result's pixels the export keeps, and by what rule."""
    import numpy as np

    from recon.export import trusted_pixels

    finite = np.isfinite(result.disparity_px)
    if result.mask is not None:
        finite &= result.mask
    total = int(finite.sum())
    if keep_all:
        return f"kept {total} of {finite.size} pixels (every finite one: --keep-all)"
    kept = int((finite & trusted_pixels(result.disparity_px, confidence=result.confidence,
                                        min_confidence=min_confidence, search_range=result.search_range)).sum())
    rule = (f"confidence >= {min_confidence:g} and inside the searched range" if result.confidence is not None
            else "no confidence map: finite and inside the searched range")
    return f"kept {kept} of {finite.size} pixels ({100.0 * kept / max(finite.size, 1):.1f} %): {rule}"


# --------------------------------------------------------------------------------------------------
# lfrig batch


def _register_batch(subparsers: argparse._SubParsersAction) -> None:
    batch = subparsers.add_parser(
        "batch",
        help="run many reconstructions on a Dask cluster (local or by scheduler address)",
        description="Run work on a Dask cluster: a local one sized to this machine, or --scheduler tcp://HOST:PORT.",
    )
    actions = batch.add_subparsers(dest="batch_command", metavar="ACTION", required=True)
    rec = actions.add_parser(
        "reconstruct",
        help="reconstruct (and export) every capture, one task each",
        description=(
            "Reconstruct every CAPTURE_DIR into OUT_DIR/<its folder name>/ (the files of `lfrig reconstruct`, "
            "a PLY and batch.json), one cluster task per capture. Captures whose results are complete are "
            "skipped, so the same command resumes an interrupted batch. A failing capture is reported and "
            "the others go on. Without --scheduler a local cluster starts and stops with the command. "
            "See docs/scale-out.md."
        ),
    )
    rec.add_argument("captures", nargs="+", type=Path, metavar="CAPTURE_DIR",
                     help="light-field folders (capture or benchmark layout)")
    rec.add_argument("-o", "--output", type=output_folder, required=True, metavar="OUT_DIR", help="folder for the results")
    rec.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                     help="address of a running `dask scheduler` (default: start a local cluster)")
    rec.add_argument("--workers", type=positive_int, metavar="N",
                     help="local cluster: worker processes (default: one per core, at most one per capture "
                          "unless tiling)")
    rec.add_argument("--transfer", choices=("auto", "shared", "ship"), default="auto",
                     help="shared: workers read CAPTURE_DIRs and write OUT_DIR at the same paths; ship: views "
                          "are sent with each task and results sent back; auto: shared for a local cluster, "
                          "ship with --scheduler (default auto)")
    add_method_arguments(rec)  # the flags of `lfrig reconstruct`: the same flags give the same result folder
    rec.add_argument("--export", choices=("mesh", "points", "none"), default="mesh",
                     help="PLY written beside each result: mesh.ply, points.ply or none (default mesh)")
    rec.add_argument("--tile", type=positive_int, metavar="SIZE",
                     help="split each centre view into SIZE x SIZE tiles run as separate tasks, then stitch")
    rec.add_argument("--halo", type=nonnegative_int, metavar="PX", help="with --tile: halo in pixels (default: the method's)")
    rec.add_argument("--force", action="store_true", help="redo captures whose results are complete")
    rec.add_argument("--worker-timeout-s", type=positive_float, default=60.0, metavar="S",
                     help="with no worker connected for this long (at the start or after all were lost), say so "
                          "and stop; the captures not run are reported as failed (default 60)")
    rec.add_argument("--dashboard-address", type=host_port, default="127.0.0.1:8787", metavar="HOST:PORT",
                     help="local cluster: where the dashboard listens, a free port if this one is taken "
                          "(default 127.0.0.1:8787; all interfaces only when asked for by name, 0.0.0.0:PORT "
                          "or [::]:PORT)")
    add_json_argument(rec)
    rec.set_defaults(handler=_batch_reconstruct)


def _batch_reconstruct(args: argparse.Namespace) -> int:
    from recon.scale import ScaleError
    from recon.scale.batch import BatchRequest, format_summary, prepare_batch, run_batch
    from recon.scale.cluster import connect

    options = method_options(args)
    if args.tile is not None and args.tile < 8:
        raise ScaleError(f"--tile {args.tile}: tiles smaller than 8 pixels cost more in halo than they save")
    if args.halo is not None and args.tile is None:
        raise ScaleError("--halo needs --tile")
    if args.tile is not None:
        from recon.scale.tiles import tile_rule

        tile_rule(args.method)  # fail now, not on every capture
    request = BatchRequest(method=args.method, options=options,
                           export=None if args.export == "none" else args.export, tile=args.tile, halo=args.halo)
    plan = prepare_batch(args.captures, args.output, request=request, force=args.force)
    transfer = args.transfer if args.transfer != "auto" else ("ship" if args.scheduler else "shared")
    lines = sys.stderr if args.json else sys.stdout  # with --json, stdout holds only the JSON object

    def show(outcome, done: int, total: int) -> None:
        what = {"ok": "done", "skipped": "already complete", "failed": "FAILED"}[outcome.status]
        took = f" in {outcome.seconds:.1f} s" if outcome.seconds is not None and outcome.status == "ok" else ""
        error = f": {outcome.error}" if outcome.error else ""
        print(f"[{done}/{total}] {outcome.name}: {what}{took}{error}", file=lines, flush=True)

    if not plan.todo:
        outcomes = run_batch(None, plan, transfer=transfer, on_outcome=show)
    else:
        with connect(scheduler=args.scheduler, workers=args.workers, tasks=None if args.tile else len(plan.todo),
                     dashboard_address=args.dashboard_address, timeout_s=args.worker_timeout_s) as connection:
            print(connection.describe() + f"; data: {transfer}", file=lines, flush=True)
            print(f"dashboard: {connection.dashboard or 'none (install bokeh on the scheduler for one)'}", file=lines,
                  flush=True)
            if args.scheduler is None and args.dashboard_address.rpartition(":")[0].strip("[]") in ALL_INTERFACES:
                print(f"note: the dashboard listens on every interface ({args.dashboard_address}): anyone who can "
                      "reach this machine can see it", file=lines, flush=True)
            outcomes = run_batch(connection.client, plan, transfer=transfer, threads=connection.task_threads,
                                 on_outcome=show, on_note=lambda text: print(f"note: {text}", file=lines, flush=True),
                                 no_worker_timeout_s=args.worker_timeout_s)
    out = CommandReport(as_json=args.json)
    out.line("\n" + format_summary(outcomes), output=str(args.output), captures=[o.as_dict() for o in outcomes])
    out.finish()
    failed = [o for o in outcomes if o.status == "failed"]
    for o in failed:
        if o.detail:
            print(f"\n{o.name}: {o.detail}", file=sys.stderr)
    return 1 if failed else 0


def _register_import(subparsers: argparse._SubParsersAction) -> None:
    from recon.lf.params import MAX_GRID_SIDE

    imp = subparsers.add_parser(
        "import",
        help="turn a folder of views from another tool into an lfrig capture",
        description=(
            "Import the views in SRC as a complete lfrig capture folder: by a file-name pattern with the row and "
            "column (--pattern 'view_{u}_{v}.png', 'img_{v:02d}-{u:02d}.tif'), by capture order (--order with "
            "--rows/--cols; files sorted naturally, or numbered by a pattern's {i}), or from a folder in the 4D "
            "Light Field Benchmark's layout. Every file is read and checked before anything is written; the "
            "capture appears at CAPTURE only when complete."
        ),
    )
    imp.add_argument("src", type=Path, metavar="SRC",
                     help="folder holding the views, one mosaic image (with --mosaic) or an HDF5 light field (.h5)")
    imp.add_argument("-o", "--output", type=Path, required=True, metavar="CAPTURE", help="new capture folder")
    imp.add_argument("--pattern", help="file names: {u}/{row} and {v}/{col} fields, or {i} with --order; {y}/{x} match an "
                     "unused float position; 'stanford' for the Stanford archive's out_RR_CC_<y>_<x>_.png")
    imp.add_argument("--order", choices=("serpentine", "raster"),
                     help="files are in capture order (serpentine: every other row right to left, as lfrig captures)")
    imp.add_argument("--rows", type=int_range(1, MAX_GRID_SIDE), help="grid rows (u) (not needed for a benchmark folder)")
    imp.add_argument("--cols", type=int_range(1, MAX_GRID_SIDE), help="grid columns (v)")
    imp.add_argument("--index-base", type=int_range(0, 10**9), default=0, help="the number the indices in the names start at")
    focal, pitch, _ = _camera_flag_types()
    imp.add_argument("--pitch-mm", type=pitch, help="distance between neighbouring views (required unless a benchmark folder gives it)")
    imp.add_argument("--focal-px", type=focal, help="focal length of the views in pixels")
    imp.add_argument("--principal-point-px", type=finite_float, nargs=2, metavar=("CX", "CY"), help="principal point, x first")
    imp.add_argument("--disparity-range", type=finite_float, nargs=2, metavar=("MIN", "MAX"),
                     help="disparity the scene spans, pixels per view step")
    imp.add_argument("--mosaic", type=_grid_size, metavar="ROWSxCOLS",
                     help="SRC is one image holding every view, ROWS tiles down and COLS across")
    imp.add_argument("--transpose", action="store_true", help="swap the grid's rows and columns (before any flip)")
    imp.add_argument("--flip-u", action="store_true", help="reverse the grid's rows (the first row becomes the last)")
    imp.add_argument("--flip-v", action="store_true", help="reverse the grid's columns")
    imp.add_argument("--no-order-check", action="store_true",
                     help="skip the check that warns when the views' order looks mirrored")
    imp.add_argument("--quiet", action="store_true", help="no progress output")
    add_json_argument(imp)
    imp.set_defaults(handler=_import)


def _grid_size(text: str) -> tuple[int, int]:
    """``9x9`` -> ``(9, 9)``: rows first."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() and int(p) >= 1 for p in parts):
        raise argparse.ArgumentTypeError(f"{text!r}: give the grid as ROWSxCOLS, e.g. 9x9")
    return int(parts[0]), int(parts[1])


def _import(args: argparse.Namespace) -> None:
    from recon.lf.importer import import_views
    from recon.progress import Progress

    warnings: list[str] = []

    def warn(text: str) -> None:
        warnings.append(text)
        print(f"lfrig: warning: {text}", file=sys.stderr)

    with Progress("import", quiet=args.quiet) as bar:
        path = import_views(
            args.src, args.output, pattern=args.pattern, order=args.order, rows=args.rows, cols=args.cols,
            index_base=args.index_base, pitch_mm=args.pitch_mm, focal_px=args.focal_px,
            principal_point_px=tuple(args.principal_point_px) if args.principal_point_px else None,
            disparity_range=tuple(args.disparity_range) if args.disparity_range else None, mosaic=args.mosaic,
            transpose=args.transpose, flip_u=args.flip_u, flip_v=args.flip_v, check_order=not args.no_order_check,
            warn=warn, progress=bar,
        )
    from recon.pipeline import metric_camera_missing

    missing = metric_camera_missing(path)
    if missing:
        flags = " and ".join("--" + name.replace("_", "-") for name in missing)
        message = (f"{path} records no {' or '.join(missing)}, so it will only give disparity: no depth, point "
                   f"cloud or mesh. Import again with {flags} for metric output, or give them to `lfrig export` later.")
        print(f"lfrig: warning: {message}", file=sys.stderr)
        warnings.append(message)
    out = CommandReport(as_json=args.json)
    out.line(f"{path}: imported from {args.src}, complete", output=path, source=args.src, complete=True,
             warnings=warnings)
    out.finish()
