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
- **entropy**: two tile-local phases with whole-image steps between them (:func:`_entropy_run`):
  the noise sigma of the whole centre view is computed once and given to every tile; tiles return
  the raw initial estimate; the whole image fills its black holes and takes the layer map's
  minimum (the disparity histogram's bin origin); tiles run regions, windows and the line search
  (window sums are exact int64 sums, so a crop sums like the whole image); the whole image runs
  the TV refinement (Eq. 13) with its hole filling. The halo covers the chain of local steps
  (initial estimate, layer median, occlusion warp, largest window, line search). The stitched map
  equals the untiled one (bit for bit on the scene suite; ``tests/test_scale_tiles.py`` asserts
  1e-4 px/view).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon.lf.lightfield import LightField
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


def max_view_offset(grid_shape: tuple[int, int]) -> int:
    """``max |u - u0|, |v - v0|`` over the grid: how many view steps the farthest view is away."""
    rows, cols = grid_shape
    return max(rows // 2, rows - 1 - rows // 2, cols // 2, cols - 1 - cols // 2)


def _shift_px(disparity_range: tuple[float, float], grid_shape: tuple[int, int]) -> int:
    """``ceil(max|d| * max view offset)``: the farthest a view is sampled from a pixel."""
    return math.ceil(max(abs(disparity_range[0]), abs(disparity_range[1])) * max_view_offset(grid_shape) - 1e-9)


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
    #: ``run(lf, options, map_tiles) -> (H, W)`` for a method with whole-image steps between
    #: tile-local ones; ``map_tiles(task, maps=()) -> (..., H, W)`` runs
    #: ``task(crop, map_crops, options, threads) -> (..., crop H, crop W)`` on every tile (each of
    #: ``maps``, ``(H, W)`` arrays, cut to the tile's crop) and stitches. ``None``: one
    #: :func:`run_tile` per tile.
    run: Callable[..., np.ndarray] | None = None


def _baseline_resolve(lf: LightField, options: dict[str, Any]) -> dict[str, Any]:
    from recon.baseline import DEFAULT_DISPARITY_RANGE

    out = dict(options)
    out["disparity_range"] = tuple(options.get("disparity_range") or lf.disparity_range or DEFAULT_DISPARITY_RANGE)
    return out


def _baseline_halo(lf: LightField, options: dict[str, Any]) -> int:
    from recon.baseline import estimate_baseline

    window = options.get("window", inspect.signature(estimate_baseline).parameters["window"].default)
    return int(window) // 2 + _shift_px(options["disparity_range"], lf.grid_shape) + 1


def _entropy_resolve(lf: LightField, options: dict[str, Any]) -> dict[str, Any]:
    from recon.entropy import make_options

    opts = make_options(**{k: v for k, v in options.items() if v is not None})
    out = dict(options)
    known = opts.disparity_range or lf.disparity_range
    if known is None and opts.discover_range:  # the whole image's coarse search, as untiled
        from recon.entropy.estimate import unknown_range
        from recon.entropy.regions import noise_sigma

        gray = np.ascontiguousarray(lf.gray(), dtype=np.float32)
        U, V = lf.grid_shape
        known = unknown_range(gray, options=opts, noise_sigma=noise_sigma(gray[U // 2, V // 2]))
    out["disparity_range"] = tuple(known or opts.initial_range)
    return out


def _entropy_options(options: dict[str, Any]):
    from recon.entropy import make_options

    return make_options(**{k: v for k, v in options.items() if v is not None})


def _entropy_initial_task(crop: LightField, maps: list[np.ndarray], options: dict[str, Any],
                          threads: int | None) -> np.ndarray:
    """Tile-local phase 1: the raw nine-view estimate, its ambiguity and the flat mask."""
    from recon.entropy.estimate import estimate_disparity
    from recon.scale.cluster import limit_threads

    limit_threads(threads)
    options = dict(options)  # a retried task gets the same dict again
    shared = options.pop("_shared")
    r = estimate_disparity(crop, options=_entropy_options(options), stop_after="initial", **shared)
    return np.stack([r.initial_disparity, r.info["initial_ambiguity"], r.info["flat"]]).astype(np.float32)


def _entropy_matching_task(crop: LightField, maps: list[np.ndarray], options: dict[str, Any],
                           threads: int | None) -> np.ndarray:
    """Tile-local phase 2 (given the whole image's filled initial estimate): labels, windows and
    the line search up to the matched disparity, its labels and cost ambiguity."""
    from recon.entropy.estimate import estimate_disparity
    from recon.scale.cluster import limit_threads

    limit_threads(threads)
    options = dict(options)  # a retried task gets the same dict again
    shared = options.pop("_shared")
    d0, ambiguity0, noise_limited = maps
    r = estimate_disparity(crop, options=_entropy_options(options), stop_after="matching",
                           initial=(d0, ambiguity0.astype(np.int32)), noise_limited=noise_limited > 0.5,
                           **shared)
    return np.stack([r.matched_disparity, r.labels, r.info["ambiguity"]]).astype(np.float32)


def _entropy_run(lf: LightField, options: dict[str, Any], map_tiles) -> np.ndarray:
    """Entropy tiled exactly: tile-local phases between whole-image steps that are cheap.

    1. every tile: raw initial estimate (nine views), its ambiguity, flat mask, with the whole
       centre view's noise sigma;
    2. whole image: black holes of ``d0`` filled (``fill_initial``), the layer map's minimum (the
       disparity histogram's bin origin), the noise-limited pixels (``noise_limited_pixels``);
    3. every tile: regions, windows, line search, centroid correction;
    4. whole image: TV refinement with hole filling (``refine_global``).
    """
    from recon.entropy.estimate import fill_initial, layer_origin, no_data_pixels, noise_limited_pixels, refine_global
    from recon.entropy.regions import noise_sigma

    opts = _entropy_options(options)
    sigma = noise_sigma(np.asarray(lf.gray(), np.float32)[lf.grid_shape[0] // 2, lf.grid_shape[1] // 2])
    common = {k: v for k, v in options.items() if v is not None}
    first = map_tiles(_entropy_initial_task, options={**common, "_shared": {"noise_sigma": sigma}})
    d0_raw, ambiguity0, flat = first[0], first[1].astype(np.int32), first[2] > 0.5
    d0, _ = fill_initial(d0_raw, ambiguity0, flat, options=opts)
    origin = layer_origin(d0, ambiguity0, flat, options=opts)
    centre = np.asarray(lf.gray(), np.float32)[lf.grid_shape[0] // 2, lf.grid_shape[1] // 2]
    limited = noise_limited_pixels(centre, flat, ambiguity0, noise=sigma, options=opts)
    second = map_tiles(_entropy_matching_task, maps=(d0, ambiguity0.astype(np.float32),
                                                     limited.astype(np.float32)),
                       options={**common, "_shared": {"noise_sigma": sigma, "disparity_origin": origin}})
    matched, labels, ambiguity = second[0], second[1].astype(np.uint8), second[2].astype(np.int32)
    refined, _ = refine_global(matched, labels, flat, ambiguity, options=opts,
                               no_data=no_data_pixels(centre, limited, noise=sigma, options=opts),
                               disparity_range=opts.disparity_range)
    return refined


def _entropy_halo(lf: LightField, options: dict[str, Any]) -> int:
    from recon.entropy import make_options
    from recon.entropy.boundary import boundary_reach_px
    from recon.entropy.estimate import texture_sigma_px
    from recon.entropy.noise import filter_reach_px, soften_reach_px, texture_reach_px

    opts = make_options(**{k: v for k, v in options.items() if v is not None})
    lo, hi = opts.disparity_range
    # the initial search looks one initial_step beyond a known range
    shift = _shift_px((lo - opts.initial_step, hi + opts.initial_step), lf.grid_shape) + 1
    # the strips' aperture test reads the centre view strip_aperture_length // 2 along each strip
    gate = opts.strip_aperture_length // 2 if opts.strip_windows and opts.strip_aperture > 0 else 0
    joint_gate = gate if opts.strip_aperture_scope == "all" else 0
    initial = shift + max(opts.initial_window // 2, gate)  # d0 at a pixel
    layers = opts.layer_median // 2 + shift             # median of d0, then the occlusion warp
    matching = max(max(opts.window_sizes) // 2, joint_gate) + shift  # windows over labels/entropy, then the views
    # which windows a pixel may use depends on depth jumps and layers within a window of it, and the
    # side windows' centroid correction fits over one more window
    window_tests = 2 * (max(opts.window_sizes) // 2) + 1
    # views filtered where noise-limited pixels (a whole-image mask, given) land (a forward warp with
    # d0) and the view is flat (Eq. 12, or with noise_gate="texture" the window-scale test)
    radius = max(opts.window_sizes) // 2 if opts.noise_gate == "texture" else None
    filtered = filter_reach_px(opts.noise_filter, size=opts.smooth_neighbourhood, radius_px=radius) + shift + 1
    if opts.weak_texture_filter > 0:  # then the mild filter where weak-texture pixels land (the same warp)
        filtered += (soften_reach_px(opts.weak_texture_filter) + shift + 1
                     + texture_reach_px(texture_sigma_px(opts), radius_px=max(opts.window_sizes) // 2))
    # the boundary test after matching reads the matched map along each pixel's rays
    # (recon.entropy.boundary.boundary_reach_px)
    boundary = boundary_reach_px((lo, hi), lf.grid_shape) if opts.boundary_snap else 0
    # ... and, with boundary_snap_initial, the initial disparity's over the initial search's range
    if opts.boundary_snap_initial:
        boundary += boundary_reach_px((lo - opts.initial_step, hi + opts.initial_step), lf.grid_shape)
    return (filtered + initial + layers + matching + window_tests + boundary
            + opts.smooth_neighbourhood // 2)


#: Tiling rule per method name (the lead may move ``halo_px`` next to each runner in
#: ``recon.methods.METHODS``; this table is the stand-in).
TILE_RULES: dict[str, TileRule] = {
    "baseline": TileRule(resolve=_baseline_resolve, halo_px=_baseline_halo, exact=True),
    "entropy": TileRule(
        resolve=_entropy_resolve, halo_px=_entropy_halo, exact=True, run=_entropy_run,
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
    """The stitched ``(H, W)`` disparity, the tiles, the halo and the options every tile ran with."""

    disparity: np.ndarray
    tiles: list[Tile]
    halo: int
    options: dict[str, Any]
    exact: bool

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
        Not used for a method whose rule has its own ``run`` (entropy: two rounds of tiles).

    Returns
    -------
    :class:`TiledResult`; ``disparity`` is ``(H, W)`` float32, pixels per view step.
    """
    rule = tile_rule(method)
    resolved = rule.resolve(lf, dict(options or {}))
    halo = rule.halo_px(lf, resolved) if halo is None else int(halo)
    tiles = plan_tiles(lf.image_shape, tile=tile, halo=halo)
    rounds = 2 if rule.run is not None else 1
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

    if rule.run is not None:
        disparity = rule.run(lf, resolved, map_tiles).astype(np.float32)
    else:
        disparity = map_tiles(lambda crop, _maps, opts, th: runner(crop, method, opts, th))
    return TiledResult(disparity=disparity, tiles=tiles, halo=halo, options=resolved, exact=rule.exact)


def tiled_estimator(*, tile: int, halo: int | None = None, client: Any = None, threads: int | None = None,
                    record: dict[str, Any] | None = None):
    """A :data:`recon.pipeline.Estimator` that tiles: on ``client``; inside a cluster task, on that
    task's cluster (the task steps aside while its tiles run); elsewhere, in this process.

    ``record``, when given, receives :meth:`TiledResult.describe` (before ``result.json`` is
    written). The method's own intermediate maps are not stitched: a tiled result has only the
    disparity.
    """
    from recon.methods import MethodResult

    def estimate(lf: LightField, method: str, options: dict[str, Any], progress: Any) -> MethodResult:
        def run(c):
            result = tiled_disparity(lf, method=method, options=options, tile=tile, halo=halo, client=c,
                                     threads=threads, progress=progress)
            if record is not None:
                record.update(result.describe())
            return MethodResult(disparity=result.disparity, options=result.options)

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
