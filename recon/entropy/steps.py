"""The steps of the estimator (:data:`recon.entropy.plan.PLAN` puts them in order), each with its reach.

A step reads and writes fields of :class:`recon.entropy.plan.State` and calls the step's own module
for the work (:mod:`~recon.entropy.initial`, :mod:`~recon.entropy.regions`,
:mod:`~recon.entropy.noise`, :mod:`~recon.entropy.entropy`, :mod:`~recon.entropy.matching`,
:mod:`~recon.entropy.boundary`, :mod:`~recon.entropy.refine`, :mod:`~recon.entropy.confidence`).
Its ``reach_px(options, reach)`` beside it says how many pixels around a pixel of its output it
reads of the previous step's (``reach.view_px(options)``: how far a view is sampled); a tile's halo
is the sum over the tile-local steps (:func:`recon.entropy.plan.halo_px`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from recon.entropy.aperture import informative_strips
from recon.entropy.boundary import boundary_reach_px, snap_boundaries
from recon.entropy.calibration import matching_cost, probability_right
from recon.entropy.entropy import quantise_disparity, quantise_grey, select_windows
from recon.entropy.initial import (discover_range, initial_disparity, initial_view_mask, range_from_initial,
                                  sure_pixels)
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH
from recon.entropy.matching import JOINT_TABLES, cost_ambiguity, disparity_candidates, joint_line_search, line_search
from recon.entropy.noise import (filter_flat_view, filter_reach_px, mask_landings, noise_limited_windows,
                                 soften_reach_px, soften_view, texture_reach_px, texture_to_noise, warp_landings,
                                 weak_texture_pixels)
from recon.entropy.options import EntropyOptions
from recon.entropy.refine import centroid_correction, harmonic_fill, tv_refine, valley_weights
from recon.entropy.regions import (flat_pixels, jump_distance, layer_jumps, layer_map, region_labels,
                                   smooth_tolerance_abs)
from recon.entropy.state import Reach, State, Step
from recon.entropy.volume import SparseVolume
from recon.entropy.windows import N_SHAPES, STRIP_SHAPES, curvature_size_cap, window_rect
from recon.lf.lightfield import view_shift_px
from recon.native import library, thread_count


def _no_reach(options: EntropyOptions, reach: Reach) -> int:
    return 0


# --------------------------------------------------------------------------------------------------
# phase "initial" (tile-local): flat pixels, the nine-view estimate


def flat_step(s: State) -> None:
    """Eq. 12's flat pixels of the centre view (``s.flat``)."""
    o = s.options
    s.flat, _ = flat_pixels(s.centre, size=o.smooth_neighbourhood, tolerance=o.smooth_tolerance,
                            sigma=s.noise_sigma)


def flat_reach(options: EntropyOptions, reach: Reach) -> int:
    return options.smooth_neighbourhood // 2


def initial_step(s: State) -> None:
    """The raw nine-view estimate ``s.d0`` and its cost ambiguity ``s.ambiguity0`` (candidates),
    in bands of rows when the whole image's search would take more than :data:`INITIAL_BAND_MIB`
    (:func:`initial_in_bands`)."""
    s.reporter.step("initial", "initial disparity (nine views)")
    s.d0, s.ambiguity0 = initial_in_bands(s)


#: Working memory (MiB) the nine-view initial search may take at once: its cost volume (one
#: float32 map per candidate), the nine views' rows, the window gate (and its copy window by
#: window) and the maps it returns; the fused kernel keeps only a few rows per thread besides
#: (:func:`recon.entropy.cost.min_window_costs`). An image whose search needs more is searched in
#: bands of rows, each with a halo of the rows its windows and views reach (the same maps bit for
#: bit, as the joint search's bands). 512x512 with 52 candidates: 0.14 MB a row, one band; a
#: 1198x906 view set with 36 candidates: 0.26 MB a row, two bands.
INITIAL_BAND_MIB = 128


def initial_band_rows(views_shape: tuple[int, int, int, int], *, n_candidates: int, n_windows: int,
                      budget_mib: float = INITIAL_BAND_MIB) -> int:
    """How many rows of a ``(U, V, H, W)`` view set one band of the nine-view search
    (:func:`recon.entropy.initial.initial_disparity`) takes within ``budget_mib`` (at least one).
    Per pixel of a row: the nine float32 view samples, ``n_candidates`` float32 costs, the
    ``n_windows`` bool gate twice (as given and window by window) and the float32 disparity and
    cost and int32 ambiguity it returns."""
    W = views_shape[3]
    per_row = W * (4 * 9 + 4 * n_candidates + 2 * n_windows + 12)
    return max(int(budget_mib * 2 ** 20 // per_row), 1)


def row_bands(H: int, *, rows: int, halo: int):
    """``(y0, y1, a, b)`` per band: the core rows ``[y0, y1)`` a band gives and the rows
    ``[a, b)`` it reads (``halo`` rows around the core, within the image), for bands of at most
    ``rows`` rows (the whole image when ``rows >= H``; a core of at least ``halo`` rows)."""
    core = H if rows >= H else max(rows - 2 * halo, halo)
    for y0 in range(0, H, core):
        y1 = min(y0 + core, H)
        yield y0, y1, max(y0 - halo, 0), min(y1 + halo, H)


def initial_in_bands(s: State, *, budget_mib: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`recon.entropy.initial.initial_disparity` over ``s.raw`` with the options' window,
    step and strip gate, in bands of rows within ``budget_mib`` (default :data:`INITIAL_BAND_MIB`).
    Each band is searched with a halo of the window's half side plus the farthest view shift of the
    candidates plus two rows, so that every pixel of its core gets the whole image's values (a
    pixel's costs read the views within that reach; the summed-area tables are exact integers). A
    band holds only the nine views the search reads. Returns ``(d0 float32, ambiguity0 int32)``,
    ``(H, W)`` each."""
    o = s.options
    U, V, H, W = s.raw.shape
    strip_ok = _strip_ok(s.centre, (o.initial_window,), s.noise_sigma, o)
    candidates = disparity_candidates(s.initial_range[0], s.initial_range[1], o.initial_step)
    rows = initial_band_rows(s.raw.shape, n_candidates=len(candidates), n_windows=N_SHAPES,
                             budget_mib=INITIAL_BAND_MIB if budget_mib is None else budget_mib)
    halo = o.initial_window // 2 + view_shift_px((candidates[0], candidates[-1]), (U, V)) + 2
    bands = list(row_bands(H, rows=rows, halo=halo))
    nine = [tuple(uv) for uv in np.argwhere(initial_view_mask((U, V)))]
    d0 = np.empty((H, W), np.float32)
    ambiguity0 = np.empty((H, W), np.int32)
    for i, (y0, y1, a, b) in enumerate(bands):
        if len(bands) == 1:
            views = s.raw
        else:  # only the nine views are written (and so take memory); the search reads no other
            views = np.empty((U, V, b - a, W), np.float32)
            for u, v in nine:
                views[u, v] = s.raw[u, v, a:b]
        d, _, amb = initial_disparity(
            views, disparity_range=s.initial_range, step=o.initial_step, window=o.initial_window,
            shiftable=o.initial_shiftable, strips=o.strip_windows,
            ambiguity_delta=s.hole_delta / o.intensity_scale,
            progress=lambda f, i=i: s.reporter.within((i + f) / len(bands)),
            strip_ok=None if strip_ok is None else strip_ok[a:b, ..., 0])
        d0[y0:y1] = d[y0 - a:y1 - a]
        ambiguity0[y0:y1] = amb[y0 - a:y1 - a]
        del views, d, amb
    return d0, ambiguity0


def initial_reach(options: EntropyOptions, reach: Reach) -> int:
    return reach.view_px(options) + max(options.initial_window // 2, _strip_gate_px(options))


# --------------------------------------------------------------------------------------------------
# phase "layers" (whole image): holes of d0 filled, the range, the layers' origin, noise-limited pixels


def fill_initial_step(s: State) -> None:
    """Black holes of ``s.d0`` (``s.holes0``) filled from their surroundings."""
    s.d0, s.holes0 = fill_initial(s.d0, s.ambiguity0, s.flat, options=s.options)


def snap_initial_step(s: State) -> None:
    """With ``boundary_snap_initial``: the boundary test on ``s.d0`` (``docs/entropy-method.md``)."""
    if s.options.boundary_snap_initial:
        s.d0 = _snap(s.raw, s.d0, s.noise_sigma, s.initial_range, s.options)


def noise_limited_step(s: State) -> None:
    """``s.noise_limited``: the pixels whose matching the noise decides (:func:`noise_limited_pixels`)."""
    s.noise_limited = noise_limited_pixels(s.centre, s.flat, s.ambiguity0, noise=s.noise_sigma,
                                           options=s.options)


def search_range_step(s: State) -> None:
    """``s.disparity_range``: the known range, else the robust extent of ``s.d0``."""
    o = s.options
    if s.known is not None:
        s.disparity_range = (float(s.known[0]), float(s.known[1]))
    else:
        s.disparity_range = range_from_initial(
            s.d0, percentile=o.range_percentile, margin=o.range_margin, limits=s.initial_range,
            grid_shape=s.raw.shape[:2],
            sure=sure_pixels(s.ambiguity0, step=o.initial_step, width=o.initial_hole_width))


def layer_origin_step(s: State) -> None:
    """``s.origin``: the disparity histogram's bin origin, the same for every tile."""
    s.origin = layer_origin(s.d0, s.ambiguity0, s.flat, options=s.options)


# --------------------------------------------------------------------------------------------------
# phase "matching" (tile-local): filtered views, regions, windows, line search, boundaries


def view_filters_step(s: State) -> None:
    """``s.view_filters``: the centre-view pixels where the views are filtered, where noise-limited
    pixels land (``noise_filter``) and where pixels of weak texture land (``weak_texture_filter``;
    ``docs/entropy-method.md``), ``None`` for a filter that is off or has nothing to filter. The
    views themselves are filtered where the line search reads them, a band of rows at a time
    (:func:`filtered_views`): ``s.raw`` stays as read, for the boundary step after the search."""
    o = s.options
    noise = s.noise_limited if o.noise_filter > 0 and s.noise_limited.any() else None
    weak = None
    if o.weak_texture_filter > 0:  # the rest of the weak texture, mildly
        weak = weak_texture_pixels(_texture_ratio(s.centre, s.noise_sigma, o),
                                   texture_ratio=o.weak_texture_ratio) & ~s.noise_limited
        weak = weak if weak.any() else None
    s.view_filters = (noise, weak)


def filtered_views(s: State, a: int, b: int) -> np.ndarray:
    """``(U, V, b - a, W)`` float32: the image rows ``[a, b)`` of the views ``s.raw`` filtered where
    ``s.view_filters`` lands in each view (:func:`recon.entropy.noise.warp_mask_to_views` with
    ``s.d0``): the Gaussian of ``noise_filter`` where the view is noise-limited too
    (:func:`recon.entropy.noise.filter_flat_views`, ``noise_gate="texture"``: the window-scale test,
    else Eq. 12's), then the mild one of ``weak_texture_filter``
    (:func:`recon.entropy.noise.soften_views`). Each view is filtered over the rows ``[a, b)`` and
    as many around them as the two filters reach (:func:`view_filter_rows`), so that the rows are
    those of the whole views filtered, bit for bit; the rows of ``s.raw`` themselves (not a copy)
    when no filter has anything to filter. The views go to :func:`recon.native.thread_count`
    threads, one view a task (OpenCV's filters and the C kernels release the interpreter's lock),
    each mask's pixels found once for all of them."""
    o, (noise, weak) = s.options, s.view_filters
    if noise is None and weak is None:
        library("views")  # asked for all the same: every estimate's record names the same C libraries
        return s.raw[:, :, a:b]
    U, V, H, W = s.raw.shape
    reach = view_filter_rows(o)
    top, bottom = max(a - reach, 0), min(b + reach, H)
    rows = range(top, bottom)
    largest = float(np.nanmax(np.abs(s.d0)))  # for every warp of the band
    # each mask's pixels found once, for every view
    noise_at, weak_at = (None if m is None else mask_landings(m, s.d0, (U, V), image_rows=rows, max_disparity=largest)
                         for m in (noise, weak))
    out = np.empty((U, V, b - a, W), np.float32)
    core = slice(a - top, b - top)

    def one(k: int) -> None:  # a view at a time, its masks' temporaries a view's: OpenCV and C release the GIL
        u, v = divmod(k, V)
        view = s.raw[u, v, top:bottom]
        if noise_at is not None:
            view = filter_flat_view(view, sigma_px=o.noise_filter, noise_sigma=s.noise_sigma,
                                    size=o.smooth_neighbourhood, tolerance=o.smooth_tolerance,
                                    where=warp_landings(noise_at, [(u, v)], threads=1)[0],
                                    texture_ratio=o.noise_texture_ratio if o.noise_gate == "texture" else None,
                                    radius_px=o.windows.largest_radius_px)
        if weak_at is not None:  # the band's rows straight into their place
            soften_view(view, sigma_px=o.weak_texture_filter, where=warp_landings(weak_at, [(u, v)], threads=1)[0],
                        out=out[u, v], rows=core)
        else:
            out[u, v] = view[core]

    with ThreadPoolExecutor(max_workers=max(1, min(U * V, thread_count()))) as pool:
        list(pool.map(one, range(U * V)))
    return out


def view_filter_rows(options: EntropyOptions) -> int:
    """How far (pixels) a value of :func:`filtered_views` depends on the view it filters and on
    the filters' masks in that view: the noise filter's reach, then the mild filter's over it."""
    o = options
    return (filter_reach_px(o.noise_filter, size=o.smooth_neighbourhood,
                            radius_px=o.windows.largest_radius_px if o.noise_gate == "texture" else None)
            + soften_reach_px(o.weak_texture_filter))


def view_filters_reach(options: EntropyOptions, reach: Reach) -> int:
    # views filtered where noise-limited pixels land (a forward warp with d0) and the view is flat
    # (Eq. 12, or with noise_gate="texture" the window-scale test); then the mild filter where
    # weak-texture pixels land (the same warp)
    o = options
    px = view_filter_rows(o) + reach.view_px(o) + 1
    if o.weak_texture_filter > 0:
        px += reach.view_px(o) + 1 + texture_reach_px(texture_sigma_px(o), radius_px=o.windows.largest_radius_px)
    return px


def regions_step(s: State) -> None:
    """``s.labels`` (Eqs. 8-11) and ``s.region_info``: the layer map (for the window selection) and
    the noise figures; Eq. 12's smooth region is ``s.flat`` (:func:`flat_step`, the same test on
    the same centre view), and the rest of :func:`recon.entropy.regions.region_labels`' info (the
    occlusion differences: 23 MiB at 2000x1500) has no reader and is let go."""
    o = s.options
    s.lap("initial")
    s.reporter.step("regions", "region types")
    s.labels, info = region_labels(
        s.raw, s.d0, layer_gap=o.layer_gap, layer_median=o.layer_median,
        smooth_neighbourhood=o.smooth_neighbourhood, smooth_tolerance=o.smooth_tolerance,
        occlusion_views=o.occlusion_views, noise=s.noise_sigma, keep=_layer_keep(s.ambiguity0, s.flat, o),
        flat=s.flat)
    s.region_info = {"layers": info["layers"], "noise_sigma": s.noise_sigma,
                     "smooth_tolerance_abs": smooth_tolerance_abs(o.smooth_tolerance, s.noise_sigma)}
    s.lap("regions")


def regions_reach(options: EntropyOptions, reach: Reach) -> int:
    return options.layer_median // 2 + reach.view_px(options)  # median of d0, then the occlusion warp


def windows_step(s: State) -> None:
    """The windows each pixel is offered and their matching entropy (Eq. 1), in ``s.windows``."""
    o = s.options
    s.reporter.step("windows", "window selection (matching entropy)")
    layers = s.region_info.pop("layers")  # read by no later step
    H, W = layers.shape
    grey_q = quantise_grey(s.centre, o.grey_bins)
    disp_q = quantise_disparity(layers, o.disparity_bin, origin=s.origin)
    sizes = tuple(sorted(o.window_sizes))
    if o.side_windows == "edges":
        side_radius = jump_distance(layer_jumps(layers, layer_gap=o.side_jump))
    else:
        side_radius = None if o.side_windows == "occlusion" else np.zeros((H, W), np.int64)
    max_size = None if o.crease_tolerance <= 0 else np.where(
        s.noise_limited, max(sizes),  # a harmonic fill there: its curvature was not measured
        curvature_size_cap(layers, sizes, tolerance=o.crease_tolerance, measured=~s.noise_limited,
                           initial=s.d0, noise_factor=o.crease_noise))
    shape_map, size_map, entropy, all_entropy = select_windows(
        grey_q, disp_q, s.labels, sizes=sizes, alpha1=o.alpha1, alpha2_occlusion=o.alpha2_occlusion,
        alpha2_other=o.alpha2_other, strips=o.strip_windows, side_radius=side_radius,
        layers=layers if o.single_layer_windows else None, layer_gap=o.layer_gap, return_all="sparse",
        max_size=max_size)
    s.windows = {"sizes": sizes, "shape": shape_map, "size": size_map, "entropy": entropy,
                 "all_entropy": all_entropy}  # SparseVolume, -inf: not offered
    s.lap("windows")


def windows_reach(options: EntropyOptions, reach: Reach) -> int:
    # which windows a pixel may use depends on depth jumps and layers within a window of it
    return options.windows.largest_radius_px + 1


def line_search_step(s: State) -> None:
    """The line search of Eqs. 5-7: ``s.matched``, ``s.cost`` and the cost ambiguity ``s.ambiguity``
    (candidates), the chosen windows in ``s.windows``."""
    o, w = s.options, s.windows
    sizes, labels = w["sizes"], s.labels
    candidates = disparity_candidates(s.disparity_range[0], s.disparity_range[1], o.step)
    s.reporter.set_matching(len(candidates))
    s.reporter.step("matching", f"line search over [{s.disparity_range[0]:.2f}, "
                                f"{s.disparity_range[1]:.2f}] step {o.step}")
    occluded = {"none": np.zeros(labels.shape, bool), "occluded": labels == OCCLUDED,
                "occlusion": (labels == OCCLUDED) | (labels == OCCLUDING),
                "all": np.ones(labels.shape, bool)}[o.visible_sets]
    if o.joint:
        windows = [(sh, z) for sh in range(N_SHAPES if o.strip_windows else 9) for z in sizes]
        del w["shape"], w["size"], w["entropy"]  # the search chooses them anew: not alive beside it
        s.matched, s.cost, k, s.ambiguity = joint_search_in_bands(s, candidates, windows=windows,
                                                                  use_shape_set=occluded)
        w["shape"] = k // len(sizes)
        w["size"] = np.asarray(sizes)[k % len(sizes)]
        w["entropy"] = w["all_entropy"].take(k)
    del w["all_entropy"]
    w["set"] = np.where(occluded, w["shape"], 0)
    if not o.joint:
        s.matched, s.cost, costs = line_search(filtered_views(s, 0, labels.shape[0]), candidates,
                                               shape_map=w["shape"], size_map=w["size"], set_map=w["set"],
                                               return_costs=True, progress=s.reporter.within)
        s.ambiguity = cost_ambiguity(costs, s.hole_delta / o.intensity_scale)


#: Working memory (MiB) the joint line search may take at once, as :func:`joint_band_rows` counts
#: it: the band's filtered views, its penalty, its cost volume (one float32 map per candidate) and
#: the summed-area tables. A search within :data:`JOINT_WHOLE_MIB` runs on the whole image; one
#: that needs more is searched in bands of rows within this budget, each with a halo of the rows
#: its pixels' windows and views reach (the same maps bit for bit: every value of a pixel depends
#: only on the rows within the halo), so that the search's memory grows with the image, not with
#: the image times the candidates. The 1198x906 demo capture (25 candidates over 3.35..4.29
#: px/view): 1.2 MB a row, seven bands of 187 rows with halos of 27; the 2000x1500 synthetic set
#: (82 candidates): 2.4 MB a row, 27 bands of 90 rows with halos of 17. The budget does not grow
#: with the views: at 2000x1500 they alone take 927 MiB.
JOINT_BAND_MIB = 208
#: The largest joint search (MiB, as :data:`JOINT_BAND_MIB` counts) that runs whole, without halo
#: rows swept twice: 512x512 with 81 views, 77 windows and 61 candidates (backgammon) takes 1.1 MB
#: a row, 279 MiB.
JOINT_WHOLE_MIB = 288
#: Bytes a pixel of a band of the joint search holds besides its views, penalty, costs and tables:
#: the running least cost and window, the pixels' view sets, the three maps it returns and the
#: window lists' runs (measured with one candidate a pass: 1,114-1,136 bytes a pixel in all at
#: 2000x1500 with 82 candidates, 806-894 on the demo capture with 25).
JOINT_PIXEL_BYTES = 96


def joint_band_rows(views_shape: tuple[int, int, int, int], *, n_candidates: int, n_windows: int,
                    budget_mib: float = JOINT_BAND_MIB, whole_mib: float = JOINT_WHOLE_MIB) -> int:
    """How many rows of a ``(U, V, H, W)`` view set one band of the joint search takes: ``H`` when
    the whole image's search takes at most ``whole_mib``, else as many as ``budget_mib`` holds (at
    least one). Per pixel of a row, what is alive at the search's peak, its sweep over the
    candidates in :func:`recon.entropy.matching.joint_line_search`: the band's ``U * V`` float32
    view samples (:func:`filtered_views`), its ``n_windows`` float32 penalty, ``n_candidates``
    float32 costs, the rings of summed-area table rows of a pass over a group of candidates (at
    most :data:`~recon.entropy.matching.JOINT_TABLES` whole sets of nine int64 tables) and
    :data:`JOINT_PIXEL_BYTES`. The penalty while it is made, a row of its flat pixels at a time,
    and the filters' temporaries, a row of views at a time, take less."""
    U, V, H, W = views_shape
    per_row = W * (4 * U * V + 4 * n_windows + 4 * n_candidates + 8 * 9 * JOINT_TABLES + JOINT_PIXEL_BYTES)
    if H * per_row <= whole_mib * 2 ** 20:
        return H
    return max(int(budget_mib * 2 ** 20 // per_row), 1)


def joint_search_in_bands(s: State, candidates: np.ndarray, *, windows: list[tuple[int, int]],
                          use_shape_set: np.ndarray, budget_mib: float | None = None):
    """:func:`recon.entropy.matching.joint_line_search` over the filtered views (:func:`filtered_views`)
    with the penalty of ``s.windows["all_entropy"]`` (:func:`_search_penalty`, the strips gated), in
    bands of rows within ``budget_mib`` (default :data:`JOINT_BAND_MIB`) when the whole image's
    search would take more than :data:`JOINT_WHOLE_MIB`. Each band is searched with a halo of
    ``largest_radius_px`` plus the farthest view shift of the candidates plus two rows, so that
    every pixel of its core gets the whole image's values; the band's views are filtered, and its
    penalty made, band by band, and only one band's cost volume is alive at a time. Returns
    ``(disparity, objective, window_index, ambiguity)``, ``(H, W)`` each."""
    o, w = s.options, s.windows
    sizes = w["sizes"]
    U, V, H, W = s.raw.shape
    rows = joint_band_rows(s.raw.shape, n_candidates=len(candidates), n_windows=len(windows),
                           budget_mib=JOINT_BAND_MIB if budget_mib is None else budget_mib,
                           whole_mib=JOINT_WHOLE_MIB)  # read at the call: tests lower it
    halo = o.windows.largest_radius_px + view_shift_px((candidates[0], candidates[-1]), (U, V)) + 2
    gate = _strip_gate(s.centre, sizes=sizes, noise=s.noise_sigma, opts=o)

    def penalty(a: int, b: int) -> np.ndarray:  # the rows [a, b) of the search's penalty
        p = _search_penalty(w["all_entropy"], a, b, s.noise_limited[a:b], o, len(sizes))
        return p if gate is None else _bar_strips(p, gate[a:b], len(sizes))

    bands = list(row_bands(H, rows=rows, halo=halo))
    maps = (np.empty((H, W), np.float32), np.empty((H, W), np.float32), np.empty((H, W), np.int64),
            np.empty((H, W), np.int32))
    for i, (y0, y1, a, b) in enumerate(bands):
        band = joint_line_search(
            filtered_views(s, a, b), candidates, windows=windows, penalty=penalty(a, b),
            use_shape_set=use_shape_set[a:b], intensity_scale=o.intensity_scale,
            ambiguity_delta=s.hole_delta,
            progress=lambda f, i=i: s.reporter.within((i + f) / len(bands)))
        for out, got in zip(maps, band):
            out[y0:y1] = got[y0 - a:y1 - a]
        del band
    return maps


def line_search_reach(options: EntropyOptions, reach: Reach) -> int:
    # windows over labels and entropy, then the views; the strips' aperture test along each strip
    joint_gate = _strip_gate_px(options) if options.strip_aperture_scope == "all" else 0
    return max(options.windows.largest_radius_px, joint_gate) + reach.view_px(options)


def centroid_step(s: State) -> None:
    """With ``centroid_correction``: each side window's estimate moved from its centroid back to
    the pixel (:func:`recon.entropy.refine.centroid_correction`)."""
    o, w = s.options, s.windows
    if o.centroid_correction:
        sizes = w["sizes"]
        rect_table = np.array([[window_rect(sh, z) if z % 2 else (0, 0, 0, 0) for z in range(max(sizes) + 1)]
                               for sh in range(N_SHAPES)], np.int64)
        s.matched = centroid_correction(s.matched, rect_table[w["shape"], w["size"]],
                                        max_residual=o.centroid_max_residual, max_shift=o.step * 10)


def centroid_reach(options: EntropyOptions, reach: Reach) -> int:
    return options.windows.largest_radius_px  # the plane is fitted over the window


def boundary_step(s: State) -> None:
    """With ``boundary_snap``: the boundary test on ``s.matched`` (``docs/entropy-method.md``)."""
    if s.options.boundary_snap:
        s.matched = _snap(s.raw, s.matched, s.noise_sigma, s.disparity_range, s.options)
    s.raw = None  # the last step that reads the views: the refinement needs only the centre's maps
    s.source.release_views()  # and the light field's own, when it was read for this one estimate
    s.lap("matching")


def boundary_reach(options: EntropyOptions, reach: Reach) -> int:
    # the matched map along each pixel's rays (recon.entropy.boundary.boundary_reach_px)
    return boundary_reach_px(reach.disparity_range, reach.grid_shape) if options.boundary_snap else 0


# --------------------------------------------------------------------------------------------------
# phase "refine" (whole image): TV refinement, confidence


def refine_step(s: State) -> None:
    """``s.refined``: the TV refinement of Eq. 13, black holes ``s.holes`` filled by it, wide cost
    valleys joining with their valley's weight (``valley_weights``)."""
    s.reporter.step("refine", "TV refinement of smooth regions")
    no_data = no_data_pixels(s.centre, s.noise_limited, noise=s.noise_sigma, options=s.options)
    s.refined, s.holes = refine_global(s.matched, s.labels, s.flat, s.ambiguity, options=s.options,
                                       no_data=no_data, disparity_range=s.disparity_range)


def confidence_step(s: State) -> None:
    """``s.confidence``: the probability that the final disparity is within 0.07 px/view of the truth
    (:func:`recon.entropy.calibration.probability_right`); a tiled run's matching phase hands
    back every map it reads (:data:`recon.entropy.plan.PLAN`)."""
    o = s.options
    if s.cost is not None and "size" in s.windows:
        s.confidence = probability_right(
            refined=s.refined, matched=s.matched, initial=s.d0, ambiguity=s.ambiguity, labels=s.labels,
            holes=s.holes, noise_limited=s.noise_limited, window_size=s.windows["size"],
            cost=matching_cost(s.cost, s.windows["entropy"], lambda_entropy=o.lambda_entropy,
                               intensity_scale=o.intensity_scale), entropy=s.windows["entropy"],
            noise_sigma=s.noise_sigma, step=o.step, disparity_range=s.disparity_range, valley_px=o.hole_width,
            hole_support=o.hole_support, hole_ramp=o.hole_ramp)
    s.lap("refine")
    s.reporter.done()


# --------------------------------------------------------------------------------------------------
# the steps as the plan names them


def _step(name, run, reach=_no_reach) -> Step:
    return Step(name, run, reach)


FLAT = _step("flat", flat_step, flat_reach)
INITIAL = _step("initial", initial_step, initial_reach)
FILL_INITIAL = _step("fill_initial", fill_initial_step)
SNAP_INITIAL = _step("snap_initial", snap_initial_step)
NOISE_LIMITED = _step("noise_limited", noise_limited_step)
SEARCH_RANGE = _step("search_range", search_range_step)
LAYER_ORIGIN = _step("layer_origin", layer_origin_step)
VIEW_FILTERS = _step("view_filters", view_filters_step, view_filters_reach)
REGIONS = _step("regions", regions_step, regions_reach)
WINDOWS = _step("windows", windows_step, windows_reach)
LINE_SEARCH = _step("line_search", line_search_step, line_search_reach)
CENTROID = _step("centroid", centroid_step, centroid_reach)
BOUNDARY = _step("boundary", boundary_step, boundary_reach)
REFINE = _step("refine", refine_step)
CONFIDENCE = _step("confidence", confidence_step)


# --------------------------------------------------------------------------------------------------
# the steps' arithmetic on options


def _snap(gray: np.ndarray, disparity: np.ndarray, noise: float, rng: tuple[float, float],
          opts: EntropyOptions) -> np.ndarray:
    """:func:`recon.entropy.boundary.snap_boundaries` with the options' parameters."""
    return snap_boundaries(gray, disparity, noise_sigma=noise, disparity_range=rng,
                           jump=opts.boundary_jump, support=opts.boundary_support,
                           confidence=opts.boundary_confidence, mix=opts.boundary_mix,
                           mix_contrast=opts.boundary_mix_contrast,
                           mix_extrapolate=opts.boundary_mix_extrapolate)[0]


def _search_penalty(all_entropy: SparseVolume, a: int, b: int, noise_limited: np.ndarray,
                    opts: EntropyOptions, n_sizes: int) -> np.ndarray:
    """The rows ``[a, b)`` of the joint search's penalty, laid out ``(b - a, K, W)`` float32:
    ``-lambda E`` of the packed entropies ``(H, W, K)`` (the float32 product, what numpy makes of
    ``-lambda * E``; ``inf``: window not offered), with ``flat_windows="largest"`` applied
    (``noise_limited``: the rows' ``(b - a, W)``). Made from the packed volume in one pass
    (:meth:`SparseVolume.window_major`), without a dense ``(H, W, K)`` volume."""
    out = all_entropy.window_major(a, b, scale=-opts.lambda_entropy)
    if opts.flat_windows == "largest":
        out = _largest_windows_only(out, noise_limited, n_sizes, in_place=True)
    return out


def hole_tolerance(options: EntropyOptions, noise_sigma: float) -> float:
    """How far above a cost curve's least value a candidate still counts as part of its valley, in
    the cost's units (``intensity_scale``): ``hole_delta``, or ``hole_delta_noise`` times the
    noise sigma (``[0, 1]`` grey units) if that is larger."""
    return max(options.hole_delta, options.hole_delta_noise * noise_sigma * options.intensity_scale)


def unknown_range(gray: np.ndarray, *, options: EntropyOptions, noise_sigma: float
                  ) -> tuple[float, float]:
    """The range the initial search covers when nobody gave one: :func:`initial.discover_range`
    over ``options.initial_range`` with the estimator's own window, step, percentiles and hole
    tolerance (``noise_sigma`` of the centre view in ``[0, 1]`` grey units)."""
    hole_delta = hole_tolerance(options, noise_sigma)
    return discover_range(gray, search_range=options.initial_range, step=options.initial_step,
                          window=options.initial_window, percentile=options.range_percentile,
                          margin=options.range_margin, shiftable=options.initial_shiftable,
                          strips=options.strip_windows,
                          ambiguity_delta=hole_delta / options.intensity_scale,
                          sure_width=options.initial_hole_width)


def _largest_windows_only(penalty: np.ndarray, flat: np.ndarray, n_sizes: int, *,
                          in_place: bool = False) -> np.ndarray:
    """``penalty`` ``(H, K, W)`` (window ``k`` has shape ``k // n_sizes`` and the ``k % n_sizes``-th
    size, smallest first; ``inf`` = not offered) with every window but those of the largest offered
    size barred at the ``flat`` pixels (the square alone where it is offered, as Eq. 12 gives the
    smooth region). A flat window's cost curve is noise: offered several windows, the joint minimum
    picks whichever window's noise dips lowest, most often the smallest and noisiest. A row at a
    time: the temporaries hold one row's flat pixels (on a noisy wall nearly every pixel of a
    band, 4 bytes a window each, several times over)."""
    out = penalty if in_place else penalty.astype(np.float32, copy=True)
    K = penalty.shape[1]
    size_of = np.arange(K) % n_sizes
    if not flat.any():  # none on most textured scenes: one pass instead of one a row
        return out
    for y, row in enumerate(out):
        xs = np.flatnonzero(flat[y])  # only those pixels change
        if xs.size == 0:
            continue
        sub = row[:, xs].T  # (N, K)
        N = sub.shape[0]
        by_size = np.isfinite(sub).reshape(N, K // n_sizes, n_sizes)
        offered = by_size.any(axis=1)
        largest = n_sizes - 1 - np.argmax(offered[:, ::-1], axis=1)
        bar = size_of[None, :] != largest[:, None]
        has_square = by_size[np.arange(N), 0, largest]
        bar |= has_square[:, None] & (np.arange(K) >= n_sizes)[None, :]
        row[:, xs] = np.where(bar, np.inf, sub).T
    return out


#: Least variation along a strip that counts as texture: Eq. 12's floor, half an 8-bit grey level.
STRIP_FLOOR = 0.5 / 255


def _strip_ok(centre: np.ndarray, sizes: tuple[int, ...], noise: float,
              opts: EntropyOptions) -> np.ndarray | None:
    """``(H, W, 2, len(sizes))`` :func:`informative_strips`, or ``None`` when not gated."""
    if not opts.strip_windows or opts.strip_aperture == 0:
        return None
    return informative_strips(centre, sizes=sizes, noise_sigma=noise, factor=opts.strip_aperture,
                              floor=STRIP_FLOOR, length=opts.strip_aperture_length)


def _strip_gate(centre: np.ndarray, *, sizes: tuple[int, ...], noise: float,
                opts: EntropyOptions) -> np.ndarray | None:
    """``(H, W, 2, len(sizes))`` bool: where each strip window can measure disparity
    (:func:`recon.entropy.aperture.informative_strips`; the floor is Eq. 12's, half a grey level)
    when the joint search gates its strips (``strip_aperture_scope="all"``), else ``None``."""
    return _strip_ok(centre, sizes, noise, opts) if opts.strip_aperture_scope == "all" else None


def _bar_strips(penalty: np.ndarray, ok: np.ndarray, n_sizes: int) -> np.ndarray:
    """``penalty`` ``(H, K, W)`` float32 (window ``k``: shape ``k // n_sizes``, the ``k %
    n_sizes``-th size) with the strip windows barred (``inf``) where ``ok`` (:func:`_strip_gate`,
    ``(H, W, 2, n_sizes)``) says they cannot measure disparity, in place. A pixel offered nothing
    but uninformative strips keeps them: some window must be matched."""
    n = n_sizes
    ok = ok.transpose(0, 2, 3, 1)  # (H, 2, n_sizes, W), as the penalty
    kept = np.zeros((penalty.shape[0], penalty.shape[2]), bool)  # pixels left some window after the gate
    for shape in range(penalty.shape[1] // n):
        block = np.isfinite(penalty[:, shape * n:(shape + 1) * n])
        if shape in STRIP_SHAPES:
            block &= ok[:, STRIP_SHAPES.index(shape)]
        kept |= block.any(axis=1)
    for j, shape in enumerate(STRIP_SHAPES):
        block = penalty[:, shape * n:(shape + 1) * n]
        block[~ok[:, j] & kept[:, None]] = np.inf
    return penalty


def noise_limited_pixels(centre: np.ndarray, flat: np.ndarray, ambiguity0: np.ndarray, *,
                         noise: float, options: EntropyOptions) -> np.ndarray:
    """``(H, W)`` bool: the pixels whose matching the noise, not the texture, decides
    (``options.noise_gate``): ``"texture"``: inside a window of the largest size whose every pixel
    has nothing but noise around it (:func:`recon.entropy.noise.texture_to_noise` below
    ``noise_texture_ratio``, with the ``noise_filter`` sigma, 1.5 px when the filter is off;
    :func:`recon.entropy.noise.noise_limited_windows`); Eq. 12's per-pixel count is not used: on a
    wall under noise it flips from pixel to pixel. ``"holes"`` (the first version): Eq. 12-flat
    with no valley in the initial nine-view cost."""
    if options.noise_gate == "holes":
        return flat & (ambiguity0 * options.initial_step > options.initial_hole_width)
    return noise_limited_windows(_texture_ratio(centre, noise, options) < options.noise_texture_ratio,
                                 radius_px=options.windows.largest_radius_px)


def texture_sigma_px(options: EntropyOptions) -> float:
    """Sigma (px) of the filter with which the texture gates measure texture against noise
    (:func:`recon.entropy.noise.texture_to_noise`): ``noise_filter``, 1.5 px when it is off."""
    return options.noise_filter if options.noise_filter > 0 else 1.5


def _texture_ratio(centre: np.ndarray, noise: float, options: EntropyOptions) -> np.ndarray:
    # texture_to_noise over the largest window
    return texture_to_noise(centre, noise_sigma=noise, sigma_px=texture_sigma_px(options),
                            radius_px=options.windows.largest_radius_px)


def _layer_keep(ambiguity0: np.ndarray, flat: np.ndarray, opts: EntropyOptions) -> np.ndarray:
    return (ambiguity0 * opts.initial_step <= opts.layer_keep_width) & ~flat


def fill_initial(d0: np.ndarray, ambiguity0: np.ndarray, flat: np.ndarray, *,
                 options: EntropyOptions) -> tuple[np.ndarray, np.ndarray | None]:
    """Whole-image step after the initial search: black holes of ``d0`` (flat pixels whose
    nine-view cost curve is flat) filled from their surroundings (:func:`harmonic_fill`).

    ``(H, W)`` maps in, ``(filled d0 float32, holes bool or None)`` out."""
    holes0 = (flat & (ambiguity0 * options.initial_step > options.initial_hole_width)
              if options.fill_holes else None)
    if holes0 is not None and holes0.any():
        d0 = harmonic_fill(d0, holes0)
    return d0, holes0


def layer_origin(d0: np.ndarray, ambiguity0: np.ndarray, flat: np.ndarray, *,
                 options: EntropyOptions) -> float:
    """The disparity histogram's bin origin the whole image uses: the layer map's minimum."""
    layers = layer_map(d0, median_size=options.layer_median,
                       keep=_layer_keep(ambiguity0, flat, options))
    return float(np.nanmin(layers))


def refine_global(matched: np.ndarray, labels: np.ndarray, flat: np.ndarray,
                  ambiguity: np.ndarray, *, options: EntropyOptions,
                  no_data: np.ndarray | None = None,
                  disparity_range: tuple[float, float] | None = None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Whole-image last step: the TV refinement of Eq. 13 over the smooth region, black holes
    (flat pixels whose matching cost curve is flat) filled by it; with ``valley_weights`` the
    pixels with a wide cost valley join it with their valley's weight
    (:func:`recon.entropy.refine.valley_weights`; ``no_data``, the ``(H, W)`` bool mask of
    :func:`no_data_pixels`, keep none, and so do plateaus over the whole searched
    ``disparity_range``).

    ``(H, W)`` maps in (matched disparity, labels, flat mask, cost ambiguity in candidates);
    ``(refined float32, holes bool or None)`` out (the black holes, whose data term is dropped)."""
    holes = flat & (ambiguity * options.step > options.hole_width) if options.fill_holes else None
    joined, weight = holes, None
    if holes is not None and options.valley_weights:
        span = (np.inf if disparity_range is None else
                len(disparity_candidates(disparity_range[0], disparity_range[1], options.step)) * options.step)
        joined, weight = valley_weights(ambiguity * options.step, flat=flat, no_data=no_data,
                                        hole_width=options.hole_width, unsure_width=options.unsure_width,
                                        plateau_width=span)
    refined = tv_refine(matched, labels == SMOOTH, gamma=options.gamma,
                        iterations=options.tv_iterations, holes=joined, hole_weight=weight)
    return refined, holes


def no_data_pixels(centre: np.ndarray, noise_limited: np.ndarray, *, noise: float,
                   options: EntropyOptions) -> np.ndarray:
    """``(H, W)`` bool: pixels whose matched value carries no information about the surface, so
    that the refinement's valley weights give them none: the noise-limited pixels
    (:func:`noise_limited_pixels`) and every pixel whose own largest window holds nothing but noise
    (:func:`recon.entropy.noise.texture_to_noise` below ``noise_texture_ratio``; a textureless
    patch narrower than the noise gate's window is not noise-limited, yet matches itself at every
    shift). ``centre``: ``(H, W)`` grey centre view; ``noise``: its sigma, ``[0, 1]`` grey units."""
    return np.asarray(noise_limited, bool) | (_texture_ratio(centre, noise, options) < options.noise_texture_ratio)


def _strip_gate_px(options: EntropyOptions) -> int:
    """How far (pixels) the strips' aperture test reads the centre view along a strip; 0 when off."""
    return options.strip_aperture_length // 2 if options.strip_windows and options.strip_aperture > 0 else 0
