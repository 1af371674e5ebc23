"""The joint line search's C kernels (recon/native/joint.c) give numba's bits: the group kernel of
Eq. 7 (recon.entropy.matching._joint_group_kernel) and the offer runs it reads
(recon.entropy.layout.offer_runs), on random inputs that reach every branch, through
joint_line_search and on a whole backgammon estimate."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import require_hci_scene, require_native, use_native_build
from tests.kernel_inputs import joint_inputs

ROOT = Path(__file__).resolve().parents[1]


def _same_bits(a: np.ndarray, b: np.ndarray, what: str = "") -> None:
    assert a.dtype == b.dtype and a.shape == b.shape, what
    assert np.array_equal(a.view(np.uint8), b.view(np.uint8)), what


def _group(kernel, gray, disparities, rects, shapes, counts, penalty, occluded, *, rows, group, threads=2,
           scale=255.0, view_mask=None):
    """``(out, least, best_k)`` of the group kernel over ``disparities`` in passes of ``group``, ``rows``
    rows at a time; penalty ``(H, K, W)``. The C kernel reads the C offer runs, numba's numba's."""
    from recon.entropy.cost import set_sums_plan, view_lists
    from recon.entropy.layout import offer_runs
    from recon.entropy.matching import _joint_group_kernel, _offer_runs_native
    from recon.native import call

    U, V, H, W = gray.shape
    views = view_lists((U, V), view_mask)
    plan = set_sums_plan(np.arange(11))
    disparities = np.asarray(disparities, np.float32)
    out = np.full((len(disparities), H, W), np.nan, np.float32)
    least = np.full((H, W), np.inf, np.float32)
    best_k = np.full((H, W), -1, np.int64)
    if kernel == "native":
        run_start, runs = _offer_runs_native(penalty, occluded, shapes, threads)
    else:
        run_start, runs = offer_runs(penalty, occluded, shapes)
    for i in range(0, len(disparities), group):
        d = np.ascontiguousarray(disparities[i:i + group])
        if kernel == "native":
            call("joint", "lfrig_joint_group", gray, U, V, H, W, *views[:4], views[4], len(views[0]), d, len(d),
                 *plan, len(plan[0]), occluded, rects, shapes, len(rects), counts, penalty, run_start, runs,
                 float(scale), rows, out[i:i + group], least, best_k, threads)
        else:
            _joint_group_kernel(gray, *views, d, *plan, occluded, rects, shapes, counts, penalty, run_start, runs,
                                float(scale), rows, out[i:i + group], least, best_k)
    return out, least, best_k


def _both(*args, threads=2, **kwargs):
    c = _group("native", *args, threads=threads, **kwargs)
    n = _group("numba", *args, **kwargs)
    for name, a, b in zip(("out", "least", "best_k"), c, n):
        _same_bits(a, b, name)
    return c


def _case(rng, H, W, *, grid=(9, 9), sizes=(3, 5, 15), quantised=True):
    """``(gray, rects, shapes, counts, penalty (H, K, W), occluded)`` for any size (joint_inputs' where it
    applies: ties, runs, rows offering one window)."""
    from recon.entropy.cost import set_view_counts
    from recon.entropy.windows import N_SHAPES, window_rect

    gray = rng.random(grid + (H, W)).astype(np.float32)
    if quantised:
        gray = np.round(gray * 8).astype(np.float32) / 8  # ties between candidates and windows
    if H >= 2 and W >= 3:
        _, rects, shapes, penalty, occluded, _ = joint_inputs(rng, H, W, sizes)
    else:
        windows = [(s, z) for s in range(N_SHAPES) for z in sizes]
        rects = np.array([window_rect(s, z) for s, z in windows], np.int64)
        shapes = np.array([s for s, _ in windows], np.int64)
        penalty = np.round(rng.normal(0, 1, (H, W, len(windows))) * 4).astype(np.float32) / 4
        penalty[rng.random(penalty.shape) < 0.5] = np.inf
        occluded = rng.random((H, W)) < 0.4
    counts = set_view_counts(grid).astype(np.float64)
    return gray, rects, shapes, counts, np.ascontiguousarray(penalty.transpose(0, 2, 1)), occluded


def test_the_c_joint_kernel_gives_numbas_bits_on_random_inputs():
    # sizes (windows wider and taller than the image, one row, one column, one pixel, rows of several
    # runs), grids (an even one), view masks, stretches of 1..50 rows, groups of 1..5 candidates (the
    # last short), repeated candidates (ties: the first wins), whole-pixel shifts and shifts beyond the
    # image, set values that round half up, scales, 1..5 threads
    from recon.entropy.layout import RUN_GAP

    require_native("joint")
    rng = np.random.default_rng(23)
    shapes_ = [(21, 33), (6, 9), (7, RUN_GAP + 20), (1, 12), (12, 1), (1, 1), (2, 3), (16, 5), (3, 40)]
    for trial in range(27):
        H, W = shapes_[trial % len(shapes_)]
        grid = [(9, 9), (9, 9), (5, 5), (3, 4), (3, 3)][trial % 5]
        inputs = _case(rng, H, W, grid=grid, sizes=[(3, 5, 15), (3,), (5, 7, 9)][trial % 3],
                       quantised=trial % 4 != 3)
        view_mask = rng.random(grid) < 0.7 if trial % 6 == 5 else None
        if view_mask is not None:
            from recon.entropy.cost import set_view_counts
            view_mask[grid[0] // 2, grid[1] // 2] = True
            inputs = inputs[:3] + (set_view_counts(grid, view_mask).astype(np.float64),) + inputs[4:]
        if trial % 7 == 2:
            candidates = np.array([-2.0, -1.0, 0.0, 1.0, 0.0])  # whole pixels, a repeat
        elif trial % 7 == 4:
            candidates = np.array([-25.0, 0.35, 19.5])  # shifts beyond the image
        else:
            candidates = np.sort(rng.uniform(-1.5, 1.5, int(rng.integers(1, 7))))
        if trial % 9 == 8:  # set values at half units of 1 / FIXED_POINT (whole shifts of odd multiples of
            # 2^-29) that round up, in rows of the vector rounding and, by a NaN in a corner, of the scalar one
            gray = rng.integers(0, 64, inputs[0].shape).astype(np.float32) * np.float32(2.0 ** -29)
            gray[0, 0, 0, 0] = np.nan
            inputs = (gray,) + inputs[1:]
            candidates = np.array([-1.0, 0.0, 2.0])
        rows = [1, 3, 8, 50][trial % 4]
        group = int(rng.integers(1, 6))
        # 0 and negative: signed zeros; 3e38: objectives beyond float32's range
        scale = [255.0, 1.0, -2.0, 0.0, 3e38][trial % 5] if trial % 3 == 1 else 255.0
        _both(*inputs[:1], candidates, *inputs[1:], rows=rows, group=group, threads=1 + trial % 5, scale=scale,
              view_mask=view_mask)


def test_the_c_joint_kernel_gives_numbas_bits_with_several_candidates_a_thread():
    # each thread's candidates' block rows made view by view for all of them (3, 2 and 2 of 7 on three
    # threads; 9 on one), stretches whose rows are made in several steps (rows 1, 3) or none (the last
    # ones), and rings of table rows of 2 MiB and more (2 MiB pages where the system gives them)
    require_native("joint")
    rng = np.random.default_rng(43)
    for trial, (H, W, G, threads, rows) in enumerate(((26, 230, 7, 3, 3), (26, 230, 9, 1, 8), (12, 19, 7, 2, 1),
                                                      (9, 40, 8, 4, 3), (5, 6, 6, 5, 8))):
        inputs = _case(rng, H, W, quantised=trial % 2 == 0)
        candidates = np.sort(rng.uniform(-1.5, 1.5, G))
        _both(*inputs[:1], candidates, *inputs[1:], rows=rows, group=G, threads=threads)


def test_the_c_joint_kernel_gives_numbas_bits_with_blocks_without_views():
    # view masks that leave some of the nine blocks no view (their block rows stay zero: the others' first
    # views put their differences onto zeros), the centre view alone, one block of several views; runs of
    # every length about a vector's eight pixels (whole vectors and the last few), 1..4 threads
    from recon.entropy.cost import set_view_counts

    require_native("joint")
    rng = np.random.default_rng(47)
    masks = [[(4, 4), (0, 0), (8, 8), (4, 0)], [(4, 4)], [(4, 4), (3, 3), (3, 4), (4, 3), (5, 5)],
             [(4, 4), (0, 1), (1, 0), (0, 0)]]
    for trial, views in enumerate(masks * 2):
        H, W = [(13, 9), (10, 17), (6, 31), (9, 8)][trial % 4]
        mask = np.zeros((9, 9), bool)
        mask[tuple(np.array(views).T)] = True
        gray, rects, shapes, _, penalty, occluded = _case(rng, H, W, quantised=trial % 2 == 0)
        counts = set_view_counts((9, 9), mask).astype(np.float64)
        _both(gray, np.array([-0.9, 0.2, 0.55]), rects, shapes, counts, penalty, occluded, rows=[1, 3, 8][trial % 3],
              group=3, threads=1 + trial % 4, view_mask=mask)


def test_the_c_joint_kernel_keeps_numbas_bits_on_large_and_odd_values():
    # grey values up to 5000 (window totals beyond 2^51 in the lower rows: the plain int64 -> float64
    # conversion there), NaN and inf in views (set values out of range: the scalar rounding, and
    # tables that wrap), a penalty with NaN, -inf and -0.0, every pixel occluded or none
    require_native("joint")
    rng = np.random.default_rng(29)
    for trial in range(8):
        H, W = (30, 40) if trial % 2 == 0 else (11, 17)
        gray, rects, shapes, counts, penalty, occluded = _case(rng, H, W, quantised=False)
        if trial in (0, 1):
            gray[:, :, H // 2:] *= 5000
        if trial in (2, 3):
            gray[0, 0, 3:6, 4:9] = np.nan
            gray[8, 2, H - 2:] = np.inf
            gray[4, 4, 1, 1] = -np.inf  # the centre view
        if trial in (4, 5):
            penalty[2, :, 1] = np.nan
            penalty[3, 0, :] = -np.inf
            penalty[4, 1:4] = -0.0
            penalty[5] = np.inf  # a row offering nothing
        if trial == 6:
            occluded[:] = True
        if trial == 7:
            occluded[:] = False
        _both(gray, np.array([-0.7, 0.1, 0.6, 0.1]), rects, shapes, counts, penalty, occluded, rows=[8, 3][trial % 2],
              group=[4, 3, 2, 1][trial % 4])


def test_the_c_joint_kernel_takes_empty_inputs_and_no_windows():
    require_native("joint")
    rng = np.random.default_rng(31)
    gray, rects, shapes, counts, penalty, occluded = _case(rng, 6, 7)
    # no windows: every objective inf, nothing folded
    out, least, best_k = _both(gray, np.array([0.0, 0.4]), rects[:0], shapes[:0], counts,
                               np.ascontiguousarray(penalty[:, :0]), occluded, rows=8, group=2)
    assert np.isinf(out).all() and np.isinf(least).all() and (best_k == -1).all()
    # no candidates, no rows, no columns: nothing written
    _both(gray, np.zeros(0), rects, shapes, counts, penalty, occluded, rows=8, group=1)
    for H, W in ((0, 7), (6, 0)):
        g = np.zeros((9, 9, H, W), np.float32)
        _both(g, np.array([0.2]), rects, shapes, counts, np.zeros((H, len(rects), W), np.float32),
              np.zeros((H, W), bool), rows=8, group=1)


def test_the_c_offer_runs_are_numbas():
    # rows with gaps longer and shorter than RUN_GAP, NaN (offered), -inf, -0.0, nothing offered,
    # shaped and square windows, empty shapes
    from recon.entropy.layout import RUN_GAP, offer_runs
    from recon.entropy.matching import _offer_runs_native

    require_native("joint")
    rng = np.random.default_rng(37)
    for H, W, K in ((13, 17, 11), (5, 3 * RUN_GAP + 7, 6), (1, 1, 1), (4, 9, 0), (0, 5, 3), (3, 0, 4), (9, 150, 22)):
        penalty = rng.normal(0, 1, (H, K, W)).astype(np.float32)
        penalty[rng.random(penalty.shape) < [0.5, 0.97][W > 100]] = np.inf
        if H > 3 and W > 3 and K > 2:
            penalty[1, 0, 2] = np.nan
            penalty[2, 1, :3] = -np.inf
            penalty[3, 2, 1] = -0.0
            penalty[0] = np.inf
        occluded = rng.random((H, W)) < 0.4
        shapes = rng.integers(0, 11, K).astype(np.int64)
        for threads in (1, 2, 3):
            c = _offer_runs_native(penalty, occluded, shapes, threads)
            n = offer_runs(penalty, occluded, shapes)
            for a, b in zip(c, n):
                _same_bits(a, b)


def _search(kernel, rng, H, W, *, view_mask=None, grid=(9, 9)):
    from recon.entropy.matching import joint_line_search
    from recon.entropy.windows import N_SHAPES

    gray = np.round(rng.random(grid + (H, W)) * 16).astype(np.float32) / 16
    windows = [(s, z) for s in range(N_SHAPES) for z in (3, 5, 7)]
    penalty = np.round(rng.normal(0, 1, (H, len(windows), W)) * 4).astype(np.float32) / 4
    penalty[rng.random(penalty.shape) < 0.5] = np.inf
    penalty[:, 0] = 0.0
    occluded = rng.random((H, W)) < 0.3
    candidates = -0.8 + 0.1 * np.arange(int(rng.integers(3, 12)))
    return joint_line_search(gray, candidates, windows=windows, penalty=penalty, use_shape_set=occluded,
                             intensity_scale=255.0, view_mask=view_mask, ambiguity_delta=0.5, kernel=kernel)


def test_joint_line_search_gives_the_same_maps_with_either_kernel():
    require_native("joint")
    for seed, (H, W), view_mask in ((1, (20, 24), None), (2, (9, 70), None), (3, (15, 11), "random")):
        mask = None
        if view_mask:
            mask = np.random.default_rng(seed).random((9, 9)) < 0.6
            mask[4, 4] = True
        c = _search("native", np.random.default_rng(seed), H, W, view_mask=mask)
        n = _search("numba", np.random.default_rng(seed), H, W, view_mask=mask)
        for name, a, b in zip(("disparity", "objective", "window", "ambiguity"), c, n):
            _same_bits(a, b, name)


def test_joint_line_search_checks_what_the_c_kernel_reads():
    from recon.entropy.matching import joint_line_search

    require_native("joint")
    gray = np.zeros((3, 3, 6, 7), np.float32)
    windows = [(0, 3), (1, 3)]
    with pytest.raises(ValueError, match="penalty must be"):
        joint_line_search(gray, np.zeros(2), windows=windows, penalty=np.zeros((6, 7, 2), np.float32),
                          use_shape_set=np.zeros((6, 7), bool), intensity_scale=1.0, kernel="native")
    with pytest.raises(ValueError, match="use_shape_set"):
        joint_line_search(gray, np.zeros(2), windows=windows, penalty=np.zeros((6, 2, 7), np.float32),
                          use_shape_set=np.zeros((7, 6), bool), intensity_scale=1.0, kernel="native")
    with pytest.raises(ValueError, match="kernel must be"):
        joint_line_search(gray, np.zeros(2), windows=windows, penalty=np.zeros((6, 2, 7), np.float32),
                          use_shape_set=np.zeros((6, 7), bool), intensity_scale=1.0, kernel="fortran")


def test_the_c_joint_search_needs_no_numba_kernel():
    # in a fresh process: joint_line_search on the C path compiles or loads no numba kernel of the
    # modules it calls into
    require_native("joint")
    require_native("initial")
    script = """
import json, numba, numpy as np
import recon.entropy.cost as cost, recon.entropy.layout as layout, recon.entropy.matching as matching
import recon.costvolume as costvolume
from recon.entropy.matching import joint_line_search
rng = np.random.default_rng(0)
gray = rng.random((3, 3, 8, 9)).astype(np.float32)
penalty = rng.random((8, 2, 9)).astype(np.float32)
joint_line_search(gray, np.array([-0.2, 0.0, 0.3]), windows=[(0, 3), (1, 5)], penalty=penalty,
                  use_shape_set=rng.random((8, 9)) < 0.5, intensity_scale=255.0)
used = [f"{m.__name__}.{n}" for m in (cost, layout, matching, costvolume) for n, f in vars(m).items()
        if isinstance(f, numba.core.registry.CPUDispatcher) and f.signatures]
print(json.dumps(used))
"""
    run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout.strip().splitlines()[-1]) == []


def test_the_portable_c_loops_give_numbas_bits(tmp_path, monkeypatch):
    # joint.c built without AVX-512 (its plain loops, as on a CPU without it) gives the same bits
    require_native("joint")
    use_native_build("joint", monkeypatch, tmp_path, flags=("-mno-avx512f",))
    rng = np.random.default_rng(41)
    for trial, (H, W) in enumerate(((21, 33), (7, 90), (2, 3))):
        gray, rects, shapes, counts, penalty, occluded = _case(rng, H, W, quantised=trial != 1)
        if trial == 1:
            gray[:, :, H // 2:] *= 5000  # the plain conversion in the lower rows
        _both(gray, np.array([-0.6, 0.0, 0.45, 0.0]), rects, shapes, counts, penalty, occluded, rows=3, group=3)


@pytest.mark.hci
def test_a_backgammon_estimate_is_the_same_with_either_joint_kernel(monkeypatch):
    # every map of the whole estimate, with the joint search's C kernels and with numba's
    import recon.entropy.matching as matching
    from recon.entropy.estimate import estimate_disparity
    from recon.lf.io import read_lightfield

    require_native("joint")
    lf = read_lightfield(require_hci_scene(), grey=True)
    native = estimate_disparity(lf)
    chosen, kernel, passes = matching.chosen, matching._joint_group_kernel, []
    monkeypatch.setattr(matching, "chosen", lambda name, kernel="auto": name != "joint" and chosen(name, kernel))
    monkeypatch.setattr(matching, "_joint_group_kernel", lambda *args: passes.append(kernel(*args)))
    twin = estimate_disparity(lf)
    assert passes  # the twin's joint search ran numba's kernel
    compared = 0
    for field in dataclasses.fields(native):
        a, b = getattr(native, field.name), getattr(twin, field.name)
        if isinstance(a, np.ndarray):
            _same_bits(a, b, field.name)
            compared += 1
    assert compared >= 9 and native.disparity_range == twin.disparity_range
