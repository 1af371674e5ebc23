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
    """What tiling calls (recon.scale.tiles): the raw initial search, the whole-image hole fill,
    the matching with the whole image's noise sigma and bin origin, the whole-image refinement;
    composed they give exactly the untiled result."""
    from recon.entropy.estimate import fill_initial, layer_origin, refine_global

    lf, _ = occluding_square_scene(48, seed=5, back=-0.5, front=0.9, grid=(5, 5))
    whole = estimate_disparity(lf)
    first = estimate_disparity(lf, stop_after="initial")
    sigma = first.info["noise_sigma"]
    d0, _ = fill_initial(first.initial_disparity, first.info["initial_ambiguity"], first.info["flat"],
                         options=DEFAULTS)
    np.testing.assert_array_equal(d0, whole.initial_disparity)
    origin = layer_origin(d0, first.info["initial_ambiguity"], first.info["flat"], options=DEFAULTS)
    second = estimate_disparity(lf, stop_after="matching", noise_sigma=sigma, disparity_origin=origin,
                                initial=(d0, first.info["initial_ambiguity"]))
    np.testing.assert_array_equal(second.matched_disparity, whole.matched_disparity)
    refined, _ = refine_global(second.matched_disparity, second.labels, second.info["flat"],
                               second.info["ambiguity"], options=DEFAULTS)
    np.testing.assert_array_equal(refined, whole.disparity)
    with pytest.raises(ValueError, match="stop_after"):
        estimate_disparity(lf, stop_after="windows")


def test_disparity_bins_from_a_given_origin():
    from recon.entropy.entropy import quantise_disparity

    d = np.array([[0.31, 0.5], [0.77, 1.25]])
    np.testing.assert_array_equal(quantise_disparity(d, 0.1), [[0, 1], [4, 9]])
    np.testing.assert_array_equal(quantise_disparity(d, 0.1, origin=0.0), [[3, 5], [7, 12]])
