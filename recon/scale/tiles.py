"""One large light field as tiles of the centre view, each with a halo, run anywhere and stitched.

A tile is a rectangle of the centre view (its **core**); the light field is cropped to the core grown
by a **halo** on every side (clipped to the image) in *every* view at the same rectangle, so a
pixel ``(y, x)`` of the crop is the pixel ``(y + top, x + left)`` of the whole image in every view and
the sign convention of ``docs/conventions.md`` holds inside the crop unchanged. The method runs on
the crop; only the core of its result is kept; the cores partition the image.

How wide the halo must be is the method's business: :data:`TILE_RULES` holds, per method, a rule
that fills in the options every tile must share (the disparity range: it bounds the halo and must not
be re-derived per tile) and returns the halo in pixels.

- **baseline**: tile-local, exactly. Its disparity at a pixel depends on the per-pixel cost inside
  the ``window x window`` box around it, and the cost at a pixel on the other views sampled
  (bilinearly) at most ``max|d| * max(|u - u0|, |v - v0|)`` pixels away. So
  ``halo = window // 2 + ceil(max|d| * max view offset) + 1`` (one more pixel for the bilinear
  neighbour, so no sample inside the core's reach is clamped at the crop's edge). The stitched map
  equals the untiled one bit for bit (``tests/test_scale_tiles.py``).
- **entropy**: the estimator's phase plan (:data:`recon.entropy.plan.PLAN`) run in order, its
  tile-local phases tile by tile (each tile given the whole image's maps and numbers it reads), its
  whole-image phases (hole filling, search range, TV refinement) on the stitched maps. The halo is
  the sum of the tile-local steps' reaches, each declared beside its step
  (:func:`recon.entropy.plan.halo_px`); window sums are exact int64 sums, so a crop sums like the
  whole image. The stitched map equals the untiled one (bit for bit on the scene suite;
  ``tests/test_scale_tiles.py`` asserts 1e-4 px/view).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon.lf.lightfield import LightField, max_view_offset, view_shift_px  # noqa: F401 (max_view_offset re-exported)
from recon.progress import ProgressCallback, report
from recon.scale import ScaleError


@dataclass(frozen=True)
class Tile:
    """One tile: ``core`` and ``crop`` are ``(top, bottom, left, right)`` half-open pixel bounds in
    the whole centre view; ``crop`` contains ``core``."""

    index: int
    core: tuple[int, int, int, int]
    crop: tuple[int, int, int, int]

    @property
    def inner(self) -> tuple[slice, slice]:
        """``(rows, cols)`` slices of the core inside the crop."""
        top, bottom, left, right = self.core
        return slice(top - self.crop[0], bottom - self.crop[0]), slice(left - self.crop[2], right - self.crop[2])


def _bounds(length: int, tile: int) -> list[tuple[int, int]]:
    count = max(1, math.ceil(length / tile))
    edges = [round(k * length / count) for k in range(count + 1)]
    return list(zip(edges[:-1], edges[1:]))


def plan_tiles(image_shape: tuple[int, int], *, tile: int, halo: int) -> list[Tile]:
    """Split an ``(H, W)`` image into tiles of at most ``tile x tile`` core pixels (sizes balanced so
    no tile is a sliver), each cropped with ``halo`` pixels around it, clipped to the image.

    The cores partition the image; tiles are listed row by row.
    """
    if tile < 1:
        raise ValueError(f"tile size must be at least 1 pixel; got {tile}")
    if halo < 0:
        raise ValueError(f"halo must be >= 0 pixels; got {halo}")
    height, width = image_shape
    tiles = []
    for top, bottom in _bounds(height, tile):
        for left, right in _bounds(width, tile):
            crop = (max(top - halo, 0), min(bottom + halo, height), max(left - halo, 0), min(right + halo, width))
            tiles.append(Tile(index=len(tiles), core=(top, bottom, left, right), crop=crop))
    return tiles


def crop_lightfield(lf: LightField, tile: Tile) -> LightField:
    """The light field cut to ``tile.crop`` in every view (a contiguous copy, nothing else shared)."""
    top, bottom, left, right = tile.crop
    return LightField(
        views=np.ascontiguousarray(lf.views[:, :, top:bottom, left:right]),
        pitch_mm=lf.pitch_mm, focal_px=lf.focal_px, disparity_range=lf.disparity_range,
        disparity_offset=lf.disparity_offset, metadata={"tile": tile.index, "crop": list(tile.crop)},
        source=None,
    )


def stitch(image_shape: tuple[int, int], tiles: list[Tile], results: list[np.ndarray]) -> np.ndarray:
    """Put the core of each tile's ``(..., crop H, crop W)`` result into one ``(..., H, W)`` float32
    map (leading axes, e.g. several maps stacked, are kept)."""
    lead = results[0].shape[:-2] if results else ()
    out = np.full(lead + tuple(image_shape), np.nan, dtype=np.float32)
    for tile, result in zip(tiles, results):
        top, bottom, left, right = tile.crop
        if result.shape[-2:] != (bottom - top, right - left) or result.shape[:-2] != lead:
            raise ScaleError(
                f"tile {tile.index}: the method returned a {result.shape[-1]}x{result.shape[-2]} map for a "
                f"{right - left}x{bottom - top} crop; a tiled method must keep the crop's size"
            )
        rows, cols = tile.inner
        out[..., tile.core[0]:tile.core[1], tile.core[2]:tile.core[3]] = result[..., rows, cols]
    return out


# --------------------------------------------------------------------------------------------------
# what each method needs
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TileRule:
    """How to tile one method.

    ``resolve(lf, options) -> options`` fills in what every tile must share (at least
    ``disparity_range``); ``halo_px(lf, resolved_options) -> int``; ``exact`` says whether the
    stitched result equals the untiled one; ``note`` says why not, when it does not.
    """

    resolve: Callable[[LightField, dict[str, Any]], dict[str, Any]]
    halo_px: Callable[[LightField, dict[str, Any]], int]
    exact: bool
    note: str = ""
    #: ``run(lf, options, map_tiles) -> MethodResult`` for a method with whole-image steps between
    #: tile-local ones (its disparity and its own maps, as an untiled run makes them);
    #: ``map_tiles(task, maps=()) -> (..., H, W)`` runs
    #: ``task(crop, map_crops, options, threads) -> (..., crop H, crop W)`` on every tile (each of
    #: ``maps``, ``(H, W)`` arrays, cut to the tile's crop) and stitches. ``None``: one
    #: :func:`run_tile` per tile.
    run: Callable[..., np.ndarray] | None = None
    #: How many rounds of tiles ``run`` makes (for the progress), a number or a function giving it.
    rounds: int | Callable[[], int] = 1


def _baseline_resolve(lf: LightField, options: dict[str, Any]) -> dict[str, Any]:
    from recon.baseline import DEFAULT_DISPARITY_RANGE

    out = dict(options)
    out["disparity_range"] = tuple(options.get("disparity_range") or lf.disparity_range or DEFAULT_DISPARITY_RANGE)
    return out


def _baseline_halo(lf: LightField, options: dict[str, Any]) -> int:
    from recon.baseline import estimate_baseline

    window = options.get("window", inspect.signature(estimate_baseline).parameters["window"].default)
    return int(window) // 2 + view_shift_px(options["disparity_range"], lf.grid_shape) + 1


def _entropy_options(options: dict[str, Any]):
    from recon.entropy import make_options

    return make_options(**{k: v for k, v in options.items() if v is not None})


def _entropy_resolve(lf: LightField, options: dict[str, Any]) -> dict[str, Any]:
    opts = _entropy_options(options)
    out = dict(options)
    known = opts.disparity_range or lf.disparity_range
    if known is None and opts.discover_range:  # the whole image's coarse search, as untiled
        from recon.entropy.plan import start

        known = start(lf, opts).initial_range
    out["disparity_range"] = tuple(known or opts.initial_range)
    return out


def _entropy_phase_task(crop: LightField, maps: list[np.ndarray], options: dict[str, Any],
                        threads: int | None) -> np.ndarray:
    """One tile-local phase of the estimator on one tile (``recon.entropy.plan.run_phase_on_tile``)."""
    from recon.entropy.plan import PLAN, run_phase_on_tile
    from recon.scale.cluster import limit_threads

    limit_threads(threads)
    options = dict(options)  # a retried task gets the same dict again
    name = options.pop("_phase")
    phase = next(p for p in PLAN if p.name == name)
    shared = options.pop("_shared")
    return run_phase_on_tile(crop, phase, maps, options=_entropy_options(options), shared=shared)


def _entropy_run(lf: LightField, options: dict[str, Any], map_tiles):
    """The estimator's phases (``recon.entropy.plan.PLAN``) in order: tile-local ones tile by tile
    (each tile given the whole image's maps it reads and its shared numbers, its outputs stitched),
    whole-image ones here. Returns a :class:`recon.methods.MethodResult` with the whole
    :class:`recon.entropy.EntropyResult` (the confidence and every map of an untiled run) and its
    files."""
    from recon.entropy.estimate import result_of
    from recon.entropy.outputs import write_outputs
    from recon.entropy.plan import PLAN, run_phase, shared_numbers, start, take_tiles
    from recon.entropy.regions import smooth_tolerance_abs
    from recon.methods import MethodResult

    opts = _entropy_options(options)
    state = start(lf, opts)
    common = {k: v for k, v in options.items() if v is not None}
    for phase in PLAN:
        if phase.tile_local:
            stitched = map_tiles(_entropy_phase_task, maps=[getattr(state, name) for name in phase.reads],
                                 options={**common, "_phase": phase.name, "_shared": shared_numbers(state)})
            take_tiles(state, phase, stitched)
            del stitched
        else:
            run_phase(state, phase)
    # the numbers the tiles' region step reports, the same for every tile
    state.region_info = {"noise_sigma": state.noise_sigma,
                         "smooth_tolerance_abs": smooth_tolerance_abs(opts.smooth_tolerance, state.noise_sigma)}
    result = result_of(state)
    return MethodResult(disparity=result.disparity, extras=result, options=options,
                        write_extras=lambda folder: write_outputs(result, folder))


def _entropy_rounds() -> int:
    from recon.entropy.plan import PLAN

    return sum(phase.tile_local for phase in PLAN)


def _entropy_halo(lf: LightField, options: dict[str, Any]) -> int:
    from recon.entropy.plan import halo_px
    from recon.entropy.state import Reach

    opts = _entropy_options(options)
    return halo_px(opts, Reach(lf.grid_shape, tuple(opts.disparity_range)))


#: Tiling rule per method name.
TILE_RULES: dict[str, TileRule] = {
    "baseline": TileRule(resolve=_baseline_resolve, halo_px=_baseline_halo, exact=True),
    "entropy": TileRule(
        resolve=_entropy_resolve, halo_px=_entropy_halo, exact=True, run=_entropy_run, rounds=_entropy_rounds,
        note="bit-identical on the scene suite; asserted to 1e-4 px/view",
    ),
}


def tile_rule(method: str) -> TileRule:
    try:
        return TILE_RULES[method]
    except KeyError:
        raise ScaleError(
            f"method {method!r} has no tiling rule (its halo is unknown); tile one of "
            f"{', '.join(sorted(TILE_RULES))}, or run it untiled"
        ) from None


# --------------------------------------------------------------------------------------------------
# running
# --------------------------------------------------------------------------------------------------


def run_tile(crop: LightField, method: str, options: dict[str, Any], threads: int | None = None) -> np.ndarray:
    """One tile's disparity ``(crop H, crop W)`` float32 (a cluster task; ``threads`` caps numba/OpenCV)."""
    from recon.methods import run_method
    from recon.scale.cluster import limit_threads

    limit_threads(threads)
    return run_method(method, crop, **options).disparity


@dataclass
class TiledResult:
    """The stitched ``(H, W)`` disparity, the tiles, the halo and the options every tile ran with;
    for a method whose rule has its own ``run`` (entropy) also its result object (``extras``: an
    :class:`recon.entropy.EntropyResult` with the confidence) and the writer of its own maps."""

    disparity: np.ndarray
    tiles: list[Tile]
    halo: int
    options: dict[str, Any]
    exact: bool
    extras: Any = None
    write_extras: Callable[[Any], list[Any]] | None = None

    def describe(self) -> dict[str, Any]:
        """What ``result.json`` records about the tiling."""
        top, bottom, left, right = self.tiles[0].core
        return {"tiles": len(self.tiles), "tile_px": [right - left, bottom - top], "halo_px": self.halo,
                "exact": self.exact, "disparity_range": list(self.options["disparity_range"])}


def tiled_disparity(
    lf: LightField,
    *,
    method: str,
    options: dict[str, Any] | None = None,
    tile: int,
    halo: int | None = None,
    client: Any = None,
    threads: int | None = None,
    progress: ProgressCallback | None = None,
    runner: Callable[..., np.ndarray] = run_tile,
) -> TiledResult:
    """The centre view's disparity of ``lf``, computed tile by tile and stitched.

    Parameters
    ----------
    lf
        The whole light field (the caller holds it; each tile's crop is sent to a worker).
    method, options
        As for :func:`recon.methods.run_method`; the method's :class:`TileRule` fills in the disparity
        range so all tiles search the same one.
    tile
        Core side in pixels.
    halo
        Pixels around each core; default the method's :attr:`TileRule.halo_px`. A smaller halo gives
        wrong pixels along the tile seams.
    client
        A ``distributed.Client``: tiles run as tasks (as many at once as the cluster has threads).
        ``None``: one after the other in this process.
    threads
        numba/OpenCV threads per tile task (``None``: the worker's setting).
    progress
        ``progress(fraction, message)`` (:mod:`recon.progress`) as tiles finish, or ``None``.
    runner
        ``runner(crop, method, options, threads) -> (crop H, crop W)``; default :func:`run_tile`.
        Not used for a method whose rule has its own ``run`` (entropy: a round of tiles per tile-local phase).

    Returns
    -------
    :class:`TiledResult`; ``disparity`` is ``(H, W)`` float32, pixels per view step.
    """
    rule = tile_rule(method)
    resolved = rule.resolve(lf, dict(options or {}))
    halo = rule.halo_px(lf, resolved) if halo is None else int(halo)
    tiles = plan_tiles(lf.image_shape, tile=tile, halo=halo)
    rounds = rule.rounds() if callable(rule.rounds) else rule.rounds
    done_before = [0]

    def map_tiles(task, maps=(), options=resolved):
        def cut(t):
            top, bottom, left, right = t.crop
            return [np.ascontiguousarray(m[top:bottom, left:right]) for m in maps]

        total = rounds * len(tiles)
        results: list[np.ndarray | None] = [None] * len(tiles)
        if client is None:
            for i, t in enumerate(tiles):
                results[i] = task(crop_lightfield(lf, t), cut(t), dict(options), threads)
                report(progress, (done_before[0] + i + 1) / total, "tiles")
        else:
            from distributed import as_completed

            futures = {}
            for t in tiles:
                crop = client.scatter(crop_lightfield(lf, t), hash=False)
                futures[client.submit(task, crop, cut(t), dict(options), threads, pure=False)] = t.index
            for done, future in enumerate(as_completed(futures), start=1):
                results[futures[future]] = future.result()
                report(progress, (done_before[0] + done) / total, "tiles")
        done_before[0] += len(tiles)
        return stitch(lf.image_shape, tiles, results)

    extras = write_extras = None
    if rule.run is not None:
        made = rule.run(lf, resolved, map_tiles)
        disparity = made.disparity.astype(np.float32)
        extras, write_extras = made.extras, made.write_extras
    else:
        disparity = map_tiles(lambda crop, _maps, opts, th: runner(crop, method, opts, th))
    return TiledResult(disparity=disparity, tiles=tiles, halo=halo, options=resolved, exact=rule.exact,
                       extras=extras, write_extras=write_extras)


def tiled_estimator(*, tile: int, halo: int | None = None, client: Any = None, threads: int | None = None,
                    record: dict[str, Any] | None = None):
    """A :data:`recon.pipeline.Estimator` that tiles: on ``client``; inside a cluster task, on that
    task's cluster (the task steps aside while its tiles run); elsewhere, in this process.

    ``record``, when given, receives :meth:`TiledResult.describe` (before ``result.json`` is
    written). A method whose rule runs its own phases (entropy) hands back its own maps too, the
    confidence among them, and they are written as an untiled run writes them; for the others a
    tiled result has only the disparity.
    """
    from recon.methods import MethodResult

    def estimate(lf: LightField, method: str, options: dict[str, Any], progress: Any) -> MethodResult:
        def run(c):
            result = tiled_disparity(lf, method=method, options=options, tile=tile, halo=halo, client=c,
                                     threads=threads, progress=progress)
            if record is not None:
                record.update(result.describe())
            return MethodResult(disparity=result.disparity, extras=result.extras, options=result.options,
                                write_extras=result.write_extras)

        if client is not None:
            return run(client)
        try:
            from distributed import get_worker, worker_client

            get_worker()
        except (ImportError, ValueError):
            return run(None)
        with worker_client() as c:
            return run(c)

    return estimate
