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
