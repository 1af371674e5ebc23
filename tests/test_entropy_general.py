"""What makes the entropy estimator general beyond backgammon: the rendered scene suite, occlusion
found in every view, side windows only near jumps with the centroid correction, single-layer
windows, black-hole filling and fractional progress (docs/entropy-method.md, "Generality")."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from recon.baseline import estimate_baseline
from recon.entropy import estimate_disparity
from recon.entropy.entropy import select_windows, select_windows_reference
from recon.entropy.cost import cost_ambiguity
from recon.entropy.refine import centroid_correction, harmonic_fill, tv_refine
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH, TEXTURE
from recon.entropy.regions import (jump_distance,
                                   layer_jumps, layer_map, region_labels)
from recon.entropy.scenes import (REGION_KINDS, SCENES, Surface, make_scene, region_masks,
                                  render_surfaces)
from recon.entropy.windows import window_rect
from recon.evaluate import score
from recon.synthetic import noise_texture


def _rng():
    return np.random.default_rng(11)


# --- the scene suite -------------------------------------------------------------------------

def test_render_surfaces_follows_the_sign_convention_and_the_closest_surface_wins():
    tex = noise_texture((40, 40), seed=1)
    front_tex = noise_texture((40, 40), seed=2)
    box = lambda y, x: (y >= 15) & (y < 25) & (x >= 15) & (x < 25)  # noqa: E731
    lf, truth, clean = render_surfaces([Surface(tex, 0.5), Surface(front_tex, 1.5, box)],
                                       grid=(5, 5), quantise=False)
    assert truth[20, 20] == pytest.approx(1.5) and truth[5, 5] == pytest.approx(0.5)
    np.testing.assert_array_equal(clean, lf.views[2, 2])
    # view (u, v) shows centre pixel p at p - (du, dv) d: the background 2 px right of centre
    # appears at x - 2 * 0.5 = x - 1 in view (2, 4)
    np.testing.assert_allclose(lf.views[2, 4, 5, 3:10], lf.views[2, 2, 5, 4:11], atol=1e-5)
    # the box (d = 1.5) moved 3 px left in view (2, 4) and hides the background there
    np.testing.assert_allclose(lf.views[2, 4, 20, 12:22], lf.views[2, 2, 20, 15:25], atol=1e-5)


def test_region_masks_partition_the_image():
    scene = make_scene("boxes", size=64)
    masks = region_masks(scene.truth, scene.clean_centre)
    stack = np.stack([masks[k] for k in REGION_KINDS])
    assert (stack.sum(0) == 1).all()
    assert masks["edge"].any() and masks["flat"].any()


@pytest.mark.parametrize("name", list(SCENES))
def test_every_scene_renders_with_finite_truth_in_its_range(name):
    scene = make_scene(name, size=48)
    assert scene.lf.views.shape == (9, 9, 48, 48)
    assert np.isfinite(scene.truth).all()
    lo, hi = scene.lf.disparity_range
    assert lo < scene.truth.min() and scene.truth.max() < hi


# --- occlusion in every view -----------------------------------------------------------------

def test_background_beside_a_thin_bar_is_occluded_in_middle_views_only():
    # Bars 6 px tall every 18 px, 1.8 px/view in front: the background row just above a bar is
    # covered in views du = 1..3 but visible again in du = 4, so the paper's nine views miss it.
    scene = make_scene("bars", size=72)
    gray = scene.lf.views.astype(np.float32)
    kw = dict(layer_gap=0.25, layer_median=1, smooth_neighbourhood=5, smooth_tolerance=2.0)
    nine, _ = region_labels(gray, scene.truth, occlusion_views="nine", **kw)
    every, _ = region_labels(gray, scene.truth, occlusion_views="all", **kw)
    row = 35  # bar rows 36..41 (truth), background above
    assert scene.truth[row, 30] < 0 < scene.truth[row + 1, 30]
    assert (every[row, 20:50] == OCCLUDED).all()
    assert not (nine[row, 20:50] == OCCLUDED).any()
    assert (every[row + 1, 20:50] == OCCLUDING).all()


def test_bars_scene_beats_the_baseline():
    scene = make_scene("bars", size=54)
    ours = score(estimate_disparity(scene.lf).disparity, scene.truth, border=8)
    base = score(estimate_baseline(scene.lf, window=7, step=0.02).disparity, scene.truth, border=8)
    assert ours["badpix_0.07"] < 0.5 * base["badpix_0.07"]
    assert ours["mse_x100"] < 0.5 * base["mse_x100"]


# --- layers and side windows -----------------------------------------------------------------

def test_layer_map_keeps_a_sure_thin_slit_and_drops_an_outlier():
    d0 = np.zeros((15, 15), np.float32)
    d0[7, :] = 1.0          # a one-pixel slit, matched with certainty
    d0[3, 3] = 1.0          # an isolated outlier, also "sure"
    keep = np.ones_like(d0, bool)
    layers = layer_map(d0, median_size=5, keep=keep)
    assert (layers[7, 2:-2] == 1.0).all()
    assert layers[3, 3] == 0.0
    assert (layer_map(d0, median_size=5)[7] == 0.0).all()  # the plain median erases the slit


def test_layer_jumps_ignore_slants_and_find_steps():
    y, x = np.mgrid[0:20, 0:20].astype(np.float32)
    slant = 0.1 * x                      # 0.2 over two pixels: below a 0.3 gap
    assert not layer_jumps(slant, layer_gap=0.3).any()
    step = np.where(x >= 10, 1.0, 0.0).astype(np.float32)
    jumps = layer_jumps(step, layer_gap=0.3)
    assert jumps[:, 9:11].all() and not jumps[:, :8].any() and not jumps[:, 12:].any()
    dist = jump_distance(jumps)
    assert dist[5, 9] == 0 and dist[5, 3] == 5
    assert (jump_distance(np.zeros((4, 4), bool)) > 1000).all()


def test_select_windows_with_side_radius_and_layers_matches_reference():
    rng = _rng()
    grey = rng.integers(0, 16, (14, 12))
    layers = np.where(np.arange(12)[None] < 6, 0.0, 1.0).repeat(14, 0).astype(np.float32)
    disp = (layers * 10).astype(np.int64) + rng.integers(0, 2, (14, 12))
    labels = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH], (14, 12)).astype(np.uint8)
    side = rng.integers(0, 5, (14, 12))
    kw = dict(sizes=(3, 5, 7), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0,
              side_radius=side, layers=layers, layer_gap=0.25)
    s_ref, z_ref, e_ref = select_windows_reference(grey, disp, labels, **kw)
    s_f, z_f, e_f = select_windows(grey, disp, labels, **kw)
    np.testing.assert_allclose(e_f, e_ref, atol=1e-5)
    assert np.array_equal(s_f, s_ref) and np.array_equal(z_f, z_ref)


def test_texture_windows_stay_on_their_layer():
    rng = _rng()
    grey = rng.integers(0, 32, (25, 25))
    layers = np.zeros((25, 25), np.float32)
    layers[:, 14:] = 1.0
    disp = (layers * 10).astype(np.int64)
    labels = np.full((25, 25), TEXTURE, np.uint8)
    shape, size, _, every = select_windows(
        grey, disp, labels, sizes=(3, 5, 7, 9, 11, 13, 15), alpha1=1.0, alpha2_occlusion=1.0,
        alpha2_other=0.0, side_radius=np.zeros((25, 25), np.int64), layers=layers,
        layer_gap=0.25, return_all=True)
    y, x = 12, 11  # three pixels left of the step
    for k in np.flatnonzero(np.isfinite(every[y, x])):
        s, z = divmod(k, 7)
        size_ = (3, 5, 7, 9, 11, 13, 15)[z]
        y0, y1, x0, x1 = window_rect(s, size_)
        assert x + x1 < 14 or (s == 0 and size_ == 3), (s, size_)
    assert size[y, x] >= 9 and shape[y, x] in (1, 3, 4, 5, 7, 9, 10)


# --- centroid correction, holes, ambiguity ----------------------------------------------------

def test_centroid_correction_is_exact_on_a_plane():
    y, x = np.mgrid[0:30, 0:30].astype(np.float64)
    plane = 0.3 + 0.02 * y - 0.015 * x
    rects = np.empty((30, 30, 4), np.int64)
    rects[:] = window_rect(5, 9)   # up-left quadrant: centroid 2 px up and 2 px left
    matched = 0.3 + 0.02 * (y - 2) - 0.015 * (x - 2)   # what that window finds: d at its centroid
    fixed = centroid_correction(matched.astype(np.float32), rects, max_residual=0.05,
                                max_shift=0.5)
    np.testing.assert_allclose(fixed[5:, 5:], plane[5:, 5:], atol=1e-4)
    square = np.empty_like(rects)
    square[:] = window_rect(0, 9)
    same = centroid_correction(plane.astype(np.float32), square, max_residual=0.05, max_shift=0.5)
    np.testing.assert_allclose(same[5:-5, 5:-5], plane[5:-5, 5:-5], atol=1e-5)


def test_harmonic_fill_reproduces_a_plane_and_tv_fills_holes():
    y, x = np.mgrid[0:40, 0:40].astype(np.float32)
    plane = 0.1 + 0.01 * x + 0.02 * y
    holes = np.zeros((40, 40), bool)
    holes[10:30, 8:33] = True
    noisy = plane.copy()
    noisy[holes] = _rng().uniform(-2, 2, holes.sum())
    np.testing.assert_allclose(harmonic_fill(noisy, holes), plane, atol=1e-4)
    refined = tv_refine(noisy, holes, gamma=0.2, iterations=100, holes=holes)
    assert np.abs(refined - plane)[holes].max() < 0.02
    assert np.array_equal(refined[~holes], noisy[~holes])


def test_a_wide_valley_keeps_its_data_against_a_near_rim():
    """The blob on a faint wall (blender-dev slanted-v2): a large region whose matched values are
    right but whose cost valleys are wide. Filled from its rim alone (a black hole, no data term),
    it takes the fixed near surface's value wherever its own measured pixels are sparse; with the
    valley weights (Eq. 13's data term as the cost's curvature) it keeps the wall's value."""
    from recon.entropy.options import DEFAULTS
    from recon.entropy.steps import refine_global
    H, W = 60, 60
    rng = _rng()
    truth = np.full((H, W), -1.0, np.float32)
    matched = (truth + 0.03 * rng.standard_normal((H, W))).astype(np.float32)  # unbiased, noisy
    labels = np.full((H, W), SMOOTH, np.uint8)
    matched[:, :12] = 1.0  # a near surface along the left edge, sure and held (not smooth)
    labels[:, :12] = OCCLUDING
    flat = np.ones((H, W), bool)
    flat[:, :12] = False
    ambiguity = np.full((H, W), 20, np.int32)  # valleys 0.8 px/view wide on the wall (step 0.04)
    ambiguity[:, :12] = 3
    anchors = rng.random((H, W)) < 0.002  # a few narrow valleys on the wall
    ambiguity[anchors] = 3
    refined, holes = refine_global(matched, labels, flat, ambiguity, options=DEFAULTS,
                                   no_data=np.zeros((H, W), bool))
    wall = np.s_[:, 14:]
    assert holes[wall].mean() > 0.99
    assert np.mean(np.abs(refined[wall] - truth[wall]) <= 0.07) > 0.98
    old, _ = refine_global(matched, labels, flat, ambiguity, no_data=np.zeros((H, W), bool),
                           options=dataclasses.replace(DEFAULTS, valley_weights=False))
    assert np.mean(np.abs(old[wall] - truth[wall]) <= 0.07) < 0.5  # the fill follows the near rim
    # a wall without texture above the noise keeps no data term: its matched values are the noise's
    limited, _ = refine_global(matched, labels, flat, ambiguity, options=DEFAULTS,
                               no_data=np.ones((H, W), bool))
    np.testing.assert_array_equal(limited, old)


def test_cost_ambiguity_tells_a_valley_from_a_plateau():
    d = np.linspace(-1, 1, 101)
    valley = np.abs(d - 0.2)[:, None, None] * 10
    plateau = np.full((101, 1, 1), 3.0) + 0.01 * np.sin(d)[:, None, None]
    costs = np.concatenate([valley, plateau], axis=2).astype(np.float32)
    amb = cost_ambiguity(costs, 0.5)
    assert amb[0, 0] <= 11 and amb[0, 1] == 101


def test_a_flat_patch_wider_than_the_largest_window_is_filled():
    tex = noise_texture((72, 72), seed=4)
    tex[18:54, 18:54] = 0.5  # 36 px: no window of 15 px reaches texture from its centre
    lf, truth, _ = render_surfaces([Surface(tex, 0.3)])
    result = estimate_disparity(lf)
    assert result.info["holes"][30:42, 30:42].all()
    assert np.abs(result.disparity - truth)[20:52, 20:52].max() < 0.05
    unfilled = estimate_disparity(lf, fill_holes=False)
    assert np.median(np.abs(unfilled.disparity - truth)[30:42, 30:42]) > 0.1


def test_slanted_plane_next_to_a_step_keeps_sub_pixel_accuracy():
    # A steep slant meets a closer box: side windows are offered near the box's edge, and the
    # centroid correction removes their slant bias.
    scene = make_scene("slants", size=64)
    with_fix = estimate_disparity(scene.lf)
    without = estimate_disparity(scene.lf, centroid_correction=False)
    inner = (slice(8, -8), slice(8, -8))
    side = (with_fix.window_shape > 0)[inner]
    e_fix = np.abs(with_fix.disparity - scene.truth)[inner]
    e_raw = np.abs(without.disparity - scene.truth)[inner]
    assert side.any()
    assert np.median(e_fix[side]) < np.median(e_raw[side])
    assert np.mean(e_fix > 0.07) < 0.03


# --- progress ---------------------------------------------------------------------------------

def test_progress_fraction_is_monotone_and_ends_at_one():
    scene = make_scene("boxes", size=32)
    seen = []
    estimate_disparity(scene.lf, progress=lambda f, note: seen.append((f, note)))
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and seen[-1] == (1.0, "done")
    assert len({note for _, note in seen} - {"done"}) == 5  # one message per step, five steps
    search = [f for f, note in seen if note.startswith("line search")]
    assert len(search) > 20 and search[-1] - search[0] > 0.5  # the line search is most of the run
