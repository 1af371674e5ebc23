"""The entropy estimator on light fields whose disparity range nobody gave (a lab capture)."""

from __future__ import annotations

import dataclasses

import numpy as np

from recon.entropy import DEFAULTS, estimate_disparity
from recon.entropy.steps import unknown_range
from recon.entropy.initial import coarse_factor, downsample_views, initial_disparity
from recon.lf.lightfield import LightField
from recon.synthetic import Layer, noise_texture, occluding_square_scene, render


def _without_range(lf: LightField) -> LightField:
    return dataclasses.replace(lf, disparity_range=None)


def test_downsampled_views_carry_the_disparity_divided_by_the_factor():
    lf, _ = render([Layer(noise_texture((96, 96), seed=3, scale=4.0), 1.2)])
    coarse = downsample_views(np.asarray(lf.views, np.float32), 2)
    assert coarse.shape == (9, 9, 48, 48)
    d, _ = initial_disparity(coarse, disparity_range=(-2.0, 2.0), step=0.05, window=5)
    assert abs(np.median(d[8:-8, 8:-8]) - 0.6) < 0.03


def test_coarse_factor_keeps_a_usable_image():
    assert coarse_factor((512, 512)) == 4
    assert coarse_factor((226, 300)) == 2
    assert coarse_factor((64, 64)) == 1


def test_the_found_range_holds_the_scene_beyond_the_old_default_and_is_narrow():
    # A square at 5 px/view (closer than the old default range -4..4 reached) before a plane at -1.
    lf, truth = occluding_square_scene(192, back=-1.0, front=5.0)
    gray = np.asarray(lf.views, np.float32)
    lo, hi = unknown_range(gray, options=DEFAULTS, noise_sigma=0.0)
    assert lo <= -1.0 - 0.2 and hi >= 5.0 + 0.2
    assert hi - lo < 0.5 * (DEFAULTS.initial_range[1] - DEFAULTS.initial_range[0])


def test_estimate_without_a_range_finds_the_scene():
    lf, truth = occluding_square_scene(96, back=-0.5, front=2.5)
    result = estimate_disparity(_without_range(lf))
    lo, hi = result.disparity_range
    assert lo <= -0.5 and hi >= 2.5 and hi - lo < 4.5
    inner = (slice(10, -10), slice(10, -10))
    assert np.mean(np.abs(result.disparity - truth)[inner] > 0.07) < 0.05


def test_a_textureless_stripe_does_not_widen_the_found_range():
    # A plain vertical bar matches at any disparity; the range must come from the textured plane.
    texture = noise_texture((192, 192), seed=5)
    texture[:, 90:96] = 0.9
    lf, _ = render([Layer(texture, 1.0)])
    lo, hi = unknown_range(np.asarray(lf.views, np.float32), options=DEFAULTS, noise_sigma=0.0)
    assert lo <= 1.0 <= hi and hi - lo < 2.0
