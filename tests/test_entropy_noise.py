"""Noise-limited matching (recon.entropy.noise), flat pixels' windows, presets and the confidence map."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from recon.entropy import DEFAULTS, estimate_disparity, make_options
from recon.entropy.confidence import confidence_map
from recon.entropy.options import PRESETS
from recon.entropy.steps import _largest_windows_only, noise_limited_pixels
from recon.entropy.noise import (filter_flat_views, filter_gain, filter_reach_px, gradient_noise_energy,
                                 soften_reach_px, soften_views, texture_reach_px, texture_to_noise,
                                 warp_mask_to_views, weak_texture_pixels)
from recon.lf.lightfield import LightField
from recon.synthetic import noise_texture


def _views(centre_rows: np.ndarray, n: int = 3) -> np.ndarray:
    return np.broadcast_to(centre_rows, (n, n) + centre_rows.shape).astype(np.float32).copy()


def test_filter_leaves_a_constant_light_field_constant():
    views = np.full((3, 3, 20, 24), 0.4, np.float32)
    out = filter_flat_views(views, sigma_px=1.5, noise_sigma=2 / 255, size=5, tolerance=2.0)
    np.testing.assert_allclose(out, 0.4, atol=1e-6)


def test_filter_off_returns_the_views():
    views = np.random.default_rng(0).random((3, 3, 8, 8)).astype(np.float32)
    assert filter_flat_views(views, sigma_px=0.0, noise_sigma=0.01, size=5, tolerance=2.0) is views


def test_filter_reduces_noise_where_flat_and_keeps_texture():
    rng = np.random.default_rng(1)
    sigma = 2 / 255
    image = np.full((64, 64), 0.5, np.float32)
    image[:, 32:] = 0.25 + 0.5 * rng.random((64, 32))  # strong texture on the right
    views = _views(image) + rng.normal(0, sigma, (3, 3, 64, 64)).astype(np.float32)
    out = filter_flat_views(views, sigma_px=1.5, noise_sigma=sigma, size=5, tolerance=2.0)
    left = (slice(None), slice(None), slice(8, -8), slice(4, 22))
    right = (slice(None), slice(None), slice(8, -8), slice(42, 60))
    assert np.std(out[left] - 0.5) < 0.3 * np.std(views[left] - 0.5)  # gain 0.19 for white noise
    np.testing.assert_array_equal(out[right], views[right])  # textured: untouched
    assert 0.18 < filter_gain(1.5) < 0.2 and filter_gain(0) == 1.0


def test_filter_is_local_within_its_reach():
    """What tiling relies on: a crop filtered alone equals the whole, filtered, beyond the reach."""
    rng = np.random.default_rng(3)
    image = np.full((60, 60), 0.5, np.float32)
    image[20:40, 10:50] = noise_texture((20, 40), seed=4)
    views = _views(image) + rng.normal(0, 0.01, (3, 3, 60, 60)).astype(np.float32)
    opts = {"sigma_px": 1.5, "noise_sigma": 0.01, "size": 5, "tolerance": 2.0}
    whole = filter_flat_views(views, **opts)
    crop = filter_flat_views(np.ascontiguousarray(views[:, :, 5:55, 5:55]), **opts)
    r = filter_reach_px(1.5, size=5)
    np.testing.assert_allclose(crop[:, :, r:-r, r:-r], whole[:, :, 5 + r:55 - r, 5 + r:55 - r], atol=1e-6)


def test_flat_pixels_get_only_the_largest_offered_windows():
    n_sizes, n_shapes = 3, 4
    penalty = np.zeros((2, 2, n_shapes * n_sizes), np.float32)
    penalty[0, 0, [2, 5, 8, 11]] = np.inf  # largest size barred everywhere for pixel (0, 0)
    penalty[1, 1, 0:n_sizes] = np.inf  # no square for pixel (1, 1) (an occlusion pixel)
    flat = np.array([[True, False], [False, True]])
    out = _largest_windows_only(penalty.transpose(0, 2, 1), flat, n_sizes).transpose(0, 2, 1)  # (H, K, W)
    assert np.flatnonzero(np.isfinite(out[0, 0])).tolist() == [1]  # the square of the middle size
    assert np.array_equal(out[0, 1], penalty[0, 1]) and np.array_equal(out[1, 0], penalty[1, 0])
    assert np.flatnonzero(np.isfinite(out[1, 1])).tolist() == [5, 8, 11]  # every shape, largest size


def test_gradient_noise_energy_matches_filtered_white_noise():
    rng = np.random.default_rng(11)
    noise = rng.normal(0, 1, (400, 400)).astype(np.float32)
    ratio = texture_to_noise(noise, noise_sigma=1.0, sigma_px=1.5, radius_px=7)[20:-20, 20:-20]
    assert abs(float(ratio.mean()) - 1.0) < 0.03  # the analytic energy is white noise's
    assert gradient_noise_energy(3.0) < gradient_noise_energy(1.5) < gradient_noise_energy(0.8)


def test_texture_to_noise_tells_a_faint_wall_from_texture_beside_a_flat_patch():
    """Texture below the noise reads ~1 at the window scale; a flat pixel whose window reaches an
    edge (the inside of a brick, a textureless pole before texture) reads far above it."""
    rng = np.random.default_rng(12)
    sigma = 1.5 / 255
    faint = cv2.GaussianBlur(rng.standard_normal((80, 80)).astype(np.float32), (0, 0), 1.0)
    image = 0.5 + faint * (0.7 / 255) / faint.std() + rng.normal(0, sigma, (80, 80)).astype(np.float32)
    image[:, 60:] += 0.1 * (np.arange(20)[None, :] % 6 < 3)  # stripes of 25 grey levels
    ratio = texture_to_noise(image, noise_sigma=sigma, sigma_px=1.5, radius_px=7)
    assert np.percentile(ratio[10:-10, 10:40], 95) < DEFAULTS.noise_texture_ratio  # ~2.3 here
    assert ratio[10:-10, 55:59].min() > 50  # flat itself, but its window reaches the stripes
    with pytest.raises(ValueError, match="sigma_px must be > 0"):
        texture_to_noise(image, noise_sigma=sigma, sigma_px=0.0, radius_px=7)


def test_texture_gate_is_local_within_its_reach():
    rng = np.random.default_rng(13)
    image = np.full((60, 60), 0.5, np.float32) + rng.normal(0, 0.01, (60, 60)).astype(np.float32)
    image[20:40, 30:50] = noise_texture((20, 20), seed=4)
    whole = texture_to_noise(image, noise_sigma=0.01, sigma_px=1.5, radius_px=7)
    crop = texture_to_noise(np.ascontiguousarray(image[5:55, 5:55]), noise_sigma=0.01, sigma_px=1.5,
                            radius_px=7)
    r = texture_reach_px(1.5, radius_px=7)
    np.testing.assert_allclose(crop[r:-r, r:-r], whole[5 + r:55 - r, 5 + r:55 - r], rtol=1e-5)
    views = _views(image)
    opts = {"sigma_px": 1.5, "noise_sigma": 0.01, "size": 5, "tolerance": 2.0, "texture_ratio": 4.0,
            "radius_px": 7}
    filtered = filter_flat_views(views, **opts)
    assert not np.array_equal(filtered[:, :, 5:15, 5:15], views[:, :, 5:15, 5:15])  # noise: filtered
    np.testing.assert_array_equal(filtered[:, :, 28:32, 38:42], views[:, :, 28:32, 38:42])  # texture: not
    crop_f = filter_flat_views(np.ascontiguousarray(views[:, :, 5:55, 5:55]), **opts)
    rf = filter_reach_px(1.5, size=5, radius_px=7)
    np.testing.assert_allclose(crop_f[:, :, rf:-rf, rf:-rf], filtered[:, :, 5 + rf:55 - rf, 5 + rf:55 - rf],
                               atol=1e-6)


def test_noise_limited_pixels_by_gate():
    rng = np.random.default_rng(14)
    image = np.full((50, 50), 0.5, np.float32) + rng.normal(0, 0.01, (50, 50)).astype(np.float32)
    image[:, 35:] = noise_texture((50, 15), seed=5)
    flat = np.ones((50, 50), bool)
    hole = np.full((50, 50), 100)  # no valley anywhere in the initial cost
    texture = noise_limited_pixels(image, flat, hole, noise=0.01, options=DEFAULTS)
    assert texture[:, :20].all() and not texture[:, 30:].any()  # noise only / window reaches texture
    holes = noise_limited_pixels(image, flat, hole, noise=0.01,
                                 options=dataclasses.replace(DEFAULTS, noise_gate="holes"))
    assert holes.all()  # the first version: every flat hole, the texture's neighbours too
    with pytest.raises(ValueError, match="noise_gate must be one of"):
        estimate_disparity(LightField(views=_views(image)), noise_gate="flat")


def _faint_wall(n: int, d: float, seed: int, *, texture_levels: float = 0.7) -> LightField:
    # A plane at disparity d whose texture (0.7 grey levels by default) is weaker than the render
    # noise (1.5 levels, its own in every view).
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.standard_normal((n + 40, n + 40)).astype(np.float32), (0, 0), 1.0)
    texture = 0.5 + texture * (texture_levels / 255) / texture.std()
    views = np.empty((9, 9, n, n), np.float32)
    for u in range(9):
        for v in range(9):
            # view (u, v) at q shows the texture at q + (v - 4, u - 4) d + 20 (docs/conventions.md)
            m = np.float32([[1, 0, 20 + (v - 4) * d], [0, 1, 20 + (u - 4) * d]])
            views[u, v] = cv2.warpAffine(texture, m, (n, n), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    views += rng.normal(0, 1.5 / 255, views.shape).astype(np.float32)
    return LightField(views=np.clip(views, 0, 1), disparity_range=(d - 0.75, d + 1.25))


def test_warp_mask_to_views_by_rows_is_the_whole_grid_s_rows():
    rng = np.random.default_rng(4)
    mask = rng.random((30, 40)) < 0.1
    disparity = rng.uniform(-1.5, 1.5, mask.shape).astype(np.float32)
    whole = warp_mask_to_views(mask, disparity, (5, 3))
    assert whole.shape == (5, 3, 30, 40) and whole[2, 1, mask].all()  # the centre view: the mask, grown
    for u in range(5):
        assert np.array_equal(warp_mask_to_views(mask, disparity, (5, 3), rows=range(u, u + 1)), whole[u:u + 1])
    assert np.array_equal(warp_mask_to_views(mask, disparity, (5, 3), rows=range(1, 4)), whole[1:4])
    largest = float(np.abs(disparity).max())  # given by a caller: the same rows
    assert np.array_equal(warp_mask_to_views(mask, disparity, (5, 3), rows=range(4, 5), image_rows=range(7, 19),
                                             max_disparity=largest), whole[4:5, :, 7:19])


def test_soften_views_filters_only_where_asked_and_is_local():
    rng = np.random.default_rng(21)
    views = rng.random((3, 3, 40, 40)).astype(np.float32)
    where = np.zeros(views.shape, bool)
    where[1, 2, 10:20, 10:20] = True
    out = soften_views(views, sigma_px=0.6, where=where)
    np.testing.assert_array_equal(np.delete(out.reshape(9, 40, 40), 5, 0),
                                  np.delete(views.reshape(9, 40, 40), 5, 0))  # other views untouched
    r = soften_reach_px(0.6)
    assert r == 4
    far = np.ones((40, 40), bool)
    far[10 - r:20 + r, 10 - r:20 + r] = False
    np.testing.assert_array_equal(out[1, 2][far], views[1, 2][far])
    assert out[1, 2, 12:18, 12:18].std() < 0.7 * views[1, 2, 12:18, 12:18].std()  # filtered inside
    assert soften_views(views, sigma_px=0.0, where=where) is views
    band = np.full((3, 3, 8, 40), np.nan, np.float32)  # rows 14..21 only, each view filtered whole
    assert soften_views(views, sigma_px=0.6, where=where, out=band, rows=slice(14, 22)) is band
    np.testing.assert_array_equal(band.view(np.uint32), out[:, :, 14:22].view(np.uint32))
    with pytest.raises(ValueError, match="subset of the rows"):
        soften_views(views, sigma_px=0.6, where=where, out=views, rows=slice(14, 22))
    np.testing.assert_array_equal(weak_texture_pixels(np.array([1.0, 15.9, 16.0, 40.0]), texture_ratio=16.0),
                                  [True, True, False, False])


def test_the_default_removes_the_half_pixel_pull_on_weak_texture_under_noise():
    """Texture stronger than the noise (texture/noise energy ~7 over the window, above the noise
    gate's 4): matched unfiltered, the cost minimum is pulled towards the candidates whose shifts
    fall near half pixels in most views (d = -1.75: the outer views' shifts are whole, half and
    quarter pixels); the mild filter of the weak-texture pixels removes half of the pull. (Measured
    before the refinement's valley weights, which smooth what is left of the pull.)"""
    d = -1.75
    lf = _faint_wall(72, d, seed=5, texture_levels=1.5)
    inner = (slice(15, -15), slice(15, -15))
    new = np.abs(estimate_disparity(lf, valley_weights=False).disparity[inner] - d)
    old = np.abs(estimate_disparity(lf, weak_texture_filter=0.0, valley_weights=False).disparity[inner] - d)
    assert np.median(old) > 0.05  # the pull: most of the BadPix threshold
    assert np.median(new) < 0.6 * np.median(old)
    assert np.mean(new > 0.07) < 0.5 * np.mean(old > 0.07)
    with pytest.raises(ValueError, match="weak_texture_filter must be a sigma"):
        estimate_disparity(lf, weak_texture_filter=-1.0)


def test_the_default_matches_a_faint_wall_under_noise():
    """A wall whose texture is weaker than the noise: unfiltered, the least cost sits where the
    views' sub-pixel shifts average the noise most. The default (texture-gated pre-filter, largest
    window) gets it; the old defaults (no filter, every window) did not."""
    d = -1.75
    lf = _faint_wall(72, d, seed=5)
    inner = (slice(15, -15), slice(15, -15))
    new = np.abs(estimate_disparity(lf).disparity[inner] - d)
    old = np.abs(estimate_disparity(lf, noise_filter=0.0, flat_windows="all").disparity[inner] - d)
    assert np.median(new) < 0.05
    assert np.mean(new > 0.07) < 0.6 * np.mean(old > 0.07)
    assert np.mean(new > 0.07) < 0.25


def test_paper_preset_and_unknown_preset():
    paper = make_options(preset="paper")
    for name, value in PRESETS["paper"].items():
        assert getattr(paper, name) == value
    assert paper.gamma == DEFAULTS.gamma and paper.window_sizes == DEFAULTS.window_sizes
    with pytest.raises(ValueError, match="unknown entropy preset 'papr'"):
        make_options(preset="papr")
    with pytest.raises(ValueError, match="either options or preset"):
        make_options(DEFAULTS, preset="paper")
    assert dataclasses.replace(paper, noise_filter=1.0).noise_filter == 1.0


def test_confidence_orders_valleys_and_zeroes_out_of_range():
    refined = np.array([[0.5, 0.5, 0.5, 2.0, np.nan]], np.float32)
    matched = np.array([[0.5, 0.5, 0.8, 2.0, np.nan]], np.float32)
    ambiguity = np.array([[1, 20, 1, 1, 1]])
    conf = confidence_map(refined=refined, matched=matched, ambiguity=ambiguity, step=0.02,
                          disparity_range=(0.0, 1.0))
    assert conf.dtype == np.float32 and ((conf >= 0) & (conf <= 1)).all()
    assert conf[0, 0] == pytest.approx(1.0)
    assert conf[0, 1] < conf[0, 0] and conf[0, 2] < conf[0, 0]  # wide valley; moved by the refinement
    assert conf[0, 3] == 0 and conf[0, 4] == 0  # outside the range searched; no value
    holes = np.array([[True, False, False, False, False]])
    with_holes = confidence_map(refined=refined, matched=matched, ambiguity=ambiguity, step=0.02,
                                disparity_range=(0.0, 1.0), holes=holes)
    assert with_holes[0, 0] == pytest.approx(0.5)
    on_end = confidence_map(refined=refined, matched=np.full_like(matched, 0.0), ambiguity=ambiguity, step=0.02,
                            disparity_range=(0.0, 1.0))
    assert (on_end == 0).all()  # the least cost on the first candidate: no minimum inside the range


def test_confidence_drops_a_speck():
    refined = np.full((9, 9), 1.0, np.float32)
    refined[4, 4] = 1.6  # sharp valley, wrong place
    conf = confidence_map(refined=refined, matched=refined, ambiguity=np.ones((9, 9), int), step=0.02,
                          disparity_range=(0.0, 2.0))
    assert conf[4, 4] < 0.01 and conf[0, 0] == pytest.approx(1.0)


def test_the_estimator_returns_a_confidence_map():
    rng = np.random.default_rng(7)
    tex = noise_texture((40, 40), seed=8)
    lf = LightField(views=_views(tex, 5) + rng.normal(0, 0.002, (5, 5, 40, 40)).astype(np.float32),
                    disparity_range=(-0.5, 0.5))
    result = estimate_disparity(lf)
    assert result.confidence.shape == (40, 40)
    assert np.median(result.confidence[8:-8, 8:-8]) > 0.5  # a textured plane at disparity 0


def test_reconstruct_command_takes_the_paper_preset(tmp_path, capsys):
    import json
    from pathlib import Path

    from rig.main import main

    capture = Path(__file__).resolve().parents[1] / "fixtures" / "tiny_capture"
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "out"), "--preset", "paper",
                 "--window-sizes", "3", "5", "--quiet"]) == 0
    options = json.loads((tmp_path / "out" / "result.json").read_text())["options"]
    assert options["noise_filter"] == 0.0 and options["joint"] is False and options["window_sizes"] == [3, 5]
    assert (tmp_path / "out" / "confidence.pfm").is_file()
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "b"), "--method", "baseline",
                 "--preset", "paper"]) != 0
    assert "--preset belongs to the entropy method" in capsys.readouterr().err



def test_a_flat_spot_smaller_than_the_largest_window_is_left_alone():
    """A noisy flat patch of 9x9 px in a textured plane (a weak spot on a slant, the inside of a
    brick, a thin textureless pole before texture) is not noise-limited at the window scale: the
    default gives the unfiltered, all-window result there, bit for bit."""
    rng = np.random.default_rng(15)
    tex = noise_texture((48, 48), seed=6)
    tex[20:29, 20:29] = 0.5
    lf = LightField(views=_views(tex, 5) + rng.normal(0, 1.5 / 255, (5, 5, 48, 48)).astype(np.float32),
                    disparity_range=(-0.5, 0.5))
    new = estimate_disparity(lf).disparity
    old = estimate_disparity(lf, noise_filter=0.0, flat_windows="all").disparity
    np.testing.assert_array_equal(new, old)


def test_the_estimate_leaves_the_callers_views_alone():
    """The weak-texture filter writes into the estimator's copy of the views, never into a light
    field whose views are already float grey (lf.gray() then returns the views themselves)."""
    lf = _faint_wall(40, -1.75, seed=5, texture_levels=1.5)
    before = np.array(lf.views, copy=True)
    assert lf.views.dtype == np.float32 and lf.views.ndim == 4  # lf.gray() is lf.views
    estimate_disparity(lf)
    np.testing.assert_array_equal(lf.views, before)
