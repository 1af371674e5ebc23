"""``lfrig export``: a reconstruction folder -> PLY point cloud or mesh, depth map, report."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    export = subparsers.add_parser(
        "export",
        help="turn a reconstruction into metric depth and a PLY point cloud or mesh",
        description=(
            "Read RESULT_DIR (written by lfrig reconstruct: disparity.pfm and result.json with focal_px, "
            "pitch_mm, disparity_offset, source), convert disparity to depth in mm "
            "(Z = focal_px * pitch_mm / (d + disparity_offset)), and write what is asked for. Pixels without "
            "a trustworthy disparity are left out; the mesh is cut where depth jumps. Coordinates are mm in "
            "the centre camera's frame (x right, y down, z forward)."
        ),
    )
    export.add_argument("result_dir", type=Path, metavar="RESULT_DIR", help="output folder of lfrig reconstruct")
    export.add_argument("--ply", type=Path, metavar="OUT.ply", help="write a PLY point cloud or mesh here")
    kind = export.add_mutually_exclusive_group()
    kind.add_argument("--mesh", dest="kind", action="store_const", const="mesh",
                      help="triangulate the depth grid, cut at depth jumps (the default)")
    kind.add_argument("--points", dest="kind", action="store_const", const="points",
                      help="a coloured point cloud with normals")
    export.set_defaults(kind="mesh")
    export.add_argument("--ascii", action="store_true", help="ASCII PLY instead of binary")
    export.add_argument("--poisson", action="store_true",
                        help="mesh by screened Poisson reconstruction of the point cloud instead of the grid")
    export.add_argument("--max-jump", type=float, default=None, metavar="FRACTION",
                        help="neighbours whose depths differ by more than this fraction are not joined "
                             "(default 0.05)")
    export.add_argument("--depth", type=Path, action="append", default=[], metavar="DEPTH.{pfm,png,npy}",
                        help="also write the depth map in mm (16-bit PNG records its scale); may repeat")
    export.add_argument("--report", type=Path, metavar="REPORT_DIR",
                        help="also write an HTML report (index.html and PNG figures) into this folder")
    camera = export.add_argument_group("camera (override result.json, e.g. for a scene without parameters.cfg)")
    camera.add_argument("--focal-px", type=float, help="focal length of the rectified views in pixels")
    camera.add_argument("--pitch-mm", type=float, help="grid pitch (distance between neighbouring views) in mm")
    camera.add_argument("--disparity-offset", type=float, help="refocusing shift d0 in pixels per view step")
    export.set_defaults(handler=_export)


def _export(args: argparse.Namespace) -> None:
    from recon.export import ExportError

    if args.ply is None and not args.depth and args.report is None:
        raise ExportError("nothing to do: give --ply OUT.ply, --depth DEPTH.pfm and/or --report REPORT_DIR")
    if args.poisson and args.kind == "points":
        raise ExportError("--poisson makes a mesh; drop --points")
    if args.max_jump is not None and not args.max_jump > 0:
        raise ExportError(f"--max-jump {args.max_jump}: give a positive fraction of depth, e.g. 0.05")

    from recon.cloud import MAX_RELATIVE_JUMP
    from recon.depth import disparity_to_depth, write_depth
    from recon.export import export_ply, missing_camera_error, read_result, result_camera

    result = read_result(args.result_dir)
    camera, missing = result_camera(result, focal_px=args.focal_px, pitch_mm=args.pitch_mm,
                                    disparity_offset=args.disparity_offset)
    if missing and (args.ply or args.depth):
        raise missing_camera_error(result, missing)

    if args.ply is not None:
        summary = export_ply(
            args.ply, disparity_px=result.disparity_px, image=result.image, **camera,
            principal_point_px=result.principal_point_px, mask=result.mask, kind=args.kind,
            poisson=args.poisson, ascii=args.ascii,
            max_relative_jump=MAX_RELATIVE_JUMP if args.max_jump is None else args.max_jump,
        )
        print(f"wrote {summary}")
    if args.depth:
        depth = disparity_to_depth(result.disparity_px, **camera)
        if result.mask is not None:
            depth[~result.mask] = float("nan")
        for path in args.depth:
            try:
                write_depth(path, depth)
            except ValueError as error:  # a user's path, not a bug
                raise ExportError(f"{path}: {error}") from None
            print(f"wrote {path} (depth in mm)")
    if args.report is not None:
        from recon.report import report_for_result

        page = report_for_result(result, args.report, **({} if missing else {"camera": camera}))
        print(f"wrote {page}")
