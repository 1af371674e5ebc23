"""Reference and compiled kernels of recon.entropy agree, and each does its maths on tiny inputs."""

from __future__ import annotations

import numpy as np

from recon.entropy.entropy import (matching_entropy_reference, select_windows,
                                   select_windows_reference)
from recon.entropy.matching import (WindowCost, block_abs_diff_fast, block_abs_diff_reference,
                                    set_view_counts, subpixel_argmin, window_cost_reference)
from recon.entropy.refine import tv_energy, tv_refine
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH, TEXTURE
from recon.entropy.regions import (different_neighbours, occlusion_diffs_fast,
                                   occlusion_diffs_reference)


def _rng():
    return np.random.default_rng(7)


def test_block_abs_diff_fast_matches_reference():
    gray = _rng().random((5, 5, 11, 13)).astype(np.float32)
    mask = np.ones((5, 5), bool)
    mask[0, 1] = False
    for d in (-1.3, 0.0, 0.37):
        ref = block_abs_diff_reference(gray, d, view_mask=mask)
        fast = block_abs_diff_fast(gray, d, view_mask=mask)
        np.testing.assert_allclose(fast, ref, atol=1e-5)


def test_block_abs_diff_is_zero_at_the_true_disparity_of_a_shifted_ramp():
    # View (u, v) shows the centre point p at p - (du, dv) d, i.e. I_uv(q) = I_c(q + (du, dv) d);
    # bilinear interpolation reproduces a linear ramp exactly away from the border.
    U = V = 5
    y, x = np.mgrid[0:16, 0:16].astype(np.float32)
    d = 0.4
    gray = np.stack([np.stack([0.01 * (x + (v - 2) * d) + 0.02 * (y + (u - 2) * d)
                               for v in range(V)]) for u in range(U)])
    ad = block_abs_diff_fast(gray, d).sum(0)
    assert ad[3:-3, 3:-3].max() < 1e-5


def test_window_cost_fast_matches_reference():
    rng = _rng()
    blocks = rng.random((9, 12, 10)).astype(np.float32)
    shape = rng.integers(0, 11, (12, 10))
    size = rng.choice([3, 5, 7], (12, 10))
    sets = np.where(rng.random((12, 10)) < 0.5, shape, 0)
    counts = set_view_counts((9, 9))
    ref = window_cost_reference(blocks, shape, size, sets, counts)
    fast = WindowCost(shape, size, sets, counts)(blocks)
    np.testing.assert_allclose(fast, ref, rtol=1e-5)


def test_subpixel_argmin_finds_the_vertex_of_a_parabola():
    cands = np.arange(-1, 1.0001, 0.1)
    true = np.array([[0.234, -0.51]])
    costs = (cands[:, None, None] - true[None]) ** 2
    d, _ = subpixel_argmin(costs.astype(np.float32), cands)
    np.testing.assert_allclose(d, true, atol=1e-4)


def test_occlusion_diffs_fast_matches_reference_and_marks_the_right_sides():
    layers = np.zeros((20, 20), np.float32)
    layers[:, 10:] = 1.0  # closer right half
    offsets = [(-4, -4), (-4, 0), (-4, 4), (0, -4), (0, 4), (4, -4), (4, 0), (4, 4)]
    neg_r, pos_r = occlusion_diffs_reference(layers, offsets, layer_gap=0.25)
    neg_f, pos_f = occlusion_diffs_fast(layers, offsets, layer_gap=0.25)
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
    noisy = img + 0.01 * _rng().standard_normal((7, 7)).astype(np.float32)
    assert different_neighbours(noisy, size=3, tolerance=0.1)[0, 0] == 0


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
    rng = _rng()
    grey = rng.integers(0, 16, (14, 12))
    disp = np.where(np.arange(12)[None] < 6, 0, 3) + rng.integers(0, 2, (14, 12))
    labels = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH], (14, 12)).astype(np.uint8)
    kw = dict(sizes=(3, 5, 7), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0)
    s_ref, z_ref, e_ref = select_windows_reference(grey, disp, labels, **kw)
    s_f, z_f, e_f = select_windows(grey, disp, labels, **kw)
    np.testing.assert_allclose(e_f, e_ref, atol=1e-5)
    assert np.array_equal(s_f, s_ref) and np.array_equal(z_f, z_ref)


def test_window_avoids_a_disparity_edge():
    rng = _rng()
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


def test_tv_refine_invariants():
    rng = _rng()
    f = (np.linspace(0, 1, 16)[None] + 0.05 * rng.standard_normal((16, 16))).astype(np.float32)
    mask = np.zeros((16, 16), bool)
    mask[4:12, 4:12] = True
    mu = tv_refine(f, mask, gamma=0.2, iterations=300)
    assert np.array_equal(mu[~mask], f[~mask])
    assert tv_energy(mu, f, mask, 0.2) < tv_energy(f, mask=mask, data=f, gamma=0.2)
    # a constant map stays constant
    const = np.full((8, 8), 0.3, np.float32)
    np.testing.assert_allclose(tv_refine(const, np.ones((8, 8), bool), gamma=0.2, iterations=50),
                               const, atol=1e-6)
    # it is the minimum: no small random perturbation of the mask pixels does better
    best = tv_energy(mu, f, mask, 0.2)
    for _ in range(20):
        trial = mu.copy()
        trial[mask] += 0.003 * rng.standard_normal(mask.sum())
        assert tv_energy(trial, f, mask, 0.2) >= best - 1e-4


def test_joint_line_search_fast_matches_reference():
    from recon.entropy.matching import joint_line_search, joint_line_search_reference

    rng = _rng()
    gray = rng.random((3, 3, 9, 10)).astype(np.float32)
    windows = [(s, z) for s in range(11) for z in (3, 5)]
    penalty = rng.normal(0, 1, (9, 10, len(windows))).astype(np.float32)
    penalty[rng.random(penalty.shape) < 0.4] = np.inf
    penalty[..., 0] = 0.0  # every pixel keeps at least the 3x3 square
    occluded = rng.random((9, 10)) < 0.5
    cands = np.array([-0.6, -0.2, 0.1, 0.5])
    i_ref, obj_ref, k_ref = joint_line_search_reference(
        gray, cands, windows=windows, penalty=penalty, use_shape_set=occluded, intensity_scale=255.0)
    d, obj, k, _ = joint_line_search(gray, cands, windows=windows, penalty=penalty,
                                     use_shape_set=occluded, intensity_scale=255.0)
    np.testing.assert_allclose(obj, obj_ref, rtol=1e-4)
    assert np.array_equal(k, k_ref)
    assert (np.abs(d - cands[i_ref]) <= 0.5 * 0.4 + 1e-6).all()


def test_centroid_correction_fast_agrees_with_reference_and_ignores_the_origin():
    from recon.entropy.refine import centroid_correction, centroid_correction_reference
    from recon.entropy.windows import N_SHAPES, window_rect

    rng = np.random.default_rng(4)
    H, W = 30, 34
    yy, xx = np.mgrid[0:H, 0:W]
    d = 0.3 + 0.01 * yy - 0.02 * xx + rng.normal(0, 0.002, (H, W))
    d[:, 20:] += 0.8  # a step: planes fitted across it are rejected, far from the threshold
    table = np.array([[window_rect(s, z) if z % 2 else (0, 0, 0, 0) for z in range(16)]
                      for s in range(N_SHAPES)], np.int64)
    rects = table[rng.integers(0, N_SHAPES, (H, W)), rng.choice([3, 5, 9, 15], (H, W))]
    kwargs = dict(max_residual=0.05, max_shift=0.2)
    fast = centroid_correction(d.astype(np.float32), rects, **kwargs)
    reference = centroid_correction_reference(d.astype(np.float32), rects, **kwargs)
    np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-6)
    assert np.abs(fast - d).max() > 0.01  # it did correct something
    crop = centroid_correction(np.ascontiguousarray(d[5:, 7:], dtype=np.float32), rects[5:, 7:], **kwargs)
    # away from the crop's edge (15-px windows reach 7 px) a crop is bit-identical to the whole
    np.testing.assert_array_equal(crop[7:, 7:], fast[12:, 14:])


def test_tv_refine_fast_agrees_with_reference():
    from recon.entropy.refine import tv_refine_reference

    rng = np.random.default_rng(7)
    f = (0.5 + 0.1 * rng.standard_normal((23, 31))).astype(np.float32)
    mask = rng.random(f.shape) < 0.7
    holes = np.zeros(f.shape, bool)
    holes[5:9, 10:16] = True  # a hole: data term dropped, started from the harmonic fill
    weight = np.where(holes, rng.uniform(0.0, 1.0, f.shape), 0.0)  # valley weights, some 0
    weight[5, 10:13] = 0.0
    for kwargs in ({}, {"holes": holes}, {"holes": holes, "hole_weight": weight}):
        fast = tv_refine(f, mask, gamma=0.2, iterations=120, **kwargs)
        reference = tv_refine_reference(f, mask, gamma=0.2, iterations=120, **kwargs)
        np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-7)
        assert np.abs(fast - f).max() > 0.01  # it did smooth something
    # the smallest image the kernel takes
    np.testing.assert_allclose(tv_refine(f[:2, :2], mask[:2, :2] | True, gamma=0.2, iterations=10),
                               tv_refine_reference(f[:2, :2], mask[:2, :2] | True, gamma=0.2,
                                                   iterations=10), rtol=0, atol=1e-7)
