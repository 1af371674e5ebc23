"""recon/native/views.c: the view filters' mask warp and blend give the bits of their numpy/OpenCV twins
(recon/entropy/noise.py), on random inputs and odd values, for every thread count, and without AVX-512."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import require_native, use_native_build

# the twins' casts of NaN and infinite landings warn (and drop them, as the C kernel does)
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")


def _odd_disparities(rng, shape):
    # NaN, infinities, huge values, -0.0 and disparities whose landings fall exactly on half pixels
    d = rng.uniform(-2.5, 2.5, shape)
    pick = rng.random(shape)
    d[pick < 0.04] = np.nan
    d[(pick >= 0.04) & (pick < 0.06)] = np.inf
    d[(pick >= 0.06) & (pick < 0.08)] = -np.inf
    d[(pick >= 0.08) & (pick < 0.09)] = 1e30
    d[(pick >= 0.09) & (pick < 0.10)] = -0.0
    d[(pick >= 0.10) & (pick < 0.25)] = rng.integers(-8, 9, int(((pick >= 0.10) & (pick < 0.25)).sum())) / 4
    return d.astype(rng.choice([np.float32, np.float64]))


def _warp_cases(rng):
    for H, W in ((1, 1), (1, 9), (9, 1), (2, 3), (13, 17), (40, 33), (64, 70)):
        for grid in ((1, 1), (2, 2), (3, 5), (9, 9)):
            mask = rng.random((H, W)) < rng.choice([0.0, 0.05, 0.3, 1.0])
            yield mask, _odd_disparities(rng, (H, W)), grid


def test_the_c_warp_gives_the_twins_bits_on_random_and_odd_inputs():
    from recon.entropy.noise import warp_mask_to_views

    require_native("views")
    rng = np.random.default_rng(11)
    for mask, d, grid in _warp_cases(rng):
        H = mask.shape[0]
        U = grid[0]
        for rows in (None, range(U - 1, U), range(0, (U + 1) // 2)):
            for image_rows in (None, range(0, 1), range(H // 3, H - H // 4), range(H - 1, H), range(H // 2, H // 2)):
                # a band's reach is nanmax |d| grid steps: finite (0 * inf, the centre row's, is NaN)
                dd = d if image_rows is None else np.where(np.isinf(d), 1e30, d).astype(d.dtype)
                want = warp_mask_to_views(mask, dd, grid, rows=rows, image_rows=image_rows, kernel="numba")
                got = warp_mask_to_views(mask, dd, grid, rows=rows, image_rows=image_rows, kernel="native")
                assert got.dtype == want.dtype == bool and got.shape == want.shape
                np.testing.assert_array_equal(got.view(np.uint8), want.view(np.uint8))


@pytest.mark.parametrize("threads", [1, 2, 3, 4, 7])
def test_the_c_warp_gives_the_same_bits_on_every_thread_count(threads):
    from recon.entropy.noise import mask_landings, warp_landings

    require_native("views")
    rng = np.random.default_rng(12)
    mask = rng.random((37, 45)) < 0.1
    d = _odd_disparities(rng, mask.shape)
    landings = mask_landings(mask, d, (5, 5), image_rows=range(3, 30))
    views = [(u, v) for u in range(5) for v in range(5)][::-1]  # in any order
    want = warp_landings(landings, views, kernel="numba")
    np.testing.assert_array_equal(warp_landings(landings, views, kernel="native", threads=threads), want)
    assert want.any() and not want.all()


def test_the_warp_is_asked_with_a_disparity_of_any_reach():
    # a disparity so large that no landing stays in the image, and an all-NaN one: empty masks
    from recon.entropy.noise import warp_mask_to_views

    require_native("views")
    mask = np.ones((6, 7), bool)
    for d in (np.full(mask.shape, 50.0), np.full(mask.shape, np.nan)):
        want = warp_mask_to_views(mask, d, (3, 3), kernel="numba")
        got = warp_mask_to_views(mask, d, (3, 3), kernel="native")
        np.testing.assert_array_equal(got, want)
        assert not got[0].any() and (np.isnan(d).all() or got[1, 1].all())


def _odd_views(rng, shape):
    view = rng.random(shape, dtype=np.float32)
    pick = rng.random(shape)
    view[pick < 0.01] = np.nan
    view[(pick >= 0.01) & (pick < 0.02)] = np.inf
    view[(pick >= 0.02) & (pick < 0.03)] = -0.0
    view[(pick >= 0.03) & (pick < 0.04)] = 3e38
    view[(pick >= 0.04) & (pick < 0.05)] = 1e-42  # subnormal
    return view


def _blend_cases(rng):
    from recon.entropy.noise import _blend_filtered

    for H, W in ((1, 1), (1, 13), (11, 1), (16, 16), (33, 47)):
        for odd in (False, True):
            view = _odd_views(rng, (H, W)) if odd else rng.random((H, W), dtype=np.float32)
            mask = rng.random((H, W)) < 0.2
            for sigma in (0.6, 1.5):
                for rows in (slice(None), slice(0, 1), slice(H // 3, H - H // 3)):
                    yield _blend_filtered, view, mask, sigma, rows


def test_the_c_blend_gives_opencvs_bits_on_random_and_odd_inputs():
    require_native("views")
    rng = np.random.default_rng(13)
    for blend, view, mask, sigma, rows in _blend_cases(rng):
        want = blend(view, mask, sigma, rows=rows, kernel="numba")
        got = blend(view, mask, sigma, rows=rows, kernel="native")
        assert got.dtype == want.dtype == np.float32 and got.shape == want.shape
        np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
        into = np.full(want.shape, 7.0, np.float32)
        assert blend(view, mask, sigma, rows=rows, out=into, kernel="native") is into
        np.testing.assert_array_equal(into.view(np.uint32), want.view(np.uint32))
        if rows == slice(None):  # in place, the view its own result
            own = view.copy()
            blend(own, mask, sigma, out=own, kernel="native")
            np.testing.assert_array_equal(own.view(np.uint32), want.view(np.uint32))


def test_the_portable_c_loops_give_the_twins_bits(tmp_path, monkeypatch):
    # views.c built without AVX-512 (its plain loops, as on a CPU without it)
    from recon.entropy.noise import warp_mask_to_views

    require_native("views")
    use_native_build("views", monkeypatch, tmp_path, flags=("-mno-avx512f",))
    rng = np.random.default_rng(14)
    for i, (mask, d, grid) in enumerate(_warp_cases(rng)):
        if i % 3 == 0:
            want = warp_mask_to_views(mask, d, grid, kernel="numba")
            np.testing.assert_array_equal(warp_mask_to_views(mask, d, grid, kernel="native"), want)
    for i, (blend, view, mask, sigma, rows) in enumerate(_blend_cases(rng)):
        if i % 4 == 0:
            want = blend(view, mask, sigma, rows=rows, kernel="numba")
            np.testing.assert_array_equal(blend(view, mask, sigma, rows=rows, kernel="native").view(np.uint32),
                                          want.view(np.uint32))


@pytest.mark.parametrize("threads", [1, 2, 3, 4])
def test_filtered_views_give_the_twins_bits_on_every_thread_count(threads, monkeypatch):
    # both filters acting on a noisy scene: every band's rows, with the C kernels on 1-4 threads,
    # are those of the numpy/OpenCV twins over the whole views
    from recon.entropy import steps
    from tests.test_entropy_steps import noisy_wall

    require_native("views")
    _, s, expected = noisy_wall((48, 52), 15, np.s_[6:24, 6:30], np.s_[28:46, 24:50], (4, 5))
    H = s.raw.shape[2]
    steps.view_filters_step(s)
    monkeypatch.setattr(steps, "thread_count", lambda: threads)
    for a, b in [(0, H), (0, 5), (17, 30), (H - 1, H)]:
        got = steps.filtered_views(s, a, b)
        np.testing.assert_array_equal(got.view(np.uint32), expected[:, :, a:b].view(np.uint32))
