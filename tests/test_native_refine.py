"""The C kernels of the last steps (recon/native/refine.c) give the bits of their numba twins: the
centroid correction (recon.entropy.refine._centroid_kernel) and the TV refinement (_tv_wavefront,
and _tv_blocks in any number of bands), on random inputs that reach every branch, through
centroid_correction and tv_refine, and on the HCI backgammon scene's own inputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from recon.entropy import refine
from recon.entropy.refine import centroid_correction, tv_bands, tv_refine, tv_runs
from tests.conftest import require_hci_scene, require_native, use_native_build

ROOT = Path(__file__).resolve().parents[1]


def _same_bits(a: np.ndarray, b: np.ndarray, what: str = "", *, nan_bits: bool = True) -> None:
    # nan_bits=False: a NaN may differ from the other's NaN in its sign and payload. Where two NaNs
    # meet in an operation, IEEE 754 leaves which one the result carries to the machine's order of
    # the operands, which neither LLVM nor GCC keeps as written (both commute additions); every other
    # value is compared by its bytes, and a NaN must meet a NaN.
    assert a.dtype == b.dtype and a.shape == b.shape, what
    if not nan_bits:
        both = np.isnan(a) & np.isnan(b)
        a, b = np.where(both, np.nan, a), np.where(both, np.nan, b)
    assert np.array_equal(a.view(np.uint8), b.view(np.uint8)), what


def _rects(rng, H, W, sizes=(1, 3, 5, 9, 15)):
    # every window shape (squares, sides, quadrants, strips) at odd sizes, some wider than the image
    from recon.entropy.windows import N_SHAPES, window_rect

    table = np.array([[window_rect(s, z) for z in sizes] for s in range(N_SHAPES)], np.int64)
    return table[rng.integers(0, N_SHAPES, (H, W)), rng.integers(0, len(sizes), (H, W))]


def _centroid_both(d, rects, **kw):
    c = centroid_correction(d, rects, kernel="native", **kw)
    n = centroid_correction(d, rects, kernel="numba", **kw)
    _same_bits(c, n)
    return c


def test_the_c_centroid_correction_gives_numbas_bits_on_random_inputs():
    # one pixel, one row, one column, windows wider than the image; planes (corrected), planes with a
    # step (not), noise; every window shape; corrections clipped either side; NaN and inf values;
    # thresholds of 0, inf and NaN
    require_native("refine")
    rng = np.random.default_rng(3)
    moved = 0
    for trial, (H, W) in enumerate(((1, 1), (1, 19), (23, 1), (2, 3), (9, 12), (30, 34), (41, 17), (64, 70))):
        for variant in range(4):
            yy, xx = np.mgrid[0:H, 0:W]
            d = 0.3 + rng.uniform(-0.05, 0.05) * yy + rng.uniform(-0.05, 0.05) * xx + rng.normal(0, 0.002, (H, W))
            if variant == 1:
                d[:, W // 2:] += 0.8
            if variant == 2:
                d = rng.normal(0, 1, (H, W))
            if variant == 3 and H * W > 4:
                d.flat[rng.integers(0, H * W, 3)] = [np.nan, np.inf, -np.inf]
            kw = dict(max_residual=[0.05, 0.5, np.inf, 0.0, np.nan][(trial + variant) % 5],
                      max_shift=[0.2, 0.01, np.inf, 0.0][variant])
            out = _centroid_both(d.astype(np.float32), _rects(rng, H, W), **kw)
            moved += int(np.sum(out != d.astype(np.float32)))
    assert moved > 1000


def test_the_c_centroid_kernel_gives_numbas_float64_bits():
    # the kernels' own float64 maps (centroid_correction rounds them to float32, which hides the last
    # bits of the sums): sums in numba's order, planes fitted and clipped alike; a patch of -0.0
    # with corrections of +-0 clipped by a max_shift of 0 (numba's max keeps its first argument)
    from recon.native import call

    require_native("refine")
    rng = np.random.default_rng(4)
    for trial, (H, W) in enumerate(((1, 1), (1, 30), (30, 1), (3, 2), (40, 37), (64, 51))):
        yy, xx = np.mgrid[0:H, 0:W]
        d = 0.3 + 0.01 * yy - 0.02 * xx + rng.normal(0, [0.002, 0.3][trial % 2], (H, W))
        d[: H // 2, : W // 2] = -0.0
        rects = _rects(rng, H, W)
        for max_residual, max_shift in ((0.05, 0.2), (np.inf, 0.0), (0.5, 0.003), (np.nan, 1.0)):
            c = np.full((H, W), 7.0)
            n = np.full((H, W), 7.0)
            call("refine", "lfrig_centroid", d, H, W, rects, max_residual, max_shift, c, 1 + trial % 3)
            refine._centroid_kernel(d, rects, max_residual, max_shift, n)
            _same_bits(c, n, f"{H}x{W}, {max_residual}, {max_shift}")


def test_the_c_centroid_correction_is_the_same_on_any_number_of_threads(monkeypatch):
    require_native("refine")
    rng = np.random.default_rng(5)
    d = rng.normal(0, 0.1, (37, 29)).astype(np.float32)
    rects = _rects(rng, 37, 29)
    first = centroid_correction(d, rects, max_residual=0.5, max_shift=0.2, kernel="numba")
    for threads in (1, 2, 3, 64):
        monkeypatch.setattr(refine, "thread_count", lambda: threads)
        _same_bits(centroid_correction(d, rects, max_residual=0.5, max_shift=0.2, kernel="native"), first)


def test_centroid_correction_checks_what_the_c_kernel_reads():
    require_native("refine")
    d = np.zeros((4, 5), np.float32)
    rects = np.zeros((4, 5, 4), np.int64)
    with pytest.raises(ValueError, match="rects must be"):
        centroid_correction(d, rects[:, :4], max_residual=0.1, max_shift=0.1, kernel="native")
    for k, value in ((0, 1), (1, -1), (2, 2), (3, -3)):
        bad = rects.copy()
        bad[2, 3, k] = value
        with pytest.raises(ValueError, match="hold its pixel"):
            centroid_correction(d, bad, max_residual=0.1, max_shift=0.1, kernel="native")
    with pytest.raises(ValueError, match="kernel must be"):
        centroid_correction(d, rects, max_residual=0.1, max_shift=0.1, kernel="fortran")
    # windows of any reach that hold their pixel
    huge = np.array([-2 ** 62, 2 ** 62, -2 ** 62, 2 ** 62], np.int64)
    rng = np.random.default_rng(6)
    rects = _rects(rng, 4, 5)
    rects[1, 2] = huge
    _centroid_both(rng.normal(0, 1, (4, 5)).astype(np.float32), rects, max_residual=10.0, max_shift=1.0)


def _state(rng, shape, odd: int = 0):
    # (mu, bar, py, px): a start near the data, dual values inside, on and outside the ball; odd 1:
    # signed zeros, 2: also NaN and inf (the norm's max keeps NaN at 1, turns inf to 0)
    mu = 0.5 + 0.1 * rng.standard_normal(shape)
    py = 0.2 * rng.uniform(-1.2, 1.2, shape)
    px = 0.2 * rng.uniform(-1.2, 1.2, shape)
    if odd:
        py[rng.random(shape) < 0.05] = -0.0
        px[rng.random(shape) < 0.05] = -0.0
    if odd == 2:
        mu[rng.random(shape) < 0.02] = np.nan
        px[rng.random(shape) < 0.02] = np.inf
    return [mu, mu.copy(), py, px]


def _kernel_inputs(rng, H, W, *, odd: int = 0):
    # f, mask, weight; odd 1: weights of 0, data of -0.0; 2: also NaN and -inf data and weights of
    # -1 / (2 tau) (1 + w 0: a division by 0)
    f = 0.5 + 0.1 * rng.standard_normal((H, W))
    mask = rng.random((H, W)) < 0.7
    weight = np.where(rng.random((H, W)) < 0.3, rng.uniform(0.0, 1.0, (H, W)), 1.0)
    if odd:
        f[rng.random((H, W)) < 0.05] = -0.0
        weight[rng.random((H, W)) < 0.05] = 0.0
    if odd == 2:
        weight[rng.random((H, W)) < 0.02] = -np.sqrt(8.0) / 2.0  # 2 tau w: -1.0 exactly
        f[rng.random((H, W)) < 0.02] = np.nan
        f[rng.random((H, W)) < 0.02] = -np.inf
    return f, mask, weight


def _runs_of(rng, mask, f, gap, kind):
    H, W = mask.shape
    if kind == "whole":
        return tv_runs(np.ones((H, W), bool), np.zeros((H, W)), np.zeros((H, W)))
    if kind == "sparse":  # specks, stretches on the image's edges, empty rows
        sparse = rng.random((H, W)) < 0.04
        sparse[0, :3] = sparse[-1, -3:] = sparse[H // 2, 0] = sparse[H // 3, -1] = True
        return tv_runs(sparse, f + (rng.random((H, W)) < 0.01), f, gap=gap)
    return tv_runs(mask, f, f, gap=gap)


def _numba_wavefront(f, mask, weight, gamma, iterations, state, top, H, depth, runs):
    state = [a.copy() for a in state]
    refine._tv_wavefront(f, mask, weight, gamma, iterations, *state, top, H, depth, *runs)
    return state


def _c_wavefront(f, mask, weight, gamma, iterations, state, top, H, depth, runs):
    from recon.native import call

    state = [a.copy() for a in state]
    n, W = f.shape
    call("refine", "lfrig_tv_wavefront", f, mask, weight, n, W, float(gamma), iterations, *state, top, H, depth,
         *runs)
    return state


def _c_blocks(f, mask, weight, gamma, iterations, state, edges, halo, runs, threads):
    from recon.native import call

    state = [a.copy() for a in state]
    H, W = f.shape
    call("refine", "lfrig_tv_blocks", f, mask, weight, H, W, float(gamma), iterations, *state, edges, len(edges) - 1,
         halo, *runs, threads)
    return state


def test_the_c_tv_wavefront_gives_numbas_bits_on_random_inputs():
    # whole images and bands of a taller one (cut edges above and below), widths around the vector
    # length, every kind of runs, depths below, at and above the iterations; -0.0, weights of 0 and
    # -1 / (2 tau), gammas from tiny to inf (and 0: the norm's 0 / 0); then NaN and inf (their NaNs
    # compared as NaN, _same_bits)
    require_native("refine")
    rng = np.random.default_rng(7)
    cases = [(2, 2, 0, 2), (2, 5, 0, 2), (9, 2, 0, 9), (11, 3, 0, 11), (17, 9, 5, 40), (30, 12, 10, 40),
             (25, 33, 0, 25), (12, 16, 0, 12), (13, 17, 28, 41), (40, 8, 0, 40)]
    changed = 0
    for trial, (n, W, top, H) in enumerate(cases * 3):
        odd = trial // len(cases)
        f, mask, weight = _kernel_inputs(rng, n, W, odd=odd)
        full = np.zeros((H, W), bool)
        full[top:top + n] = mask
        runs = _runs_of(rng, full, np.pad(f, ((top, H - top - n), (0, 0))), [0, 3, 8][trial % 3],
                        ["whole", "sparse", "mask"][trial % 3])
        gamma = [0.2, 0.2, 1e-300, np.inf, 0.0, 0.05][trial % 6] if odd else 0.2
        iterations = [1, 5, 8, 23][trial % 4]
        depth = [1, 3, 8, 30][(trial // 2) % 4]
        state = _state(rng, (n, W), odd)
        c = _c_wavefront(f, mask, weight, gamma, iterations, state, top, H, depth, runs)
        nb = _numba_wavefront(f, mask, weight, gamma, iterations, state, top, H, depth, runs)
        for name, a, b in zip(("mu", "bar", "py", "px"), c, nb):
            _same_bits(a, b, f"{name} trial {trial}", nan_bits=odd < 2)
        changed += int(np.sum(c[0] != state[0]))
    assert changed > 1000


def test_the_c_tv_wavefront_keeps_the_values_on_the_ball():
    # dual values on the ball of radius gamma, just inside and just outside (the norm 1 or just
    # above), with flat rows where they stay where they start at first
    require_native("refine")
    rng = np.random.default_rng(8)
    gamma = 0.2
    for W in (2, 3, 7, 8, 9, 15, 16, 17, 33):
        n = 11
        f, mask, weight = _kernel_inputs(rng, n, W)
        angle = rng.uniform(0, 2 * np.pi, f.shape)
        radius = gamma * rng.choice([1.0, 1 - 1e-12, 1 - 5e-10, 1 + 1e-12, 1 + 1e-9, 0.5], f.shape)
        state = [f.copy(), f.copy(), radius * np.sin(angle), radius * np.cos(angle)]
        state[0][3:6] = state[1][3:6] = 0.25
        runs = _runs_of(rng, mask, f, 0, "whole")
        c = _c_wavefront(f, mask, weight, gamma, 5, state, 0, n, 3, runs)
        nb = _numba_wavefront(f, mask, weight, gamma, 5, state, 0, n, 3, runs)
        for a, b in zip(c, nb):
            _same_bits(a, b, f"W={W}")


def test_the_c_tv_wavefront_keeps_the_values_at_the_balls_edge():
    # a flat map (forward differences 0): the dual values' new norm is their own, a few units in the
    # last place either side of gamma, and at gammas whose square is subnormal, 0 or beyond float64,
    # four columns at a time in the ball or not, and mixed (the C kernel leaves the divisions out
    # where all four lie in the ball)
    require_native("refine")
    rng = np.random.default_rng(12)
    n, W = 6, 41
    f = np.full((n, W), 0.25)
    mask = np.ones((n, W), bool)
    weight = np.ones((n, W))
    runs = _runs_of(rng, mask, f, 0, "whole")
    for gamma in (0.2, 0.1, 3.0, 1e-160, 1e-300, 1e200, 5e-324):
        steps = rng.integers(-3, 4, (n, W))
        steps[:, :8] = -1  # a chunk in the ball
        steps[:, 8:12] = 1  # one outside
        py = gamma * rng.choice([1.0, -1.0], (n, W))
        py = np.where(steps < 0, np.nextafter(py, 0.0), np.where(steps > 0, np.nextafter(py, 2 * py), py))
        for _ in range(2):
            py = np.where(np.abs(steps) > 1, np.nextafter(py, np.where(steps < 0, 0.0, 2 * py)), py)
        px = np.where(rng.random((n, W)) < 0.2, gamma * 1e-9, 0.0)
        state = [f.copy(), f.copy(), py, px]
        c = _c_wavefront(f, mask, weight, gamma, 1, state, 0, n, 1, runs)
        nb = _numba_wavefront(f, mask, weight, gamma, 1, state, 0, n, 1, runs)
        for name, a, b in zip(("mu", "bar", "py", "px"), c, nb):
            _same_bits(a, b, f"{name}, gamma {gamma}")


def test_the_c_tv_bands_give_the_one_thread_values_for_any_band_count():
    # 1 to 6 bands on 1 to 4 threads (several bands a thread), halos of 1 to more than the image,
    # iteration counts of an odd and an even number of rounds: every map bit for bit numba's one
    # sweep (_tv_wavefront), and mu numba's bands (_tv_blocks)
    require_native("refine")
    rng = np.random.default_rng(9)
    for trial, (H, W) in enumerate(((61, 37), (70, 45), (8, 5), (130, 18))):
        f, mask, weight = _kernel_inputs(rng, H, W, odd=trial == 1)
        runs = _runs_of(rng, mask, f, 8, ["mask", "sparse", "whole", "mask"][trial])
        state = _state(rng, (H, W), trial == 1)
        for iterations in (0, 1, 23, 32):
            one = _numba_wavefront(f, mask, weight, 0.2, iterations, state, 0, H, refine.TV_WAVE_ITERATIONS, runs)
            for n_bands in (1, 2, 3, 6):
                if n_bands > H:
                    continue
                edges = tv_bands(*runs, n_bands)
                for halo in (1, 4, 16, 200):
                    for threads in sorted({1, 2, 4, n_bands}):
                        c = _c_blocks(f, mask, weight, 0.2, iterations, state, edges, halo, runs, threads)
                        for name, a, b in zip(("mu", "bar", "py", "px"), c, one):
                            _same_bits(a, b, f"{name}: {H}x{W}, {iterations} its, {n_bands} bands, halo {halo}")
                if iterations == 23:
                    nb = refine._tv_blocks(f, mask, weight, 0.2, iterations, *[a.copy() for a in state], edges, 5,
                                           *runs)
                    _same_bits(nb, one[0], f"numba's bands, {n_bands}")
        assert np.abs(one[0] - state[0]).max() > 0.001


def _tv_both(f, mask, nan_bits=True, **kw):
    c = tv_refine(f, mask, kernel="native", **kw)
    n = tv_refine(f, mask, kernel="numba", **kw)
    _same_bits(c, n, nan_bits=nan_bits)
    return c


def test_tv_refine_gives_the_same_map_with_either_kernel(monkeypatch):
    # the smallest images, holes with and without weights, NaN and inf disparities, and images in
    # bands (the C kernels' threshold lowered) on 1 to 5 threads
    require_native("refine")
    rng = np.random.default_rng(10)
    for trial, (H, W) in enumerate(((2, 2), (2, 7), (9, 2), (3, 3), (23, 31), (150, 40), (200, 17), (131, 9))):
        f = (0.5 + 0.1 * rng.standard_normal((H, W))).astype(np.float32)
        mask = rng.random((H, W)) < 0.6
        holes = rng.random((H, W)) < 0.1
        weight = np.where(rng.random((H, W)) < 0.5, rng.uniform(0.0, 1.0, (H, W)), 0.0)
        if trial % 2:
            f[rng.random((H, W)) < 0.03] = np.nan
            f[rng.random((H, W)) < 0.01] = np.inf
        finite = trial % 2 == 0
        for kw in ({}, {"holes": holes}, {"holes": holes, "hole_weight": weight}):
            out = _tv_both(f, mask, gamma=0.2, iterations=37, nan_bits=finite, **kw)
            if H >= 128:
                for threads in (1, 2, 3, 5):
                    monkeypatch.setattr(refine, "TV_NATIVE_PARALLEL_PIXELS", 0)
                    monkeypatch.setattr(refine, "thread_count", lambda: threads)
                    _same_bits(tv_refine(f, mask, gamma=0.2, iterations=37, kernel="native", **kw), out)
                    monkeypatch.undo()
        _tv_both(f, mask, gamma=0.0, iterations=10, nan_bits=finite)  # no refinement
        _tv_both(f, mask, gamma=0.2, iterations=0, nan_bits=finite)


def test_tv_refine_checks_what_the_c_kernels_read():
    require_native("refine")
    f = np.zeros((6, 7), np.float32)
    for mask in (np.ones((1, 7), bool), np.ones((6, 1), bool)):  # refused before the C kernel reads it
        with pytest.raises(ValueError):
            tv_refine(f, mask, gamma=0.2, iterations=3, kernel="native")
    with pytest.raises(ValueError, match="kernel must be"):
        tv_refine(f, np.ones((6, 7), bool), gamma=0.2, iterations=3, kernel="fortran")


def test_the_c_path_calls_no_numba(monkeypatch):
    require_native("refine")
    rng = np.random.default_rng(11)
    f = (0.5 + 0.1 * rng.standard_normal((140, 30))).astype(np.float32)
    mask = rng.random(f.shape) < 0.6
    rects = _rects(rng, *f.shape)
    expected = (tv_refine(f, mask, gamma=0.2, iterations=20, kernel="numba"),
                centroid_correction(f, rects, max_residual=0.5, max_shift=0.2, kernel="numba"))

    def numba_called(*args, **kwargs):
        raise AssertionError("the C path called numba")

    for name in ("_tv_wavefront", "_tv_blocks", "_centroid_kernel"):
        monkeypatch.setattr(refine, name, numba_called)
    monkeypatch.setattr(refine, "numba", None)  # numba.get_num_threads
    _same_bits(tv_refine(f, mask, gamma=0.2, iterations=20), expected[0])
    monkeypatch.setattr(refine, "TV_NATIVE_PARALLEL_PIXELS", 0)  # the bands
    monkeypatch.setattr(refine, "thread_count", lambda: 2)
    _same_bits(tv_refine(f, mask, gamma=0.2, iterations=20), expected[0])
    _same_bits(centroid_correction(f, rects, max_residual=0.5, max_shift=0.2), expected[1])


def test_the_c_refinement_imports_no_numba():
    # in a fresh process: the centroid correction and the TV refinement (with holes, in bands) on the
    # C path leave numba unimported
    require_native("refine")
    script = """
import json, sys, numpy as np
from recon.entropy import refine
rng = np.random.default_rng(0)
f = rng.random((140, 20)).astype(np.float32)
refine.TV_NATIVE_PARALLEL_PIXELS = 0
refine.tv_refine(f, rng.random(f.shape) < 0.5, gamma=0.2, iterations=5, holes=rng.random(f.shape) < 0.1)
refine.centroid_correction(f, np.tile(np.array([-1, 1, -2, 0], np.int64), f.shape + (1,)), max_residual=0.1,
                           max_shift=0.1)
print(json.dumps("numba" in sys.modules))
"""
    run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout.strip().splitlines()[-1]) is False


def test_the_portable_c_loops_give_numbas_bits(tmp_path, monkeypatch):
    # refine.c built without AVX (its plain loops, as on a CPU without it, the dual step's divisions
    # everywhere) gives the same bits
    import recon.native as native

    require_native("refine")
    use_native_build("refine", monkeypatch, tmp_path, flags=("-mno-avx",))
    rng = np.random.default_rng(13)
    for n, W, top, H in ((2, 2, 0, 2), (17, 9, 5, 40), (25, 33, 0, 25), (70, 45, 0, 70)):
        f, mask, weight = _kernel_inputs(rng, n, W, odd=1)
        full = np.zeros((H, W), bool)
        full[top:top + n] = mask
        runs = _runs_of(rng, full, np.pad(f, ((top, H - top - n), (0, 0))), 3, "mask")
        state = _state(rng, (n, W), 1)
        one = _numba_wavefront(f, mask, weight, 0.2, 19, state, top, H, 8, runs)
        for a, b in zip(_c_wavefront(f, mask, weight, 0.2, 19, state, top, H, 8, runs), one):
            _same_bits(a, b, f"{n}x{W}")
        if top == 0 and n >= 6:
            for a, b in zip(_c_blocks(f, mask, weight, 0.2, 19, state, tv_bands(*runs, 3), 4, runs, 2), one):
                _same_bits(a, b, f"{n}x{W} in bands")
    d = rng.normal(0, 0.1, (30, 34))
    rects = _rects(rng, 30, 34)
    c, nb = np.empty((30, 34)), np.empty((30, 34))
    native.call("refine", "lfrig_centroid", d, 30, 34, rects, 0.5, 0.2, c, 2)
    refine._centroid_kernel(d, rects, 0.5, 0.2, nb)
    _same_bits(c, nb)


@pytest.mark.hci
def test_the_c_refinement_gives_numbas_bits_on_backgammon(monkeypatch):
    # a default backgammon estimate, whose centroid correction and TV refinement run the C kernels;
    # their inputs then go to numba's, and the TV's to the C bands (2 to 8)
    from recon.entropy import steps
    from recon.entropy.estimate import estimate_disparity
    from recon.lf.io import read_lightfield

    require_native("refine")
    lf = read_lightfield(require_hci_scene(), grey=True)
    seen = {}

    def recording(name, function):
        def run(*args, **kwargs):
            out = function(*args, **kwargs)
            seen[name] = (args, kwargs, out)
            return out
        return run

    monkeypatch.setattr(steps, "centroid_correction", recording("centroid", centroid_correction))
    monkeypatch.setattr(steps, "tv_refine", recording("tv", tv_refine))
    estimate_disparity(lf)
    assert set(seen) == {"centroid", "tv"}
    args, kwargs, out = seen["centroid"]
    assert args[0].shape == (512, 512)
    numba_out = centroid_correction(*args, **{**kwargs, "kernel": "numba"})
    _same_bits(out, numba_out, "centroid")
    assert np.sum(numba_out != args[0]) > 10_000
    args, kwargs, out = seen["tv"]
    numba_out = tv_refine(*args, **{**kwargs, "kernel": "numba"})
    _same_bits(out, numba_out, "tv")
    assert np.abs(numba_out - args[0]).max() > 0.01
    monkeypatch.setattr(refine, "TV_NATIVE_PARALLEL_PIXELS", 0)
    for threads in (2, 3, 8):
        monkeypatch.setattr(refine, "thread_count", lambda: threads)
        _same_bits(tv_refine(*args, **{**kwargs, "kernel": "native"}), numba_out, f"tv in {threads} bands")
