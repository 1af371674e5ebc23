"""recon.entropy.entropy: the matching entropy's terms, and the compiled window choice gives its
readable twin's."""

from __future__ import annotations

import numpy as np

from recon.entropy.entropy import matching_entropy_reference, select_windows, select_windows_reference
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH, TEXTURE
from kernel_inputs import seeded


def test_matching_entropy_terms():
    grey = np.zeros((9, 9), np.int64)
    disp = np.zeros((9, 9), np.int64)
    labels = np.full((9, 9), TEXTURE, np.uint8)
    # constant window: all terms zero
    assert matching_entropy_reference(grey, disp, labels, 4, 4, 0, 3, alpha1=1, alpha2=1) == 0
    # two equally likely grey levels: ln 2 of texture richness
    grey[:, 4:] = 1
    e = matching_entropy_reference(grey, disp, labels, 4, 4, 0, 9, alpha1=1, alpha2=0)
    np.testing.assert_allclose(e, -(4 / 9 * np.log(4 / 9) + 5 / 9 * np.log(5 / 9)))
    # the same split in disparity cancels it
    disp[:, 4:] = 1
    assert abs(matching_entropy_reference(grey, disp, labels, 4, 4, 0, 9, alpha1=1, alpha2=0)) < 1e-12
    # mismatched pixels lower the score of an occluded pixel's window
    labels[:, 6:] = OCCLUDING
    labels[4, 4] = OCCLUDED
    with_occ = matching_entropy_reference(grey, disp, labels, 4, 4, 0, 9, alpha1=1, alpha2=1)
    assert with_occ < 0


def test_select_windows_fast_matches_reference():
    rng = seeded()
    grey = rng.integers(0, 16, (14, 12))
    disp = np.where(np.arange(12)[None] < 6, 0, 3) + rng.integers(0, 2, (14, 12))
    labels = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH], (14, 12)).astype(np.uint8)
    kw = dict(sizes=(3, 5, 7), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0)
    s_ref, z_ref, e_ref = select_windows_reference(grey, disp, labels, **kw)
    s_f, z_f, e_f = select_windows(grey, disp, labels, **kw)
    np.testing.assert_allclose(e_f, e_ref, atol=1e-5)
    assert np.array_equal(s_f, s_ref) and np.array_equal(z_f, z_ref)


def test_window_avoids_a_disparity_edge():
    rng = seeded()
    grey = rng.integers(0, 8, (31, 31))  # texture whose grey entropy saturates (ln 8)
    disp = np.zeros((31, 31), np.int64)
    disp[:, 16:] = 5  # a depth edge two pixels right of the centre column 14
    labels = np.full((31, 31), TEXTURE, np.uint8)
    labels[:, 14] = OCCLUDED
    shape, size, _ = select_windows(grey, disp, labels, sizes=(3, 5, 7, 9, 11, 13, 15),
                                    alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0)
    assert shape[15, 14] in (1, 5, 7)  # a window that extends left, away from the edge
    assert size[15, 14] >= 11
    assert size[15, 12] <= 7  # square windows shrink near the edge (it is 4 px away)
    assert size[15, 3] >= 11  # and large far from it
