"""recon.entropy.regions: the compiled occlusion test gives its readable twin's map."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy import regions

from recon.entropy.regions import (different_neighbours, noise_sigma, noise_sigma_reference, occlusion_diffs,
                                   occlusion_diffs_reference)
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


def test_occlusion_diffs_in_bands_of_rows_are_the_references_bit_for_bit(monkeypatch):
    # quantised layers (exact ties of the top and bottom layers), signed zeros, every view of a
    # 5x5 grid; the compiled twin cut into four bands of rows whose warps reach across the cuts
    import numba

    monkeypatch.setattr(numba, "get_num_threads", lambda: 4)
    rng = seeded()
    layers = (np.round(rng.normal(0, 0.6, (96, 23)) * 4) / 4).astype(np.float32)
    layers[30, 2] = 2.5  # a far-reaching landing
    layers[80:, :] = -0.0
    offsets = [(du, dv) for du in range(-2, 3) for dv in range(-2, 3) if (du, dv) != (0, 0)]
    for reference, fast in zip(occlusion_diffs_reference(layers, offsets, layer_gap=0.25),
                               occlusion_diffs(layers, offsets, layer_gap=0.25)):
        assert fast.dtype == np.float32 and fast.tobytes() == reference.tobytes()


def test_different_neighbours_counts_with_tolerance():
    img = np.zeros((7, 7), np.float32)
    img[3, 3] = 1.0
    psi = different_neighbours(img, size=3, tolerance=0.1)
    assert psi[3, 3] == 8 and psi[3, 4] == 1 and psi[0, 0] == 0
    noisy = img + 0.01 * seeded().standard_normal((7, 7)).astype(np.float32)
    assert different_neighbours(noisy, size=3, tolerance=0.1)[0, 0] == 0


def test_noise_sigma_is_scipys_convolution_bit_for_bit():
    # float32 and float64 images of many shapes, values from 1e-8 to 1e8 (the sums round), a
    # constant image (no noise) and a linear ramp (which the operator does not see)
    rng = seeded()
    images = [np.full((9, 7), 0.25, np.float32), np.add.outer(np.arange(12.0), 0.5 * np.arange(5.0))]
    for i in range(40):
        h, w = rng.integers(3, 40, 2)
        scale = 10.0 ** rng.uniform(-8, 8, (h, w)) if i % 2 else rng.uniform(0, 255)
        images.append((rng.standard_normal((h, w)) * scale).astype(np.float32 if i % 3 else np.float64))
    for image in images:
        assert np.float64(noise_sigma(image)).tobytes() == np.float64(noise_sigma_reference(image)).tobytes()
    assert noise_sigma(images[0]) == 0.0 and noise_sigma(images[1]) == 0.0


@pytest.mark.parametrize("band_rows", [5, 64])
def test_occlusion_diffs_of_far_layers_with_few_edges_are_the_references_bit_for_bit(monkeypatch, band_rows):
    # layers far from 0 (every pixel lands rows away) with a small spread, most pixels far from
    # an edge (the compiled twin leaves those out), in bands of rows thinner than the shifts; values
    # in steps of 1/128, so that the reference's float64 sums and the twin's float32 ones are exact
    monkeypatch.setattr(regions, "OCCLUSION_BAND_ROWS", band_rows)
    rng = seeded()
    y, x = np.mgrid[0:70, 0:53]
    layers = (3.0 + (x // 9) / 64 + (y // 11) / 128).astype(np.float32)  # a slant in exact steps
    layers[20:34, 12:30] = 4.25  # a closer square
    layers[45:70, 40:42] = 3.625  # a thin bar reaching the bottom
    layers[rng.random(layers.shape) < 0.01] = 4.5  # specks
    offsets = [(du, dv) for du in range(-3, 4) for dv in range(-3, 4) if (du, dv) != (0, 0)]
    neg_r, pos_r = occlusion_diffs_reference(layers, offsets, layer_gap=0.25)
    neg_f, pos_f = occlusion_diffs(layers, offsets, layer_gap=0.25)
    assert (neg_r < 0).sum() > 100 and (pos_r > 0).sum() > 100
    assert neg_f.tobytes() == neg_r.tobytes() and pos_f.tobytes() == pos_r.tobytes()
