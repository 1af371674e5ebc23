"""The cost-volume kernel and the baseline estimator on synthetic light fields with known disparity."""

import numpy as np
import pytest

from recon.baseline import disparity_candidates, estimate_baseline, parabolic_refine
from recon.costvolume import pixel_cost, pixel_cost_reference, view_offsets
from recon.evaluate import score
from recon.lf.lightfield import LightField
from recon.synthetic import Layer, noise_texture, occluding_square_scene, render


@pytest.mark.parametrize("disparity", [0.0, 0.37, -1.8, 3.2])
def test_fast_kernel_agrees_with_reference(disparity):
    gray = np.random.default_rng(1).random((5, 5, 17, 23)).astype(np.float32)
    offsets = view_offsets((5, 5))
    indices = (offsets + 2).astype(np.int64)
    fast = pixel_cost(gray, disparity, offsets=offsets, indices=indices)
    slow = pixel_cost_reference(gray, disparity, offsets=offsets, indices=indices)
    np.testing.assert_allclose(fast, slow, atol=2e-6)


def test_constant_light_field_costs_nothing():
    gray = np.full((3, 3, 8, 8), 0.4, np.float32)
    offsets = view_offsets((3, 3))
    cost = pixel_cost(gray, 1.3, offsets=offsets, indices=(offsets + 1).astype(np.int64))
    np.testing.assert_allclose(cost, 0, atol=1e-7)


def test_cost_is_zero_at_the_true_disparity_of_a_plane():
    # An integer disparity shifts by whole pixels, so no interpolation blurs the comparison.
    lf, truth = render([Layer(noise_texture((40, 40), seed=3), 1.0)], grid=(5, 5))
    offsets = view_offsets((5, 5))
    indices = (offsets + 2).astype(np.int64)
    inner = (slice(8, -8), slice(8, -8))
    at_truth = pixel_cost(lf.views, 1.0, offsets=offsets, indices=indices)[inner].mean()
    off_truth = pixel_cost(lf.views, 1.2, offsets=offsets, indices=indices)[inner].mean()
    assert at_truth < 1e-6 < off_truth


def test_candidates_include_both_ends():
    c = disparity_candidates((-1.7, 0.7), 0.02)
    assert c[0] == -1.7 and c[-1] == pytest.approx(0.7) and len(c) == 121


def test_parabolic_refinement_finds_the_vertex():
    candidates = np.arange(-1.0, 1.01, 0.1)
    true = 0.234
    volume = ((candidates - true) ** 2)[:, None, None] * np.ones((1, 2, 2))
    disparity, _ = parabolic_refine(volume.astype(np.float32), candidates)
    np.testing.assert_allclose(disparity, true, atol=1e-5)


def test_sweep_gives_what_the_cost_volume_gives():
    # The sweep keeps only each pixel's least cost and its neighbours; the readable twin holds every
    # candidate's cost and refines with parabolic_refine. Ties (a constant patch), range ends and
    # sub-pixel vertices all occur on this scene; the maps agree bit for bit.
    from recon.costvolume import box_mean

    lf, _ = occluding_square_scene(40, back=-0.5, front=1.0)
    lf.views[..., :6, :6] = 0.5
    candidates = disparity_candidates((-0.6, 1.2), 0.1)
    result = estimate_baseline(lf, window=5, step=0.1, disparity_range=(-0.6, 1.2))
    gray = lf.gray()
    offsets = view_offsets(lf.grid_shape)
    indices = (offsets + np.array(lf.centre_index)).astype(np.int64)
    volume = np.stack([box_mean(pixel_cost(gray, d, offsets=offsets, indices=indices), 5) for d in candidates])
    disparity, cost = parabolic_refine(volume, candidates)
    assert len(np.unique(np.argmin(volume, axis=0))) > 3
    np.testing.assert_array_equal(result.disparity, disparity)
    np.testing.assert_array_equal(result.cost, cost)


@pytest.fixture(params=["native", "numba"])
def sweep_kernel(request):
    """Each of the sweep's two kernels (recon.sweep); the C one fails, not skips, under CI."""
    from tests.conftest import require_native

    if request.param == "native":
        require_native("sweep")
    return request.param


@pytest.mark.parametrize("bands", [1, 3, 7, 23])  # 23: one row each, fewer than the window's radius
def test_sweep_in_bands_of_rows_gives_the_same_numbers(bands, sweep_kernel):
    from recon.costvolume import box_mean
    from recon.sweep import sweep_least_cost

    gray = np.random.default_rng(5).random((5, 5, 23, 19)).astype(np.float32)
    offsets = view_offsets((5, 5))
    indices = (offsets + 2).astype(np.int64)
    candidates = np.linspace(-1.3, 1.1, 9)
    volume = np.stack([box_mean(pixel_cost(gray, d, offsets=offsets, indices=indices), 5) for d in candidates])
    state = sweep_least_cost(gray, candidates[:4], offsets=offsets, indices=indices, window=5, bands=bands,
                             kernel=sweep_kernel)
    state = sweep_least_cost(gray, candidates[4:], offsets=offsets, indices=indices, window=5, bands=bands,
                             state=state, first=4, kernel=sweep_kernel)
    best = np.argmin(volume, axis=0)
    rows, cols = np.indices(best.shape)
    np.testing.assert_array_equal(state["best_index"], best)
    np.testing.assert_array_equal(state["best"], volume[best, rows, cols])
    inner = (best > 0) & (best < len(candidates) - 1)
    np.testing.assert_array_equal(state["c_minus"][inner], volume[best - 1, rows, cols][inner])
    np.testing.assert_array_equal(state["c_plus"][inner], volume[np.minimum(best + 1, 8), rows, cols][inner])


@pytest.mark.parametrize("grid", [(3, 4), (1, 2), (5, 5)])  # 11 views, 1 view: the last of an odd number alone
def test_sweep_adds_the_views_in_pairs_as_one_at_a_time(grid, sweep_kernel):
    # The sweep adds two views in one pass (recon.costvolume.add_two_shifted_row_diffs); the cost
    # volume's pixel_cost adds one at a time. Shifts of several pixels beyond both borders occur.
    from recon.costvolume import box_mean
    from recon.sweep import sweep_least_cost

    gray = np.random.default_rng(7).random(grid + (13, 11)).astype(np.float32)
    offsets = view_offsets(grid)
    indices = (offsets + np.array([grid[0] // 2, grid[1] // 2])).astype(np.int64)
    candidates = np.linspace(-6.3, 5.9, 11)
    volume = np.stack([box_mean(pixel_cost(gray, d, offsets=offsets, indices=indices), 3) for d in candidates])
    state = sweep_least_cost(gray, candidates, offsets=offsets, indices=indices, window=3, bands=2,
                             kernel=sweep_kernel)
    best = np.argmin(volume, axis=0)
    rows, cols = np.indices(best.shape)
    np.testing.assert_array_equal(state["best_index"], best)
    np.testing.assert_array_equal(state["best"], volume[best, rows, cols])
    np.testing.assert_array_equal(state["previous"], volume[-1])


def test_sweep_takes_the_first_nan_as_argmin_does(sweep_kernel):
    from recon.costvolume import box_mean
    from recon.sweep import sweep_least_cost

    gray = np.random.default_rng(6).random((3, 3, 12, 14)).astype(np.float32)
    gray[0, 0, 5:8, 6:9] = np.nan  # a corner view's hole: NaN costs at some candidates only
    offsets = view_offsets((3, 3))
    indices = (offsets + 1).astype(np.int64)
    candidates = np.linspace(-1.0, 1.0, 7)
    volume = np.stack([box_mean(pixel_cost(gray, d, offsets=offsets, indices=indices), 3) for d in candidates])
    state = sweep_least_cost(gray, candidates, offsets=offsets, indices=indices, window=3, bands=2,
                             kernel=sweep_kernel)
    first_nan = np.isnan(volume).any(axis=0) & ~np.isnan(volume[0])
    assert first_nan.any()
    np.testing.assert_array_equal(state["best_index"], np.argmin(volume, axis=0))


def test_baseline_recovers_a_fronto_parallel_plane_to_sub_pixel_accuracy():
    lf, truth = render([Layer(noise_texture((48, 48), seed=5), 0.43)], grid=(9, 9))
    result = estimate_baseline(lf, window=7, step=0.05, disparity_range=(-1.0, 1.0))
    s = score(result.disparity, truth, border=8)
    assert s["badpix_0.03"] < 1.0


def test_baseline_sign_follows_the_conventions():
    lf, truth = occluding_square_scene(48, back=-0.5, front=1.0)
    d = estimate_baseline(lf, window=5, step=0.05).disparity
    assert np.median(d[20:28, 20:28]) == pytest.approx(1.0, abs=0.05)
    assert np.median(d[3:8, 3:8]) == pytest.approx(-0.5, abs=0.05)


def test_baseline_rejects_an_even_window():
    lf = LightField(views=np.zeros((3, 3, 8, 8), np.float32))
    with pytest.raises(ValueError, match="odd"):
        estimate_baseline(lf, window=4)


@pytest.mark.parametrize("window", [1, 3, 7])
def test_box_mean_agrees_with_reference_and_does_not_depend_on_the_crop(window):
    from recon.costvolume import box_mean, box_mean_reference

    image = np.random.default_rng(2).random((23, 31)).astype(np.float32)
    full = box_mean(image, window)
    np.testing.assert_allclose(full, box_mean_reference(image, window), atol=1e-6)
    r = window // 2
    crop = box_mean(image[4:20, 5:27], window)
    # Away from the crop's own border (within r of it the mirror differs), bit for bit the same.
    np.testing.assert_array_equal(crop[r:crop.shape[0] - r, r:crop.shape[1] - r],
                                  full[4 + r:20 - r, 5 + r:27 - r])


def test_the_warm_up_loads_the_kernel_the_estimate_calls(monkeypatch):
    # recon.methods.warm_in_background("baseline") (run while the views are read) loads numba's
    # sweep kernel, where the C one cannot be had, with the argument types the estimate passes: the
    # estimate adds no second signature, which would mean a compilation at run time.
    import recon.sweep
    from recon.costvolume import _sweep_kernel
    from recon.methods import warm_in_background

    monkeypatch.setattr(recon.sweep, "native_library", lambda: None)

    warm_in_background("baseline").join()
    loaded = list(_sweep_kernel.signatures)
    assert len(loaded) == 1
    lf, _ = occluding_square_scene(24, back=-0.5, front=1.0)
    estimate_baseline(lf, window=5, step=0.1, disparity_range=(-0.6, 1.2))
    assert list(_sweep_kernel.signatures) == loaded


def test_the_warm_up_does_not_import_scipy_linalg():
    # numba's start-up checks for BLAS by importing scipy.linalg; the baseline's warm-up of numba's
    # kernel (LFRIG_NATIVE=0: no C kernel) skips that check (recon.methods._warm_baseline) and puts
    # numba's own check back afterwards. With the C kernel, neither numba nor scipy loads.
    import os
    import subprocess
    import sys

    from tests.conftest import require_native

    code = ("import sys, numba.np.linalg as L; check = L.ensure_blas\n"
            "from recon.methods import warm_in_background\n"
            "warm_in_background('baseline').join()\n"
            "from recon.costvolume import _sweep_kernel\n"
            "print(len(_sweep_kernel.signatures), 'scipy.linalg' in sys.modules, L.ensure_blas is check)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "LFRIG_NATIVE": "0"})
    assert out.stdout.split() == ["1", "False", "True"]
    require_native("sweep")
    code = ("import sys\n"
            "from recon.methods import warm_in_background\n"
            "warm_in_background('baseline').join()\n"
            "print('numba' in sys.modules, 'scipy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_the_baseline_command_loads_none_of_the_entropy_estimator(tmp_path):
    # `lfrig reconstruct --method baseline` in a fresh process: the entropy method's options build
    # its flags, but neither its estimator (numba kernels, scipy.ndimage, scipy.sparse) nor the
    # parsers of the other commands' modules load.
    import subprocess
    import sys
    from pathlib import Path

    fixture = Path(__file__).resolve().parents[1] / "fixtures" / "tiny_capture"
    code = ("import sys\nfrom rig.main import main\n"
            f"status = main(['reconstruct', {str(fixture)!r}, '-o', {str(tmp_path / 'out')!r}, '--method', "
            "'baseline', '--window', '3', '--quiet'])\n"
            "loaded = [m for m in sys.modules if m.startswith(('recon.entropy.', 'scipy.ndimage', 'scipy.sparse', "
            "'rig.demo', 'rig.cli', 'calib'))]\n"
            "print(status, sorted(loaded))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines()[-1] == "0 ['recon.entropy.options']"
