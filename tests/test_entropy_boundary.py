"""The visibility-aware boundary test after matching (recon/entropy/boundary.py,
docs/entropy-method.md "Boundaries"): background seen through slits, as in backgammon."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from recon.entropy import estimate_disparity, make_options
from recon.entropy.boundary import (boundary_candidates, boundary_reach_px, near_offsets,
                                    snap_boundaries, snap_boundaries_reference)
from recon.entropy.scenes import Surface, natural_texture, render_surfaces
from recon.lf.lightfield import LightField

FRONT, BACK = 0.5, -1.5


def slits(n: int, *, noise: float, grid: tuple[int, int] = (9, 9)):
    """A textured foreground (disparity 0.5) with 6-px horizontal slits every 16 px through which a
    darker textured background (-1.5) is seen: backgammon's layout. ``(lf, truth)``."""
    back = Surface(natural_texture((n, n), seed=1, contrast=0.3) * 0.6, BACK)
    front = Surface(natural_texture((n, n), seed=2, contrast=0.35), FRONT,
                    lambda y, x: np.mod(y, 16.0) >= 6.0)
    lf, truth, _ = render_surfaces([back, front], noise=noise, seed=0, grid=grid)
    return lf, truth


def fattened(truth: np.ndarray) -> np.ndarray:
    """The truth with the foreground grown by one pixel up and down (what windows do)."""
    grown = ndimage.binary_dilation(truth > 0, structure=np.ones((3, 1), bool))
    return np.where(grown, FRONT, BACK).astype(np.float32)


def anti_aliased_slits(n: int, *, noise: float, k: int = 4):
    """:func:`slits` rendered at ``k`` times the resolution and averaged over ``k x k`` blocks: the
    slits' rims are mixed pixels. The slits span ``[-0.3, 6.3)`` (mod 16) rows, so each rim pixel
    holds 20 % foreground and its centre sees the background. ``(lf, truth)``, truth at the pixel
    centres."""
    big = n * k

    def front_mask(y, x):
        return np.mod((y - (k - 1) / 2) / k + 0.3, 16.0) >= 6.6

    back = Surface(natural_texture((big, big), seed=1, contrast=0.3) * 0.6, BACK * k)
    front = Surface(natural_texture((big, big), seed=2, contrast=0.35), FRONT * k, front_mask)
    fine, _, _ = render_surfaces([back, front], seed=0, quantise=False)
    views = fine.views.reshape(9, 9, n, k, n, k).mean(axis=(3, 5))
    views = views + np.random.default_rng(0).normal(0, noise, views.shape)
    views = (np.round(np.clip(views, 0, 1) * 255) / 255).astype(np.float32)
    rows = np.arange(n, dtype=np.float64)[:, None] * np.ones((1, n))
    truth = np.where(np.mod(rows + 0.3, 16.0) >= 6.6, FRONT, BACK).astype(np.float32)
    return LightField(views=views, disparity_range=(BACK - 0.3, FRONT + 0.3)), truth


def snap(lf, matched, *, noise, fast=True, mix=0.3):
    run = snap_boundaries if fast else snap_boundaries_reference
    return run(lf.gray().astype(np.float32), matched, noise_sigma=max(noise, 0.5 / 255),
               disparity_range=(BACK - 0.3, FRONT + 0.3), jump=0.5, support=6, confidence=3.0, mix=mix)


@pytest.mark.parametrize("noise", [0.0, 3 / 255])
def test_fattened_slit_rows_go_back_to_the_background(noise):
    lf, truth = slits(64, noise=noise)
    matched = fattened(truth)
    out, changed = snap(lf, matched, noise=noise)
    wrong = (matched == FRONT) & (truth < 0)
    inner = np.zeros(truth.shape, bool)
    inner[8:-8, 8:-8] = True  # the image edge repeats pixels: views there see no slit
    assert wrong[inner].sum() > 150
    assert (changed & wrong & inner).sum() >= 0.9 * (wrong & inner).sum()
    assert not (changed & (truth > 0)).any()              # no foreground pixel is moved back
    np.testing.assert_array_equal(out[changed], BACK)
    np.testing.assert_array_equal(out[~changed], matched[~changed])


def test_anti_aliased_rims_go_back_by_the_mix_test():
    """Rim pixels holding 20 % foreground match neither surface; the mix test gives them to the
    background (their centres' surface); the view test alone leaves most of them."""
    lf, truth = anti_aliased_slits(64, noise=2 / 255)
    matched = fattened(truth)
    wrong = np.zeros(truth.shape, bool)
    wrong[8:-8, 8:-8] = ((matched == FRONT) & (truth < 0))[8:-8, 8:-8]
    restored = {}
    for mix in (0.0, 0.3):
        _, changed = snap(lf, matched, noise=2 / 255, mix=mix)
        assert not (changed & (truth > 0)).any()
        restored[mix] = (changed & wrong).sum()
    assert restored[0.3] >= 0.5 * wrong.sum()
    assert restored[0.3] >= restored[0.0] + 0.15 * wrong.sum()


def test_a_correct_map_is_left_alone_under_noise():
    lf, truth = slits(64, noise=3 / 255)
    _, changed = snap(lf, truth.astype(np.float32), noise=3 / 255)
    assert not changed.any()


def test_hard_edged_bars_keep_their_rims():
    """suite/bars, noise-free and hard-edged: the near value sampled at a rim pixel mixes in the
    background beside it in most views, and the point hidden behind it can match its grey value by
    chance. The views in line with the pixel (du or dv 0) must agree with the view test; without
    that check 16 correct rim pixels were moved back."""
    from recon.entropy.scenes import make_scene

    scene = make_scene("bars", size=96)
    _, changed = snap_boundaries(scene.lf.gray().astype(np.float32), scene.truth.astype(np.float32),
                                 noise_sigma=0.5 / 255, disparity_range=scene.lf.disparity_range,
                                 jump=0.5, support=6, confidence=3.0, mix=0.0)
    assert not changed.any()


@pytest.mark.parametrize("anti_aliased", [False, True])
def test_reference_and_compiled_twins_agree(anti_aliased):
    if anti_aliased:  # exercises the mix test
        lf, truth = anti_aliased_slits(32, noise=2 / 255)
    else:
        lf, truth = slits(40, noise=2 / 255, grid=(5, 5))
    matched = fattened(truth)
    matched[20, 10:14] = 0.2  # a few values off the two layers
    fast, fast_changed = snap(lf, matched, noise=2 / 255)
    ref, ref_changed = snap(lf, matched, noise=2 / 255, fast=False)
    assert fast_changed.sum() > 20
    np.testing.assert_array_equal(fast_changed, ref_changed)
    np.testing.assert_array_equal(fast, ref)


def test_candidates_need_a_supported_farther_neighbour():
    m = np.zeros((20, 20), np.float32)
    m[:, 10:] = 1.0            # an edge: the pixels at x = 10 are candidates, far value 0
    m[5, 3] = -1.0             # an outlier: its neighbours are not candidates
    ys, xs, far = boundary_candidates(m, jump=0.5, support=6)
    assert set(xs.tolist()) == {10} and (far == 0).all() and len(ys) == 20
    assert near_offsets()[0] == 0 and np.isclose(np.abs(near_offsets()).max(), 0.4)
    assert boundary_reach_px((-1.5, 0.8), (9, 9)) >= 4 * 2.3


def test_the_estimator_gives_slit_rows_back_to_the_background():
    """Fails without boundary_snap: the line search alone puts the slits' rims on the foreground."""
    lf, truth = slits(64, noise=2 / 255)
    inner = (slice(8, -8), slice(8, -8))
    counts = {}
    for on in (False, True):
        d = estimate_disparity(lf, boundary_snap=on).disparity
        background = truth[inner] < 0
        counts[on] = (background & (d[inner] > (FRONT + BACK) / 2)).sum()
        assert not ((truth[inner] > 0) & (np.abs(d - truth)[inner] > 0.07)).any()
    assert counts[False] > 100
    assert counts[True] <= 0.7 * counts[False]


def test_options_are_checked_and_the_paper_preset_has_no_snap():
    assert make_options(preset="paper").boundary_snap is False
    with pytest.raises(ValueError, match="boundary_support"):
        estimate_disparity(slits(24, noise=0)[0], boundary_support=0)


def test_the_initial_disparity_can_be_snapped_too():
    """boundary_snap_initial: d0's rims go back before the layers and labels are made from it."""
    lf, truth = slits(64, noise=2 / 255)
    inner = (slice(8, -8), slice(8, -8))
    rims = {}
    for on in (False, True):
        d0 = estimate_disparity(lf, boundary_snap_initial=on).initial_disparity
        rims[on] = ((truth[inner] < 0) & (d0[inner] > (FRONT + BACK) / 2)).sum()
    assert rims[False] > 100 and rims[True] <= rims[False] - 20  # measured 176 -> 144


def test_a_shaded_silhouette_is_not_read_as_a_mix_when_extrapolated():
    """A near surface that brightens towards its rim (shading at a curved silhouette) gives the rim
    pixel a grey value between its inside and the background: a mix fraction of 0.375 read
    naively, none once the inside's gradient is carried on to the rim."""
    from recon.entropy.boundary import rim_evidence

    m = np.where(np.arange(12) >= 5, 1.0, -1.0).astype(np.float32)[None, :].repeat(9, axis=0)
    row = np.array([0.8] * 5 + [0.65, 0.4, 0.25, 0.25, 0.25, 0.25, 0.25], np.float32)
    gray = np.broadcast_to(row, (3, 3, 9, 12)).copy()
    ys, xs, far = np.array([4]), np.array([5]), np.array([-1.0], np.float32)
    naive, _ = rim_evidence(gray, m, ys, xs, far, np.array([0.8]), jump=0.5, min_contrast=0.05)
    carried, _ = rim_evidence(gray, m, ys, xs, far, np.array([0.8]), jump=0.5, min_contrast=0.05,
                              extrapolate=True)
    assert naive[0] == pytest.approx(0.375) and not carried[0] < 0.5
