"""Window choice on curved and creased surfaces (docs/entropy-method.md, "Shapes: creases")."""

from __future__ import annotations

import numpy as np

from recon.entropy import estimate_disparity
from recon.entropy.entropy import select_windows, select_windows_reference
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH, TEXTURE
from recon.entropy.scenes import Surface, natural_texture, render_surfaces
from recon.entropy.windows import curvature_size_cap

SIZES = (3, 5, 7, 9, 11, 13, 15)


def test_curvature_size_cap_ignores_planes_and_caps_at_a_crease():
    y, x = np.mgrid[0:60, 0:60].astype(np.float64)
    plane = 0.4 + 0.03 * x - 0.02 * y
    np.testing.assert_array_equal(curvature_size_cap(plane, SIZES, tolerance=0.01)[8:-8, 8:-8], 15)
    pit = 0.03 * np.maximum(np.abs(y - 30), np.abs(x - 30))  # a square pit, slope 0.03 px/view/px
    cap = curvature_size_cap(pit, SIZES, tolerance=0.01)
    assert cap[30, 30] <= 5                                      # at the apex
    assert cap[30, 36] < 15                                      # a square there reaches the ridges
    assert cap[30, 50] == 15                                     # mid-face: no crease within 7 px
    assert (cap >= 3).all() and set(np.unique(cap)) <= set(SIZES)


def test_curvature_size_cap_reads_only_measured_pixels():
    # A bent fill (a black hole's harmonic fill) beside a plane: the plane is not capped by it.
    y, x = np.mgrid[0:40, 0:40].astype(np.float64)
    layers = 0.2 + 0.01 * x
    filled = x >= 24
    layers[filled] += 0.05 * (x[filled] - 23)   # a fill that bends away from the plane
    blind = curvature_size_cap(layers, SIZES, tolerance=0.01)
    seeing = curvature_size_cap(layers, SIZES, tolerance=0.01, measured=~filled)
    assert blind[20, 23] == 3 and seeing[20, 23] == 15     # beside the fill: mostly fill in view
    assert blind[20, 10] == seeing[20, 10] == 15            # far from it: a plane


def test_select_windows_with_a_size_cap_matches_reference():
    rng = np.random.default_rng(5)
    grey = rng.integers(0, 16, (14, 12))
    disp = rng.integers(0, 3, (14, 12))
    labels = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH], (14, 12)).astype(np.uint8)
    cap = rng.choice([3, 5, 7], (14, 12))
    kw = dict(sizes=(3, 5, 7), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0,
              side_radius=rng.integers(0, 5, (14, 12)), max_size=cap)
    s_ref, z_ref, e_ref = select_windows_reference(grey, disp, labels, **kw)
    s_f, z_f, e_f = select_windows(grey, disp, labels, **kw)
    np.testing.assert_allclose(e_f, e_ref, atol=1e-5)
    assert np.array_equal(s_f, s_ref) and np.array_equal(z_f, z_ref)
    square = (labels >= TEXTURE) & (s_f == 0)
    assert (z_f[square] <= cap[square]).all()


def _pit(n: int = 72):
    c = n / 2

    def disp(y, x):  # a concave pyramid: -0.2 at the bottom, slope 0.03 px/view per pixel
        return -0.2 + 0.03 * np.maximum(np.abs(y - c), np.abs(x - c))

    return render_surfaces([Surface(natural_texture((n, n), seed=3, contrast=0.3), disp)], seed=3)


def test_square_windows_do_not_average_across_a_pit():
    # A square matched with one disparity finds about the mean disparity under it; at the bottom of
    # a pit that is above the pixel's. Capped by the layer map's curvature, the window stays small.
    lf, truth, _ = _pit()
    inner = (slice(26, 46), slice(26, 46))
    capped = estimate_disparity(lf)
    free = estimate_disparity(lf, crease_tolerance=0.0)
    e_cap = np.abs(capped.disparity - truth)[inner]
    e_free = np.abs(free.disparity - truth)[inner]
    assert np.mean(e_free > 0.07) > 0.05
    assert np.mean(e_cap > 0.07) < 0.6 * np.mean(e_free > 0.07)  # 19 % -> 9.5 %
    assert capped.window_size[36, 36] <= 7


def test_crease_tolerance_rises_with_the_noise_of_d0():
    # The same pit, once measured cleanly and once with noise in d0: the noisy one is capped less.
    y, x = np.mgrid[0:60, 0:60].astype(np.float64)
    pit = 0.03 * np.maximum(np.abs(y - 30), np.abs(x - 30))
    noisy = pit + np.random.default_rng(2).normal(0, 0.02, pit.shape)
    clean_cap = curvature_size_cap(pit, SIZES, tolerance=0.01, initial=pit, noise_factor=1.5)
    noisy_cap = curvature_size_cap(pit, SIZES, tolerance=0.01, initial=noisy, noise_factor=1.5)
    fixed_cap = curvature_size_cap(pit, SIZES, tolerance=0.01)
    np.testing.assert_array_equal(clean_cap, fixed_cap)
    assert noisy_cap[30, 30] > clean_cap[30, 30]
    assert (noisy_cap >= clean_cap).all()
