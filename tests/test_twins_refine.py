"""recon.entropy.refine: TV refinement and centroid correction, compiled and readable, agree and
keep their invariants."""

from __future__ import annotations

import numpy as np

from recon.entropy.refine import tv_energy, tv_refine
from kernel_inputs import seeded


def test_tv_refine_invariants():
    rng = seeded()
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


def _whole_rows(H, W):
    # tv_runs of every pixel: one run over each row
    from recon.entropy.refine import tv_runs

    return tv_runs(np.ones((H, W), bool), np.zeros((H, W)), np.zeros((H, W)))


def test_tv_refine_in_bands_gives_the_one_thread_values():
    # The bands of rows (one per thread, exchanged every few iterations) give bit for bit what one
    # sweep over the whole image gives: 3 bands, 4 iterations between exchanges, 23 iterations.
    from recon.entropy.refine import _tv_blocks, _tv_kernel, tv_bands

    rng = np.random.default_rng(11)
    f = 0.5 + 0.1 * rng.standard_normal((61, 37))
    mask = rng.random(f.shape) < 0.8
    weight = np.where(rng.random(f.shape) < 0.2, rng.uniform(0.0, 1.0, f.shape), 1.0)
    one = [f.copy(), f.copy(), np.zeros_like(f), np.zeros_like(f)]
    _tv_kernel(f, mask, weight, 0.2, 23, *one, 0, f.shape[0])
    runs = _whole_rows(*f.shape)
    banded = _tv_blocks(f, mask, weight, 0.2, 23, f.copy(), f.copy(), np.zeros_like(f), np.zeros_like(f),
                        tv_bands(*runs, 3), 4, *runs)
    np.testing.assert_array_equal(banded, one[0])
    assert np.abs(one[0] - f).max() > 0.01


def test_tv_runs_leave_out_only_values_that_cannot_change():
    # Over the runs of a sparse mask (specks, a stretch on each image edge, pixels outside the
    # mask that start away from their data), one sweep and the bands give the whole image's
    # refined map bit for bit, with runs joined across gaps or not.
    from recon.entropy.refine import _tv_blocks, _tv_kernel, _tv_wavefront, tv_bands, tv_runs

    rng = np.random.default_rng(15)
    H, W = 70, 45
    f = 0.5 + 0.1 * rng.standard_normal((H, W))
    mask = rng.random(f.shape) < 0.03
    mask[20:24, 30:40] = True
    mask[0, :6] = mask[-1, -7:] = mask[30:33, 0] = mask[40:44, -1] = True
    weight = np.where(rng.random(f.shape) < 0.3, rng.uniform(0.0, 1.0, f.shape), 1.0)
    start = f.copy()
    start[rng.random(f.shape) < 0.01] += 0.2
    one = [start.copy(), start.copy(), np.zeros_like(f), np.zeros_like(f)]
    _tv_kernel(f, mask, weight, 0.2, 37, *one, 0, H)
    for gap in (0, 3, 8):
        runs = tv_runs(mask, start, f, gap=gap)
        assert np.sum(runs[2] - runs[1]) < f.size // 3
        wave = [start.copy(), start.copy(), np.zeros_like(f), np.zeros_like(f)]
        _tv_wavefront(f, mask, weight, 0.2, 37, *wave, 0, H, 8, *runs)
        np.testing.assert_array_equal(wave[0], one[0])
        for n_bands in (2, 3):
            banded = _tv_blocks(f, mask, weight, 0.2, 37, start.copy(), start.copy(), np.zeros_like(f),
                                np.zeros_like(f), tv_bands(*runs, n_bands), 5, *runs)
            np.testing.assert_array_equal(banded, one[0])
    assert np.abs(one[0] - f)[mask].max() > 0.01


def test_tv_runs_and_bands():
    from recon.entropy.refine import tv_bands, tv_runs

    mask = np.zeros((5, 12), bool)
    mask[1, [2, 3, 9]] = True
    mask[4, 0] = True
    data = np.zeros(mask.shape)
    start = data.copy()
    start[3, 11] = 1.0  # outside the mask, away from its data: set to it by the first iteration
    runs, x0, x1 = tv_runs(mask, start, data, gap=0)
    # row 0: the pixels above the mask's; row 1: theirs and those to their left; row 3: above (4, 0)
    assert runs.tolist() == [0, 2, 4, 4, 6, 7]
    assert list(zip(x0.tolist(), x1.tolist())) == [(2, 4), (9, 10), (1, 4), (8, 10), (0, 1), (11, 12), (0, 1)]
    runs, x0, x1 = tv_runs(mask, start, data, gap=4)  # gaps of up to 4 columns joined
    assert list(zip(x0.tolist(), x1.tolist())) == [(2, 4), (9, 10), (1, 10), (0, 1), (11, 12), (0, 1)]
    edges = tv_bands(runs, x0, x1, 3)
    assert edges[0] == 0 and edges[-1] == 5 and np.all(np.diff(edges) >= 1)


def test_tv_wavefront_gives_the_two_sweep_values():
    # The wavefront kernel (several iterations per sweep down the rows) against the plain kernel
    # (two sweeps per iteration), bit for bit: whole images, a band of rows of a taller image (its
    # cut edges), iteration counts below, at and above the sweep's depth.
    from recon.entropy.refine import _tv_kernel, _tv_wavefront

    rng = np.random.default_rng(12)
    for n, W, top, H, iterations, depth in ((61, 37, 0, 61, 23, 8), (2, 5, 0, 2, 9, 4), (17, 9, 5, 40, 3, 8),
                                            (30, 12, 10, 40, 16, 16), (25, 2, 0, 25, 40, 7)):
        f = 0.5 + 0.1 * rng.standard_normal((n, W))
        mask = rng.random(f.shape) < 0.8
        weight = np.where(rng.random(f.shape) < 0.2, rng.uniform(0.0, 1.0, f.shape), 1.0)
        plain = [f + 0.01 * rng.standard_normal(f.shape), None, 0.01 * rng.standard_normal(f.shape), np.zeros_like(f)]
        plain[1] = plain[0].copy()
        wave = [a.copy() for a in plain]
        _tv_kernel(f, mask, weight, 0.2, iterations, *plain, top, H)
        _tv_wavefront(f, mask, weight, 0.2, iterations, *wave, top, H, depth, *_whole_rows(H, W))
        for a, b in zip(wave, plain):
            np.testing.assert_array_equal(a, b)
        assert np.abs(plain[0] - f).max() > 0.001


def test_tv_wavefront_vectorised_rows_give_the_kernel_values():
    # The row loops run several pixels at once (sqrt and division packed, no test of the ball):
    # bit for bit the plain kernel's values at widths around the vector length (a partial last
    # vector, a row shorter than one), with masks on the image's edges only or everywhere, and with
    # dual values on the ball, just inside it (closer than the 1e-9 margin a shortcut could take)
    # and just outside, where the norm is 1 or just above.
    from recon.entropy.refine import _tv_kernel, _tv_wavefront

    rng = np.random.default_rng(13)
    gamma = 0.2
    for W in (2, 3, 7, 8, 9, 15, 16, 17, 33):
        n = 11
        f = 0.5 + 0.1 * rng.standard_normal((n, W))
        edges = np.zeros((n, W), bool)
        edges[[0, -1]] = True
        edges[:, [0, -1]] = True
        for mask in (edges, ~edges, np.ones((n, W), bool)):
            weight = np.where(rng.random(f.shape) < 0.3, rng.uniform(0.0, 1.0, f.shape), 1.0)
            angle = rng.uniform(0, 2 * np.pi, f.shape)
            radius = gamma * rng.choice([1.0, 1 - 1e-12, 1 - 5e-10, 1 - 1e-9, 1 - 2e-9, 1 + 1e-12, 1 + 1e-9, 0.5], f.shape)
            plain = [f.copy(), f.copy(), radius * np.sin(angle), radius * np.cos(angle)]
            plain[0][3:6] = plain[1][3:6] = 0.25  # flat rows: the dual values stay where they start at first
            wave = [a.copy() for a in plain]
            _tv_kernel(f, mask, weight, gamma, 5, *plain, 0, n)
            _tv_wavefront(f, mask, weight, gamma, 5, *wave, 0, n, 3, *_whole_rows(n, W))
            for a, b in zip(wave, plain):
                np.testing.assert_array_equal(a, b, err_msg=f"W={W}")


def test_tv_refine_agrees_with_reference_at_odd_widths():
    from recon.entropy.refine import tv_refine_reference

    rng = np.random.default_rng(14)
    for W in (3, 9, 17, 130):
        f = (0.5 + 0.1 * rng.standard_normal((70, W))).astype(np.float32)
        mask = rng.random(f.shape) < 0.7
        mask[:, 0] = mask[:, -1] = True  # the smooth region on the image's left and right edges
        holes = np.zeros(f.shape, bool)
        holes[20:30, W // 3:W // 3 + 2] = True
        fast = tv_refine(f, mask, gamma=0.2, iterations=40, holes=holes)
        reference = tv_refine_reference(f, mask, gamma=0.2, iterations=40, holes=holes)
        np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-7, err_msg=f"W={W}")


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


def _fill_scene(H=120, W=160):
    # a slope, a wave and noise; hole masks of several shapes
    rng = np.random.default_rng(5)
    y, x = np.mgrid[0:H, 0:W]
    values = (0.3 * np.sin(y / 9.0) + 0.01 * x + 0.05 * rng.standard_normal((H, W))).astype(np.float32)
    holes = {
        "disc": (y - 60) ** 2 + (x - 80) ** 2 < 50 ** 2,
        "border": (y < 70) & (x > 50),
        "disconnected": (((y - 25) ** 2 + (x - 30) ** 2 < 20 ** 2) | ((y > 60) & (y < 110) & (x > 70) & (x < 150))
                         | ((x - y) % 23 == 0) | (y == 55)),
        "scattered": rng.random((H, W)) < 0.6,
    }
    return values, holes


def test_harmonic_fill_multigrid_agrees_with_the_lu():
    from recon.entropy.refine import MULTIGRID_COARSEST, harmonic_fill

    values, holes = _fill_scene()
    for name, hole in holes.items():
        assert hole.sum() > MULTIGRID_COARSEST, name  # the V-cycle has coarse levels
        lu = harmonic_fill(values, hole, solver="lu")
        multigrid = harmonic_fill(values, hole, solver="multigrid")
        assert np.array_equal(multigrid[~hole], values[~hole]), name
        np.testing.assert_allclose(multigrid, lu, atol=1e-6, err_msg=name)


def test_harmonic_fill_solvers_keep_a_plane_and_a_constant():
    from recon.entropy.refine import harmonic_fill

    _, holes = _fill_scene()
    y, x = np.mgrid[0:120, 0:160]
    plane = (0.2 + 0.01 * x - 0.02 * y).astype(np.float32)
    constant = np.full(plane.shape, 0.7, np.float32)
    noise = np.random.default_rng(2).uniform(-2, 2, plane.shape).astype(np.float32)
    inner = np.zeros(plane.shape, bool)  # a plane is kept where the hole has no pixel on the image's edge
    inner[1:-1, 1:-1] = True
    for solver in ("lu", "multigrid"):
        for hole in holes.values():
            np.testing.assert_allclose(harmonic_fill(np.where(hole, noise, constant), hole, solver=solver),
                                       constant, atol=1e-5)  # the system's weak tie to 0: 1e-6 here
            hole = hole & inner
            np.testing.assert_allclose(harmonic_fill(np.where(hole, noise, plane), hole, solver=solver), plane,
                                       atol=1e-5)


def test_harmonic_fill_takes_the_lu_up_to_its_size(monkeypatch):
    import pytest

    from recon.entropy import refine

    values, holes = _fill_scene()
    hole = holes["disc"]
    assert np.array_equal(refine.harmonic_fill(values, hole), refine.harmonic_fill(values, hole, solver="lu"))
    monkeypatch.setattr(refine, "LU_MAX_PIXELS", int(hole.sum()) - 1)
    assert np.array_equal(refine.harmonic_fill(values, hole),
                          refine.harmonic_fill(values, hole, solver="multigrid"))
    with pytest.raises(ValueError, match="solver"):
        refine.harmonic_fill(values, hole, solver="cg")
    ring = hole & ~np.roll(hole, 1, axis=0)  # the hole's top rim: its known neighbours lie above
    with pytest.raises(ValueError, match="non-finite"):
        refine.harmonic_fill(np.where(np.roll(ring, -1, axis=0), np.nan, values), hole)
