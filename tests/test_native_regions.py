"""The C occlusion test and boundary decision (recon/native/regions.c) give the bits of their numba
twins (recon.entropy.regions._occlusion_kernel, recon.entropy.boundary._snap_kernel): the occlusion
sums, and every output of the boundary kernel (the view test's means, views, the far samples'
median, the in-line difference) and the snapped map, on random inputs that reach every branch of
the kernels and on the HCI backgammon scene's own inputs."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from recon.entropy import boundary, regions
from recon.entropy.boundary import snap_boundaries
from recon.entropy.regions import occlusion_diffs, occlusion_diffs_reference
from tests.conftest import require_hci_scene, require_native, use_native_build

ROOT = Path(__file__).resolve().parents[1]


def _same_bits(a, b, name="") -> None:
    assert a.dtype == b.dtype and a.shape == b.shape, name
    assert np.array_equal(a.view(np.uint8), b.view(np.uint8)), name


def _occlusion_both(layers, offsets, gap):
    c = occlusion_diffs(layers, offsets, layer_gap=gap, kernel="native")
    n = occlusion_diffs(layers, offsets, layer_gap=gap, kernel="numba")
    for name, x, y in zip(("neg", "pos"), c, n):
        _same_bits(x, y, name)
    return c


def _grid_offsets(U, V, rng=None):
    u0, v0 = U // 2, V // 2
    offsets = [(u - u0, v - v0) for u in range(U) for v in range(V) if (u, v) != (u0, v0)]
    if rng is not None:
        offsets = [offsets[i] for i in rng.permutation(len(offsets))]
    return offsets


def _layers_case(rng, trial):
    """Layer maps of one trial: tiny, one-row and one-column maps and larger ones, quantised (exact
    ties of the top and bottom layers), with signed zeros, far layers (every pixel lands rows away),
    a slant, NaN and inf."""
    shapes = [(1, 1), (1, 23), (31, 1), (2, 3), (7, 5), (20, 20), (96, 23), (70, 53), (33, 64)]
    H, W = shapes[trial % len(shapes)]
    if trial >= len(shapes):
        H, W = int(rng.integers(1, 80)), int(rng.integers(1, 60))
    kind = trial % 4
    if kind == 0:
        layers = np.round(rng.normal(0, 0.6, (H, W)) * 4) / 4
    elif kind == 1:
        y, x = np.mgrid[0:H, 0:W]
        layers = 3.0 + (x // 9) / 64 + (y // 11) / 128
        layers[H // 4:H // 2, W // 4:W // 2] = 4.25
    elif kind == 2:
        layers = rng.normal(0, 1.0, (H, W))
    else:
        layers = np.where(np.arange(W) < W // 2, 0.0, 1.5) + 0.01 * rng.standard_normal((H, W))
    layers = layers.astype(np.float32)
    layers[rng.random((H, W)) < 0.02] = float(rng.choice([2.5, -1.75]))  # specks that land far
    if trial % 3 == 0:
        layers[rng.random((H, W)) < 0.1] = -0.0
    if trial % 5 == 2:  # not finite: NaN is never tested, inf is and lands nowhere
        layers[rng.random((H, W)) < 0.03] = np.nan
        layers[rng.random((H, W)) < 0.03] = np.inf
        layers[rng.random((H, W)) < 0.03] = -np.inf
    return layers


def test_the_c_occlusion_test_gives_numbas_bits_on_random_inputs(monkeypatch):
    require_native("regions")
    rng = np.random.default_rng(11)
    marked = 0
    for trial in range(60):
        layers = _layers_case(rng, trial)
        grids = [(3, 3), (5, 5), (9, 9), (1, 3), (4, 6), (7, 7)]
        offsets = _grid_offsets(*grids[trial % len(grids)], rng if trial % 2 else None)
        if trial % 7 == 3:  # views between the grid's: fractional shifts
            offsets = [(du * 0.75, dv * 1.5) for du, dv in offsets]
        gap = (0.25, 0.0, 0.5, 1.0)[trial % 4]
        monkeypatch.setattr(regions, "OCCLUSION_BAND_ROWS", (64, 1, 5, 3, 17)[trial % 5])
        monkeypatch.setattr(regions, "thread_count", lambda: (2, 1, 3, 8)[trial % 4])
        neg, pos = _occlusion_both(layers, offsets, gap)
        marked += int((neg < 0).sum() + (pos > 0).sum())
    assert marked > 20_000  # the trials mark many pixels


def test_the_c_occlusion_test_is_the_reference_and_the_same_on_any_number_of_threads(monkeypatch):
    require_native("regions")
    rng = np.random.default_rng(2)
    layers = (np.round(rng.normal(0, 0.6, (96, 23)) * 4) / 4).astype(np.float32)
    layers[30, 2] = 2.5
    offsets = _grid_offsets(5, 5)
    reference = occlusion_diffs_reference(layers, offsets, layer_gap=0.25)
    monkeypatch.setattr(regions, "OCCLUSION_BAND_ROWS", 7)
    for threads in (1, 2, 3, 64):
        monkeypatch.setattr(regions, "thread_count", lambda: threads)
        for x, y in zip(occlusion_diffs(layers, offsets, layer_gap=0.25, kernel="native"), reference):
            _same_bits(x, y)
    assert (reference[0] < 0).sum() > 100


def test_the_c_occlusion_test_takes_no_views_and_no_finite_layers(monkeypatch):
    require_native("regions")

    def numba_called(*args, **kwargs):
        raise AssertionError("the C path called numba")

    monkeypatch.setattr(regions, "_occlusion_kernel", numba_called)
    for layers, offsets in ((np.ones((4, 5), np.float32), []), (np.full((3, 3), np.nan, np.float32), [(1, 0)]),
                            (np.ones((2, 2), np.float32), [(0, 1)])):
        neg, pos = occlusion_diffs(layers, offsets, layer_gap=0.25)
        assert neg.shape == layers.shape and not neg.any() and not pos.any()


class _Outputs:
    """The boundary kernel's five outputs, recorded from either path of snap_boundaries."""

    def __init__(self, monkeypatch):
        self.calls = []
        kernel, call = boundary._snap_kernel, boundary.call

        def numba_kernel(*args):
            kernel(*args)
            self.calls.append(("numba", args[-5:]))

        def c_call(name, function, *args):
            call(name, function, *args)
            self.calls.append(("native", args[-6:-1]))

        monkeypatch.setattr(boundary, "_snap_kernel", numba_kernel)
        monkeypatch.setattr(boundary, "call", c_call)


def _snap_both(monkeypatch, gray, matched, **kw):
    outputs = _Outputs(monkeypatch)
    c = snap_boundaries(gray, matched, kernel="native", **kw)
    n = snap_boundaries(gray, matched, kernel="numba", **kw)
    for name, x, y in zip(("snapped", "changed"), c, n):
        _same_bits(x, y, name)
    if not outputs.calls:  # no pixel tested
        return c, None
    (kind_c, out_c), (kind_n, out_n) = outputs.calls
    assert (kind_c, kind_n) == ("native", "numba")
    for name, x, y in zip(("far_mean", "near_mean", "views", "far_median", "line"), out_c, out_n):
        _same_bits(x, y, name)
    return c, out_c


def _snap_case(rng, trial):
    """Views, a matched map and options of one trial: steps and thin bars (pixels on the rims, rays
    that meet occluders or leave the image), grey values quantised (ties and signed zeros in the
    medians), noisy, or with NaN and inf; grids of one view, one row of views, even and odd sides."""
    grids = [(5, 5), (3, 3), (9, 9), (1, 1), (1, 5), (4, 6), (7, 3)]
    shapes = [(30, 40), (24, 24), (1, 30), (27, 1), (2, 9), (41, 37), (16, 50)]
    U, V = grids[trial % len(grids)]
    H, W = shapes[trial % len(shapes)]
    if trial >= 14:
        H, W = int(rng.integers(1, 45)), int(rng.integers(1, 45))
    y, x = np.mgrid[0:H, 0:W]
    near, far = float(rng.choice([1.2, 2.0, 3.1])), float(rng.choice([0.0, -0.4, 0.5]))
    matched = np.where(x + (y // 3) * (trial % 2) > W // 2, near, far)
    if W > 8:
        matched[:, W // 4:W // 4 + 1 + trial % 2] = near  # a thin bar: rays of the far pixels beside it meet it
    if H > 8:
        matched[H // 3, :] = near
    matched = (matched + (0.02 * rng.standard_normal((H, W)) if trial % 3 == 1 else 0.0)).astype(np.float32)
    centre = np.where(matched > (near + far) / 2, 0.8, 0.2)
    gray = centre + rng.normal(0, 0.02, (U, V, H, W))
    if trial % 4 == 0:  # quantised: ties in the medians
        gray = np.round(gray * 4) / 4
    if trial % 4 == 1:
        gray[..., rng.random((H, W)) < 0.3] = rng.choice([0.0, -0.0], (U, V, 1))
    if trial % 4 == 2:
        gray = rng.random((U, V, H, W))
    gray = gray.astype(np.float32)
    if trial % 6 == 5:
        gray[rng.random(gray.shape) < 0.01] = np.nan
        gray[rng.random(gray.shape) < 0.01] = np.inf
    kw = dict(noise_sigma=float(rng.choice([0.002, 0.01, 0.05])),
              disparity_range=(far - float(rng.choice([0.0, 0.5])), near + float(rng.choice([0.0, 0.7]))),
              jump=float(rng.choice([0.3, 0.5])), support=int(rng.choice([1, 3, 6])),
              confidence=float(rng.choice([0.0, 1.0, 3.0])), mix=float(rng.choice([0.0, 0.4])),
              mix_extrapolate=bool(trial % 2))
    return gray, matched, kw


def test_the_c_boundary_test_gives_numbas_bits_on_random_inputs(monkeypatch):
    require_native("regions")
    rng = np.random.default_rng(13)
    tested = changed = odd_medians = searched = 0
    for trial in range(60):
        gray, matched, kw = _snap_case(rng, trial)
        monkeypatch.setattr(boundary, "thread_count", lambda: (2, 1, 3, 16)[trial % 4])
        (_, flips), out = _snap_both(monkeypatch, gray, matched, **kw)
        if out is not None:
            views = out[2]
            tested += views.size
            odd_medians += int((views % 2 == 1).sum())
            searched += int((views >= boundary.MIN_VIEWS).sum())
        changed += int(flips.sum())
    assert tested > 2000 and changed > 100 and odd_medians > 100 and searched > 1000


def _kernel_inputs(rng, U, V, H, W, n):
    """The boundary kernel's arguments drawn at random, beyond what snap_boundaries makes: any
    far and near values (samples beyond the image's edges), occluders and bounds that end the
    rays early or late, reaches and thresholds that do or do not search the near offsets."""
    gray = (np.round(rng.random((U, V, H, W)) * 6) / 6).astype(np.float32)
    gray[rng.random(gray.shape) < 0.05] = -0.0
    if rng.random() < 0.3:  # NaN and inf samples: sums, minima and medians of NaN
        gray[rng.random(gray.shape) < 0.02] = np.nan
        gray[rng.random(gray.shape) < 0.02] = -np.inf
    elif rng.random() < 0.4:  # views of 0.0, -0.0 or NaN: which of equal values and which NaN a median gives
        views = rng.random((U, V)) < 0.7
        values = np.array([0.0, -0.0, -0.0, np.nan, -np.nan], np.float32)
        gray[views] = rng.choice(values, int(views.sum()))[:, None, None]
    m = (rng.random((H, W)) * 4 - 1).astype(np.float32)
    occ = (rng.random((H, W)) * 4 - 1).astype(np.float32)
    top = np.where(rng.random((H, W)) < 0.5, occ.max(), rng.random((H, W)) * 3).astype(np.float32)
    ys, xs = rng.integers(0, H, n), rng.integers(0, W, n)
    far = np.where(rng.random(n) < 0.2, rng.normal(0, 20, n), m[ys, xs] - rng.random(n) * 2)
    offsets = boundary.near_offsets() if rng.random() < 0.5 else rng.normal(0, 1, int(rng.integers(1, 12)))
    return (gray, m, occ, top, int(rng.integers(0, 12)), ys, xs, far, offsets, float(rng.choice([0.5, 0.0, 2.0])),
            int(rng.integers(1, 12)), float(rng.choice([-1.0, 0.0, 0.05, 1.0])))


def test_the_c_boundary_kernel_gives_numbas_bits_on_any_arguments():
    from recon.native import call

    require_native("regions")
    rng = np.random.default_rng(17)
    hidden = searched = 0
    for trial in range(80):
        U, V = [(5, 5), (3, 3), (1, 1), (2, 7), (9, 9), (1, 4)][trial % 6]
        H, W = [(12, 15), (1, 9), (8, 1), (1, 1), (2, 2), (25, 31)][trial % 6 if trial < 30 else 5]
        n = int(rng.integers(1, 60))
        args = _kernel_inputs(rng, U, V, H, W, n)
        gray, m, occ, top, reach, ys, xs, far, offsets, landing_px, min_views, threshold = args
        c_out = [np.full(n, 7.0), np.full(n, 7.0), np.full(n, 7, np.int64), np.full(n, 7.0), np.full(n, 7.0)]
        n_out = [a.copy() for a in c_out]
        boundary._snap_kernel(*args, *n_out)
        call("regions", "lfrig_snap", gray, U, V, H, W, m, occ, top, reach, ys, xs, far, n, offsets, offsets.size,
             landing_px, min_views, threshold, *c_out, int(rng.integers(1, 5)))
        for name, x, y in zip(("far_mean", "near_mean", "views", "far_median", "line"), c_out, n_out):
            _same_bits(x, y, name)
        hidden += int((n_out[2] < U * V - 1).sum())
        searched += int((n_out[2] >= min_views).sum())
    assert hidden > 500 and searched > 500


def test_the_c_boundary_kernel_does_nothing_for_no_pixels():
    from recon.native import call

    require_native("regions")
    out = np.full(3, 7.0)
    views = np.full(3, 7, np.int64)
    z, i = np.zeros((1, 1), np.float32), np.zeros(0, np.int64)
    call("regions", "lfrig_snap", np.zeros((1, 1, 1, 1), np.float32), 1, 1, 1, 1, z, z, z, 3, i, i,
         np.zeros(0), 0, np.zeros(1), 1, 0.5, 9, 1.0, out, out, views, out, out, 2)
    assert (out == 7.0).all() and (views == 7).all()
    # a map without a jump: no pixel tested, neither kernel called
    gray = np.ones((3, 3, 6, 7), np.float32)
    snapped, changed = snap_boundaries(gray, np.ones((6, 7), np.float32), noise_sigma=0.01,
                                       disparity_range=(0.0, 1.0), jump=0.5, support=3, confidence=1.0,
                                       kernel="native")
    assert not changed.any() and (snapped == 1).all()


def test_the_c_paths_call_no_numba(monkeypatch):
    require_native("regions")
    gray, matched, kw = _snap_case(np.random.default_rng(4), 0)
    layers = _layers_case(np.random.default_rng(4), 6)
    expected = (snap_boundaries(gray, matched, kernel="numba", **kw),
                occlusion_diffs(layers, _grid_offsets(5, 5), layer_gap=0.25, kernel="numba"))

    def numba_called(*args, **kwargs):
        raise AssertionError("the C path called numba")

    monkeypatch.setattr(boundary, "_snap_kernel", numba_called)
    monkeypatch.setattr(regions, "_occlusion_kernel", numba_called)
    got = (snap_boundaries(gray, matched, **kw), occlusion_diffs(layers, _grid_offsets(5, 5), layer_gap=0.25))
    for x, y in zip((*got[0], *got[1]), (*expected[0], *expected[1])):
        _same_bits(x, y)
    for views in ([(1, 0)], []):  # with views, and without (no kernel called)
        with pytest.raises(ValueError, match="kernel must be"):
            occlusion_diffs(layers, views, layer_gap=0.25, kernel="fortran")
    for m in (matched, np.zeros_like(matched)):  # with tested pixels, and without
        with pytest.raises(ValueError, match="kernel must be"):
            snap_boundaries(gray, m, kernel="fortran", **kw)


def test_the_c_kernels_need_no_numba_kernel():
    # in a fresh process: the region labels and the boundary test on the C path load no numba
    # kernel of their modules
    require_native("regions")
    script = """
import json, numba, numpy as np
import recon.entropy.boundary as boundary, recon.entropy.regions as regions
rng = np.random.default_rng(0)
y, x = np.mgrid[0:20, 0:24]
matched = np.where(x > 11, 2.0, 0.0).astype(np.float32)
gray = (np.where(matched > 1, 0.8, 0.2) + 0.01 * rng.standard_normal((5, 5, 20, 24))).astype(np.float32)
boundary.snap_boundaries(gray, matched, noise_sigma=0.01, disparity_range=(0.0, 2.0), jump=0.5, support=3,
                         confidence=1.0, mix=0.4)
regions.occlusion_diffs(matched, [(1, 1), (-2, 0)], layer_gap=0.25)
used = [f"{m.__name__}.{n}" for m in (boundary, regions) for n, f in vars(m).items()
        if isinstance(f, numba.core.registry.CPUDispatcher) and f.signatures]
print(json.dumps(used))
"""
    run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout.strip().splitlines()[-1]) == []


def test_the_portable_conversion_gives_numbas_bits(tmp_path, monkeypatch):
    # regions.c built as for a CPU other than x86-64 (int() of a float64 by a range test, not
    # cvttsd2si): the same bits, NaN and inf layers and views among the inputs
    import recon.native as native

    require_native("regions")
    source = tmp_path / "regions-portable.c"
    source.write_text("".join(f"#include <{h}.h>\n" for h in ("math", "pthread", "stdint", "stdlib", "string"))
                      + f'#undef __x86_64__\n#include "{native.HERE / "regions.c"}"\n')
    use_native_build("regions", monkeypatch, tmp_path, source=source)
    rng = np.random.default_rng(19)
    for trial in (2, 7, 12, 17):
        _occlusion_both(_layers_case(rng, trial), _grid_offsets(5, 5), 0.25)
    for trial in (0, 5, 11):
        gray, matched, kw = _snap_case(rng, trial)
        _snap_both(monkeypatch, gray, matched, **kw)


@pytest.fixture(scope="module")
def backgammon_inputs():
    """The occlusion test's and the boundary test's inputs in a backgammon estimate (default
    options), with what the estimate's own calls gave, from its steps up to the boundary test."""
    from recon.entropy import steps
    from recon.entropy.options import make_options
    from recon.entropy.plan import PLAN, run_step, start
    from recon.lf import read_lightfield

    require_native("regions")
    lf = read_lightfield(require_hci_scene(), grey=True)
    state = start(lf, make_options(None))
    seen = {"occlusion": [], "snap": []}

    def occlusion(*args, **kwargs):
        result = occlusion_diffs(*args, **kwargs)
        seen["occlusion"].append((args, kwargs, result))
        return result

    def snap(*args, **kwargs):
        result = snap_boundaries(*args, **kwargs)
        seen["snap"].append((args, kwargs, result))
        return result

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(regions, "occlusion_diffs", occlusion)
        patch.setattr(steps, "snap_boundaries", snap)
        for phase in PLAN:
            if phase.name == "refine":
                break
            for step in phase.steps:
                run_step(state, step)
    return seen


@pytest.mark.hci
def test_the_c_occlusion_test_gives_numbas_bits_on_backgammon(backgammon_inputs):
    assert len(backgammon_inputs["occlusion"]) == 1
    args, kw, result = backgammon_inputs["occlusion"][0]
    assert args[0].shape == (512, 512) and len(args[1]) == 80
    numba_result = occlusion_diffs(*args, **{**kw, "kernel": "numba"})
    for x, y in zip(result, numba_result):  # the estimate's own call (the C kernel's where it loads)
        _same_bits(x, y)
    assert (result[0] < 0).sum() > 1000 and (result[1] > 0).sum() > 1000


@pytest.mark.hci
def test_the_c_boundary_test_gives_numbas_bits_on_backgammon(backgammon_inputs, monkeypatch):
    assert len(backgammon_inputs["snap"]) == 1
    args, kw, result = backgammon_inputs["snap"][0]
    assert args[0].shape == (9, 9, 512, 512)
    for x, y in zip(result, snap_boundaries(*args, **{**kw, "kernel": "numba"})):
        _same_bits(x, y)
    _, out = _snap_both(monkeypatch, *args, **kw)
    assert out[2].size > 1000 and result[1].sum() > 100
