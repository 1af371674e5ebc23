"""``lfrig batch reconstruct``: many captures (or tiles of a large one) on a Dask cluster.

Parse, call :mod:`recon.scale`, print. Dask is imported inside the handler so ``lfrig --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from recon.commands import add_method_arguments


def register(subparsers: argparse._SubParsersAction) -> None:
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
    rec.add_argument("-o", "--output", type=Path, required=True, metavar="OUT_DIR", help="folder for the results")
    rec.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                     help="address of a running `dask scheduler` (default: start a local cluster)")
    rec.add_argument("--workers", type=int, metavar="N",
                     help="local cluster: worker processes (default: one per core, at most one per capture "
                          "unless tiling)")
    rec.add_argument("--transfer", choices=("auto", "shared", "ship"), default="auto",
                     help="shared: workers read CAPTURE_DIRs and write OUT_DIR at the same paths; ship: views "
                          "are sent with each task and results sent back; auto: shared for a local cluster, "
                          "ship with --scheduler (default auto)")
    add_method_arguments(rec)  # the flags of `lfrig reconstruct`: the same flags give the same result folder
    rec.add_argument("--export", choices=("mesh", "points", "none"), default="mesh",
                     help="PLY written beside each result: mesh.ply, points.ply or none (default mesh)")
    rec.add_argument("--tile", type=int, metavar="SIZE",
                     help="split each centre view into SIZE x SIZE tiles run as separate tasks, then stitch")
    rec.add_argument("--halo", type=int, metavar="PX", help="with --tile: halo in pixels (default: the method's)")
    rec.add_argument("--force", action="store_true", help="redo captures whose results are complete")
    rec.add_argument("--dashboard-address", default="127.0.0.1:8787", metavar="HOST:PORT",
                     help="local cluster: where the dashboard listens, a free port if this one is taken "
                          "(default 127.0.0.1:8787)")
    rec.set_defaults(handler=_batch_reconstruct)


def _batch_reconstruct(args: argparse.Namespace) -> int:
    from recon.commands import method_options
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

    def show(outcome, done: int, total: int) -> None:
        what = {"ok": "done", "skipped": "already complete", "failed": "FAILED"}[outcome.status]
        took = f" in {outcome.seconds:.1f} s" if outcome.seconds is not None and outcome.status == "ok" else ""
        error = f": {outcome.error}" if outcome.error else ""
        print(f"[{done}/{total}] {outcome.name}: {what}{took}{error}", flush=True)

    if not plan.todo:
        outcomes = run_batch(None, plan, transfer=transfer, on_outcome=show)
    else:
        with connect(scheduler=args.scheduler, workers=args.workers, tasks=None if args.tile else len(plan.todo),
                     dashboard_address=args.dashboard_address) as connection:
            print(connection.describe() + f"; data: {transfer}", flush=True)
            print(f"dashboard: {connection.dashboard or 'none (install bokeh on the scheduler for one)'}", flush=True)
            outcomes = run_batch(connection.client, plan, transfer=transfer, threads=connection.task_threads,
                                 on_outcome=show)
    print()
    print(format_summary(outcomes))
    failed = [o for o in outcomes if o.status == "failed"]
    for o in failed:
        if o.detail:
            print(f"\n{o.name}: {o.detail}", file=sys.stderr)
    return 1 if failed else 0
