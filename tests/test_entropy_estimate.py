"""The whole matching-entropy estimator on small rendered light fields with known disparity."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from recon.baseline import estimate_baseline
from recon.entropy import DEFAULTS, EntropyOptions, estimate_disparity, make_options, write_outputs
from recon.entropy.labels import OCCLUDED, OCCLUDING, REGION_COLOURS, SMOOTH
from recon.lf.lightfield import LightField
from recon.synthetic import Layer, noise_texture, occluding_square_scene, render

INNER = (slice(8, -8), slice(8, -8))


def test_defaults_are_the_papers_values():
    assert DEFAULTS.alpha1 == 1.0 and DEFAULTS.alpha2_occlusion == 1.0 and DEFAULTS.alpha2_other == 0
    assert DEFAULTS.lambda_entropy == 1.0 and DEFAULTS.gamma == 0.2
    assert DEFAULTS.window_sizes == (3, 5, 7, 9, 11, 13, 15)
    assert all("help" in f.metadata for f in dataclasses.fields(EntropyOptions))


def test_unknown_option_is_named():
    with pytest.raises(ValueError, match="windw"):
        make_options(windw=3)


def test_subpixel_accuracy_on_a_fronto_parallel_plane():
    lf, truth = render([Layer(noise_texture((48, 48), seed=1), 0.37)])
    result = estimate_disparity(lf)
    error = np.abs(result.disparity - truth)[INNER]
    assert np.median(error) < 0.01
    assert np.mean(error > 0.07) < 0.02


def test_slanted_plane():
    lf, truth = render([Layer(noise_texture((48, 48), seed=2), 0.2, slope=(0.0, 0.012))])
    result = estimate_disparity(lf)
    error = np.abs(result.disparity - truth)[INNER]
    # A steep slant (0.55 px per view step across the image) with no depth jump: the side windows,
    # whose centre is off the pixel and which would carry a bias of about slope * r / 2, are not
    # offered (side_windows="edges"), so the result is as good as the paper's square-only windows.
    assert np.median(error) < 0.02
    square_only = estimate_disparity(lf, side_windows="occlusion")
    assert np.median(np.abs(square_only.disparity - truth)[INNER]) < 0.02


def test_search_range_found_without_one():
    lf, truth = render([Layer(noise_texture((40, 40), seed=5), -1.2)])
    lf = LightField(views=lf.views)  # no disparity_range
    result = estimate_disparity(lf)
    assert result.disparity_range[0] < -1.2 < result.disparity_range[1]
    assert np.median(np.abs(result.disparity - truth)[INNER]) < 0.02


@pytest.fixture(scope="module")
def square():
    lf, truth = occluding_square_scene(64, seed=3, back=-0.5, front=1.0)
    return lf, truth, estimate_disparity(lf)


def test_region_labels_sit_at_the_occlusion_edges(square):
    lf, truth, result = square
    labels = result.labels
    lo, hi = 20, 45  # the square covers centre-view rows/cols 20..44 (19.2 <= x < 44.8)
    row = (lo + hi) // 2
    # background just left of the square's left edge is occluded in the views to the right
    assert (labels[row, lo - 3:lo] == OCCLUDED).all()
    # the square's own edge pixels occlude the background
    assert (labels[row, lo:lo + 2] == OCCLUDING).all()
    # far from any edge there is no occlusion label
    assert not np.isin(labels[row, 2:6], (OCCLUDED, OCCLUDING)).any()
    assert not np.isin(labels[row - 3:row + 4, row - 3:row + 4], (OCCLUDED, OCCLUDING)).any()


def test_occlusion_edges_no_fatter_than_the_baseline(square):
    lf, truth, result = square
    base = estimate_baseline(lf, window=7, step=0.02).disparity
    band = np.zeros(truth.shape, bool)
    lo, hi = 20, 45
    band[lo - 8:hi + 8, lo - 8:hi + 8] = True
    band[lo + 8:hi - 8, lo + 8:hi - 8] = False
    ours_bad = np.sum((np.abs(result.disparity - truth) > 0.5) & band)
    base_bad = np.sum((np.abs(base - truth) > 0.5) & band)
    assert ours_bad <= base_bad
    assert ours_bad <= 0.02 * band.sum()


@pytest.fixture(scope="module")
def flat_patch():
    tex = noise_texture((56, 56), seed=4)
    tex[22:34, 22:34] = 0.5
    lf, truth = render([Layer(tex, 0.3)])
    return lf, truth, estimate_disparity(lf)


def test_textureless_patch_is_labelled_smooth(flat_patch):
    _, _, result = flat_patch
    assert (result.labels[26:30, 26:30] == SMOOTH).all()
    assert not (result.labels[:10, :10] == SMOOTH).any()  # the noise texture is not smooth


def test_textureless_patch_is_filled(flat_patch):
    # A 12-px patch: windows reaching its texture border, and the black-hole fill for what they
    # cannot reach (test_entropy_general.py checks a patch wider than the largest window).
    _, truth, result = flat_patch
    assert np.median(np.abs(result.disparity - truth)[22:34, 22:34]) < 0.05


def test_write_outputs(square, tmp_path):
    from recon.lf.pfm import read_pfm

    _, _, result = square
    paths = write_outputs(result, tmp_path / "out")
    names = {p.name for p in paths}
    for name in ("regions.png", "window_size.png", "window_shape.png", "window_size.npy",
                 "window_shape.npy", "initial_disparity.pfm", "refined_disparity.pfm", "holes.png"):
        assert name in names and (tmp_path / "out" / name).is_file()
    regions = cv2.imread(str(tmp_path / "out" / "regions.png"))[..., ::-1]
    assert np.array_equal(regions, REGION_COLOURS[result.labels])
    np.testing.assert_array_equal(read_pfm(tmp_path / "out" / "refined_disparity.pfm"),
                                  result.disparity)


def test_the_phases_compose_to_the_whole_estimator():
    """What tiling does (recon.scale.tiles): the phases of the plan in order, the tile-local ones
    through run_phase_on_tile (here one tile, the whole image, given the whole image's maps and
    numbers), the whole-image ones on the state; composed they give exactly the untiled result."""
    from recon.entropy.plan import PLAN, run_phase, run_phase_on_tile, shared_numbers, start, take_tiles

    lf, _ = occluding_square_scene(48, seed=5, back=-0.5, front=0.9, grid=(5, 5))
    whole = estimate_disparity(lf)
    state = start(lf, DEFAULTS)
    for phase in PLAN:
        if phase.tile_local:
            out = run_phase_on_tile(lf, phase, [getattr(state, name) for name in phase.reads],
                                    options=DEFAULTS, shared=shared_numbers(state))
            assert out.shape == (len(phase.writes), *lf.image_shape) and out.dtype == np.float32
            take_tiles(state, phase, out)
        else:
            run_phase(state, phase)
    np.testing.assert_array_equal(state.d0, whole.initial_disparity)
    np.testing.assert_array_equal(state.matched, whole.matched_disparity)
    np.testing.assert_array_equal(state.refined, whole.disparity)


def test_the_halo_is_the_sum_of_the_tile_local_steps_reaches():
    """A step added to the plan adds its reach to the halo tiles need, and nothing else does."""
    from recon.entropy.plan import PLAN, Phase, halo_px
    from recon.entropy.state import Reach, Step

    reach = Reach((9, 9), (-1.0, 2.0))
    base = halo_px(DEFAULTS, reach)
    assert base == sum(s.reach_px(DEFAULTS, reach) for p in PLAN if p.tile_local for s in p.steps)
    assert base >= max(DEFAULTS.window_sizes) // 2 + reach.view_px(DEFAULTS)
    extra = Step("extra", lambda state: None, lambda options, reach: 7)
    local = (*PLAN, Phase("extra", (extra,), tile_local=True))
    whole = (*PLAN, Phase("extra", (extra,), tile_local=False))
    assert halo_px(DEFAULTS, reach, local) == base + 7 and halo_px(DEFAULTS, reach, whole) == base


def test_disparity_bins_from_a_given_origin():
    from recon.entropy.entropy import quantise_disparity

    d = np.array([[0.31, 0.5], [0.77, 1.25]])
    np.testing.assert_array_equal(quantise_disparity(d, 0.1), [[0, 1], [4, 9]])
    np.testing.assert_array_equal(quantise_disparity(d, 0.1, origin=0.0), [[3, 5], [7, 12]])
    # a tile's halo may hold values below the whole image's origin: they take bin 0, never a
    # negative bin (the window selection refuses those)
    np.testing.assert_array_equal(quantise_disparity(d, 0.1, origin=0.5), [[0, 0], [2, 7]])
