"""recon.entropy.regions: the compiled occlusion test gives its readable twin's map."""

from __future__ import annotations

import numpy as np

from recon.entropy.regions import different_neighbours, occlusion_diffs, occlusion_diffs_reference
from kernel_inputs import seeded


def test_occlusion_diffs_matches_reference_and_marks_the_right_sides():
    layers = np.zeros((20, 20), np.float32)
    layers[:, 10:] = 1.0  # closer right half
    offsets = [(-4, -4), (-4, 0), (-4, 4), (0, -4), (0, 4), (4, -4), (4, 0), (4, 4)]
    neg_r, pos_r = occlusion_diffs_reference(layers, offsets, layer_gap=0.25)
    neg_f, pos_f = occlusion_diffs(layers, offsets, layer_gap=0.25)
    np.testing.assert_allclose(neg_f, neg_r)
    np.testing.assert_allclose(pos_f, pos_r)
    row = 10
    assert (neg_r[row, 6:10] < 0).all()        # background just left of the edge: occluded
    assert (neg_r[row, :4] == 0).all()         # far from it: not
    assert (pos_r[row, 10:14] > 0).all()       # foreground at the edge: occluding
    assert (neg_r[:, 10:] == 0).all()          # the front is never occluded


def test_different_neighbours_counts_with_tolerance():
    img = np.zeros((7, 7), np.float32)
    img[3, 3] = 1.0
    psi = different_neighbours(img, size=3, tolerance=0.1)
    assert psi[3, 3] == 8 and psi[3, 4] == 1 and psi[0, 0] == 0
    noisy = img + 0.01 * seeded().standard_normal((7, 7)).astype(np.float32)
    assert different_neighbours(noisy, size=3, tolerance=0.1)[0, 0] == 0
