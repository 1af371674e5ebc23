"""The estimator's steps (recon/entropy/steps.py): their arithmetic on options."""

from __future__ import annotations

import numpy as np
import pytest


def test_search_penalty_is_the_masked_float32_product():
    from recon.entropy.options import make_options
    from recon.entropy.steps import _search_penalty
    from recon.entropy.volume import SparseVolume
    rng = np.random.default_rng(9)
    entropy = (rng.random((9, 11, 14)) * 6 - 1).astype(np.float32)
    entropy[rng.random(entropy.shape) < 0.5] = -np.inf
    nothing_flat = np.zeros((5, 11), bool)
    for lam in (1.0, 0.37, 0.0, 2.5):
        opts = make_options(lambda_entropy=lam, flat_windows="all")
        with np.errstate(invalid="ignore"):
            expected = np.where(np.isfinite(entropy), -lam * entropy, np.inf).astype(np.float32)
        expected = np.ascontiguousarray(expected[2:7].transpose(0, 2, 1))  # rows 2..6, (H, K, W)
        got = _search_penalty(SparseVolume.pack(entropy), 2, 7, nothing_flat, opts, 7)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got.view(np.uint32), expected.view(np.uint32))



def _maps(result) -> dict:
    out = {name: getattr(result, name) for name in ("disparity", "matched_disparity", "window_size",
                                                     "window_shape", "entropy", "cost", "confidence")}
    out.update({f"info.{k}": v for k, v in result.info.items() if isinstance(v, np.ndarray)})
    return out


def _check_bands(monkeypatch, step_function: str, budget: str, rows_per_mib: int, *, poison=None) -> None:
    """Run the estimator on a scene whole, then with ``steps.<budget>`` set to about 40 rows a
    band (``rows_per_mib``: rows a band takes at 1 MiB) and ``steps.<step_function>`` counting its
    calls (``poison(views)`` first, if given); every map must be the whole image's, bit for bit
    (the occluding bars reach the bands' edges with depth jumps)."""
    from recon.entropy import estimate_disparity, steps
    from recon.entropy.scenes import make_scene
    lf = make_scene("bars", size=72).lf
    whole = _maps(estimate_disparity(lf))
    H = lf.views.shape[2]
    cuts = []
    function = getattr(steps, step_function)

    def counted(first, *args, **kwargs):  # first: the views (U, V, rows, W) or a map (rows, W)
        cuts.append(first.shape[-2])
        if poison is not None and first.shape[-2] < H:
            poison(first)
        return function(first, *args, **kwargs)

    monkeypatch.setattr(steps, step_function, counted)
    monkeypatch.setattr(steps, budget, 40 / rows_per_mib)
    banded = _maps(estimate_disparity(lf))
    assert len(cuts) >= 3 and max(cuts) < H
    for name, value in whole.items():
        assert value.dtype == banded[name].dtype, name
        np.testing.assert_array_equal(banded[name], value, err_msg=name)


def test_joint_search_in_bands_gives_the_whole_image_maps(monkeypatch):
    from recon.entropy import steps
    rows = steps.joint_band_rows((9, 9, 72, 72), n_candidates=1, n_windows=1, budget_mib=1.0, whole_mib=0)
    monkeypatch.setattr(steps, "JOINT_WHOLE_MIB", 0)  # no search runs whole
    _check_bands(monkeypatch, "joint_line_search", "JOINT_BAND_MIB", rows)


def test_a_joint_search_within_the_whole_budget_runs_whole_and_others_in_bands():
    from recon.entropy import steps
    backgammon = (9, 9, 512, 512)  # 61 candidates, 77 windows: 279 MiB
    assert steps.joint_band_rows(backgammon, n_candidates=61, n_windows=77) == 512
    capture = (9, 9, 906, 1198)  # 25 candidates: 1.2 MB a row
    rows = steps.joint_band_rows(capture, n_candidates=25, n_windows=77)
    per_pixel = 4 * 81 + 4 * 77 + 4 * 25 + 8 * 9 * steps.JOINT_TABLES + steps.JOINT_PIXEL_BYTES
    assert rows == int(steps.JOINT_BAND_MIB * 2 ** 20 // (1198 * per_pixel))
    assert steps.joint_band_rows(capture, n_candidates=25, n_windows=77, whole_mib=2000) == 906


def test_initial_search_in_bands_gives_the_whole_image_maps(monkeypatch):
    # The bands hold only the nine views: the others are never written (poisoned here).
    from recon.entropy import steps
    from recon.entropy.initial import initial_view_mask

    def poison(views):
        views[~initial_view_mask(views.shape[:2])] = np.nan

    rows = steps.initial_band_rows((9, 9, 72, 72), n_candidates=1, n_windows=1, budget_mib=1.0)
    _check_bands(monkeypatch, "initial_disparity", "INITIAL_BAND_MIB", rows, poison=poison)


def test_initial_step_is_the_nine_view_search_with_the_strip_gate():
    # The step's bands against one call of initial_disparity over the whole image with the
    # aperture gate of the horizontal and the vertical strip ((H, W, 2): a gate of one strip for
    # both would change the estimate).
    from recon.entropy import steps
    from recon.entropy.options import make_options
    from recon.entropy.plan import start
    from recon.entropy.scenes import make_scene
    s = start(make_scene("stripes", size=72).lf, make_options(None))
    o = s.options
    gate = steps._strip_ok(s.centre, (o.initial_window,), s.noise_sigma, o)
    assert gate is not None and not np.array_equal(gate[..., 0, 0], gate[..., 1, 0])
    d0, _, ambiguity0 = steps.initial_disparity(
        s.raw, disparity_range=s.initial_range, step=o.initial_step, window=o.initial_window,
        shiftable=o.initial_shiftable, strips=o.strip_windows, ambiguity_delta=s.hole_delta / o.intensity_scale,
        strip_ok=gate[..., 0])
    steps.initial_step(s)
    np.testing.assert_array_equal(s.d0, d0)
    np.testing.assert_array_equal(s.ambiguity0, ambiguity0)


def test_row_bands_cover_the_image_once_with_their_halos():
    from recon.entropy.steps import row_bands
    for H, rows, halo in ((100, 40, 7), (100, 10, 7), (5, 40, 3), (100, 100, 20), (64, 30, 0)):
        bands = list(row_bands(H, rows=rows, halo=halo))
        assert bands[0][0] == 0 and bands[-1][1] == H
        assert all(b0[1] == b1[0] for b0, b1 in zip(bands, bands[1:]))
        for y0, y1, a, b in bands:
            assert y0 < y1 and a == max(y0 - halo, 0) and b == min(y1 + halo, H)
            assert len(bands) == 1 or y1 - y0 >= min(halo, H - y0)


def test_bar_strips_in_place_is_the_gate_with_its_fallback():
    # The strips barred where not informative; a pixel left with nothing keeps its strips.
    from recon.entropy.steps import _bar_strips
    from recon.entropy.windows import STRIP_SHAPES
    rng = np.random.default_rng(4)
    n, H, W = 3, 6, 7
    penalty = rng.random((H, W, 11 * n)).astype(np.float32)
    penalty[rng.random(penalty.shape) < 0.4] = np.inf
    penalty[0, 0, :9 * n] = np.inf  # strips alone, and none informative: kept
    ok = rng.random((H, W, 2, n)) < 0.5
    ok[0, 0] = False
    expected = penalty.copy()
    for j, shape in enumerate(STRIP_SHAPES):
        block = expected[..., shape * n:(shape + 1) * n]
        block[~ok[..., j, :]] = np.inf
    none_left = ~np.isfinite(expected).any(axis=2)
    expected[none_left] = penalty[none_left]
    assert none_left[0, 0] and not none_left.all()
    window_major = np.ascontiguousarray(penalty.transpose(0, 2, 1))  # the search's (H, K, W)
    got = _bar_strips(window_major, ok, n)
    assert got is window_major
    np.testing.assert_array_equal(got, expected.transpose(0, 2, 1))


def noisy_wall(shape: tuple[int, int], seed: int, textured: tuple[slice, slice], faint: tuple[slice, slice],
               texture_seeds: tuple[int, int]):
    """``(lf, s, expected)``: a plain wall under noise with a ``textured`` and a ``faint`` patch (both
    view filters act), the state after the first two phases, and the views filtered whole by the
    numpy/OpenCV twins: the reference every band of :func:`recon.entropy.steps.filtered_views` is
    cut from."""
    from recon.entropy import steps
    from recon.entropy.noise import filter_flat_views, soften_views, warp_mask_to_views, weak_texture_pixels
    from recon.entropy.options import make_options
    from recon.entropy.plan import PLAN, run_phase, start
    from recon.native import preferring
    from recon.synthetic import Layer, noise_texture, render
    rng = np.random.default_rng(seed)
    wall = np.full(shape, 0.5, np.float32)
    wall[textured] = noise_texture(wall[textured].shape, seed=texture_seeds[0])
    wall[faint] += 0.02 * noise_texture(wall[faint].shape, seed=texture_seeds[1])
    lf, _ = render([Layer(wall, 0.4)])
    lf.views += rng.normal(0, 0.01, lf.views.shape).astype(np.float32)
    o = make_options()
    s = start(lf, o)
    for phase in PLAN[:2]:
        run_phase(s, phase)
    U, V = s.raw.shape[:2]
    with preferring("numba"):
        expected = filter_flat_views(s.raw, sigma_px=o.noise_filter, noise_sigma=s.noise_sigma,
                                     size=o.smooth_neighbourhood, tolerance=o.smooth_tolerance,
                                     where=warp_mask_to_views(s.noise_limited, s.d0, (U, V)),
                                     texture_ratio=o.noise_texture_ratio, radius_px=o.windows.largest_radius_px)
        weak = weak_texture_pixels(steps._texture_ratio(s.centre, s.noise_sigma, o),
                                   texture_ratio=o.weak_texture_ratio) & ~s.noise_limited
        expected = soften_views(expected, sigma_px=o.weak_texture_filter, out=expected,
                                where=warp_mask_to_views(weak, s.d0, (U, V)))
    assert s.noise_limited.any() and weak.any()
    return lf, s, expected


def test_filtered_views_of_a_band_are_those_rows_of_the_whole_views_filtered():
    # On a noisy scene both filters act: the rows of any band the line search matches must be those
    # of the filters over the whole views, bit for bit, and the views as read must stay unwritten.
    from recon.entropy import steps
    lf, s, expected = noisy_wall((64, 64), 5, np.s_[8:30, 8:40], np.s_[36:60, 30:60], (2, 3))
    given = lf.views.copy()
    H = s.raw.shape[2]
    steps.view_filters_step(s)
    for a, b in [(0, H), (0, 9), (20, 41), (50, H), (31, 32)]:
        got = steps.filtered_views(s, a, b)
        np.testing.assert_array_equal(got.view(np.uint32), expected[:, :, a:b].view(np.uint32))
    assert not np.array_equal(expected, given)
    np.testing.assert_array_equal(lf.views, given)  # the views as read
    assert s.raw is lf.views


def test_warped_masks_of_some_rows_are_those_rows_of_the_whole_mask():
    from recon.entropy.noise import warp_mask_to_views
    rng = np.random.default_rng(3)
    mask = rng.random((40, 30)) < 0.1
    disparity = rng.uniform(-1.5, 2.0, mask.shape)
    whole = warp_mask_to_views(mask, disparity, (5, 5))
    for top, bottom in [(0, 40), (0, 7), (12, 25), (33, 40)]:
        for rows in (range(0, 2), range(2, 3), range(4, 5)):
            part = warp_mask_to_views(mask, disparity, (5, 5), rows=rows, image_rows=range(top, bottom))
            np.testing.assert_array_equal(part, whole[rows.start:rows.stop, :, top:bottom])


def test_views_read_for_one_estimate_are_let_go_after_the_boundary_step():
    # A light field read for one estimate (views_once) loses its views after the last step that reads
    # them, keeps its shapes and centre view, and gives the same maps as one that keeps its views.
    from recon.entropy import estimate_disparity
    from recon.synthetic import Layer, noise_texture, render
    lf, _ = render([Layer(noise_texture((40, 48), seed=4), 0.6)])
    kept = estimate_disparity(lf)
    centre = lf.centre_view().copy()
    lf.stored_centre, lf.views_once = centre, True
    shapes = lf.grid_shape, lf.image_shape, lf.is_colour
    once = estimate_disparity(lf)
    assert lf.views is None and (lf.grid_shape, lf.image_shape, lf.is_colour) == shapes
    assert lf.centre_view() is centre
    for name in ("disparity", "matched_disparity", "confidence"):
        np.testing.assert_array_equal(getattr(once, name), getattr(kept, name))


def test_sparse_volume_gives_back_the_dense_one_bit_for_bit():
    from recon.entropy import volume
    from recon.entropy.volume import SparseVolume
    rng = np.random.default_rng(8)
    H, W, K = 150, 9, 13  # more rows than one chunk, K not a multiple of 8
    dense = rng.normal(size=(H, W, K)).astype(np.float32)
    dense[rng.random(dense.shape) < 0.7] = -np.inf
    dense[3, 4, :] = -np.inf  # a pixel offered nothing
    dense[5, 5, 2] = np.nan
    dense[6, 6, 1] = -0.0
    packed = SparseVolume.pack(dense)
    assert packed.nbytes < dense.nbytes / 2
    for a, b in ((0, H), (60, 70), (63, 65), (149, 150)):
        np.testing.assert_array_equal(packed.rows(a, b).view(np.uint32), dense[a:b].view(np.uint32))
    index = rng.integers(-K, K, (H, W))
    index[5, 5] = 2
    expected = np.take_along_axis(dense, index[..., None], 2)[..., 0]
    np.testing.assert_array_equal(packed.take(index).view(np.uint32), expected.view(np.uint32))
    np.testing.assert_array_equal(packed.take_reference(index).view(np.uint32), expected.view(np.uint32))
    empty = SparseVolume.pack(np.full((2, 3, K), -np.inf, np.float32))
    assert (empty.take(np.zeros((2, 3), np.int64)) == -np.inf).all()
    with pytest.raises(ValueError, match="index must be"):
        packed.take(np.full((H, W), K))
    assert volume.CHUNK_ROWS < H
