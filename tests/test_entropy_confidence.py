"""The confidence of black holes (recon/entropy/confidence.py): a hole is no surer than its rim, and
a steep fill between rims that disagree is unsure."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy.confidence import confidence_map


def _hole_scene(rim_ambiguity: int):
    """A 3-px black hole in a 11x11 map whose measured rim has cost valleys ``rim_ambiguity`` wide."""
    refined = np.full((11, 11), 1.0, np.float32)
    holes = np.zeros((11, 11), bool)
    holes[4:7, 4:7] = True
    ambiguity = np.full((11, 11), rim_ambiguity)
    ambiguity[holes] = 200
    return dict(refined=refined, matched=refined, ambiguity=ambiguity, step=0.02, disparity_range=(0.0, 2.0),
                holes=holes)


def test_a_hole_is_no_surer_than_its_rim():
    sure = confidence_map(**_hole_scene(1))
    unsure = confidence_map(**_hole_scene(40))  # rim valleys 0.78 px/view wide: confidence ~0.07
    assert sure[5, 5] == pytest.approx(0.5)  # a hole inside surely matched pixels keeps 0.5
    assert unsure[0, 0] < 0.1 and unsure[5, 5] < 0.4  # ... one inside unsure pixels falls below the export
    assert unsure[5, 5] == pytest.approx(0.5 * unsure[0, 0] / 0.25, rel=0.05)
    legacy = confidence_map(**_hole_scene(40), hole_support=0.0)
    assert legacy[5, 5] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="hole_support"):
        confidence_map(**_hole_scene(1), hole_support=2.0)


def test_a_hole_filled_as_a_steep_ramp_is_unsure():
    scene = _hole_scene(1)
    x = np.arange(11, dtype=np.float32)
    gentle = dict(scene, refined=np.tile(1.0 + 0.02 * x, (11, 1)), matched=np.tile(1.0 + 0.02 * x, (11, 1)))
    # Rims that disagree (1.1 left, 1.9 right, both matched surely): the fill is a ramp between them.
    ramp = np.where(x < 5, 1.1, 1.9).astype(np.float32) + np.where(x == 5, -0.4, 0.0).astype(np.float32)
    steep = dict(scene, refined=np.tile(ramp, (11, 1)), matched=np.tile(ramp, (11, 1)))
    assert confidence_map(**gentle)[5, 5] == pytest.approx(0.5 * np.exp(-0.2), rel=0.02)  # a plane: kept at 0.4
    assert confidence_map(**steep)[5, 5] < 0.05
    assert confidence_map(**steep, hole_ramp=0.0)[5, 5] > 0.4


def test_the_bands_give_the_whole_map_factors():
    # Holes across the bands' edges, non-finite values among them and around them: the map made band
    # by band (each band's factors once, the holes' own after the support's fill) is, bit for bit,
    # the factors of the module docstring taken over the whole map at once.
    from recon.entropy.confidence import BAND_ROWS
    from recon.entropy.median import median_filter_nearest
    from recon.entropy.refine import harmonic_fill

    rng = np.random.default_rng(8)
    H, W = 2 * BAND_ROWS + 9, 23
    refined = (0.8 + 0.2 * rng.standard_normal((H, W))).astype(np.float32)
    refined[rng.random((H, W)) < 0.02] = np.nan
    matched = refined + np.float32(0.05) * rng.standard_normal((H, W)).astype(np.float32)
    ambiguity = rng.integers(1, 30, (H, W))
    holes = rng.random((H, W)) < 0.1
    holes[BAND_ROWS - 5:BAND_ROWS + 5, 3:12] = True
    kwargs = dict(refined=refined, matched=matched, ambiguity=ambiguity, step=0.02, disparity_range=(0.2, 1.4))
    with np.errstate(invalid="ignore"):
        r, m = refined.astype(np.float64), matched.astype(np.float64)
        finite = np.isfinite(r)
        median = median_filter_nearest(np.where(finite, r, np.nanmedian(r)), size=5)
        neighbours = np.exp(-np.abs(r - median) / 0.1)
        on_end = (np.abs(m - 0.2) < 0.01) | (np.abs(m - 1.4) < 0.01)
        valley = np.exp(-np.maximum(ambiguity - 1.0, 0) * 0.02 / 0.3)
        conf = valley * np.exp(-np.abs(r - m) / 0.1) * neighbours * ~on_end
        support = harmonic_fill(np.where(holes | ~finite, 0.0, np.nan_to_num(conf)).astype(np.float32), holes)
        filled = np.where(finite, r, 0.0)
        ramp = np.exp(-np.hypot(*np.gradient(filled)) / 0.1)
        factor = 0.5 * neighbours * np.clip(support.astype(np.float64) / 0.25, 0.0, 1.0) * ramp
        inside = finite & (r >= 0.2 - 1e-6) & (r <= 1.4 + 1e-6)
    expected = np.where(inside, np.nan_to_num(np.where(holes, factor, conf)), 0.0).astype(np.float32)
    np.testing.assert_array_equal(confidence_map(**kwargs, holes=holes), expected)
    without_holes = np.where(inside, np.nan_to_num(conf), 0.0).astype(np.float32)
    np.testing.assert_array_equal(confidence_map(**kwargs), without_holes)
