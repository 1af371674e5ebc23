"""The kernels compiled ahead of time (recon/native): the C plane sweep gives numba's bits, builds
once per source and CPU, and leaves the numba kernel to run where it cannot be had."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import require_hci_scene, require_native, use_native_build

ROOT = Path(__file__).resolve().parents[1]


def _sweep(gray, candidates, kernel, *, window, chunks=1, bands=None):
    from recon.sweep import sweep_least_cost, view_offsets

    offsets = view_offsets(gray.shape[:2])
    indices = (offsets + np.array([gray.shape[0] // 2, gray.shape[1] // 2])).astype(np.int64)
    bounds = [len(candidates) * i // chunks for i in range(chunks + 1)]
    state = None
    for first, stop in zip(bounds, bounds[1:]):
        state = sweep_least_cost(gray, candidates[first:stop], offsets=offsets, indices=indices, window=window,
                                 state=state, first=first, bands=bands, kernel=kernel)
    return state


def _same_bits(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for name in a:
        assert a[name].dtype == b[name].dtype, name
        assert np.array_equal(a[name].view(np.uint8), b[name].view(np.uint8)), name


def test_the_c_sweep_gives_numbas_bits_on_random_light_fields():
    # Shapes, grids (odd and even view counts), windows, whole-pixel shifts (no blend), shifts beyond
    # the image, chunks continued through the state, and bands of one row: every branch of the kernel.
    require_native("sweep")
    rng = np.random.default_rng(11)
    for trial in range(24):
        grid = [(3, 3), (5, 5), (3, 4), (1, 2), (2, 3), (9, 9)][trial % 6]
        H, W = int(rng.integers(6, 30)), int(rng.integers(6, 30))
        window = int(rng.choice([w for w in (1, 3, 5, 7) if w // 2 < min(H, W)]))
        gray = rng.random(grid + (H, W)).astype(np.float32)
        if trial % 4 == 0:  # whole-pixel candidates: the rows are taken as they are
            candidates = np.arange(-3.0, 3.5, 1.0)
        else:
            candidates = np.sort(rng.uniform(-4.5, 4.5, int(rng.integers(1, 14))))
        chunks = int(rng.integers(1, min(len(candidates), 4) + 1))
        bands = None if trial % 3 else int(rng.integers(1, H + 1))
        _same_bits(_sweep(gray, candidates, "native", window=window, chunks=chunks, bands=bands),
                   _sweep(gray, candidates, "numba", window=window, chunks=chunks, bands=bands))


def test_the_c_sweep_keeps_numbas_nan_rule():
    require_native("sweep")
    gray = np.random.default_rng(6).random((3, 3, 12, 14)).astype(np.float32)
    gray[0, 0, 5:8, 6:9] = np.nan
    gray[2, 1, 0:2, :] = np.inf
    candidates = np.linspace(-1.0, 1.0, 7)
    _same_bits(_sweep(gray, candidates, "native", window=3), _sweep(gray, candidates, "numba", window=3))


@pytest.mark.hci
def test_the_c_sweep_gives_numbas_bits_on_backgammon():
    from recon.lf.benchmark import read_benchmark

    require_native("sweep")
    lf = read_benchmark(require_hci_scene(), grey=True)
    gray = np.ascontiguousarray(lf.gray(), np.float32)
    candidates = -3.0 + 0.02 * np.arange(121)  # the baseline's defaults on backgammon
    _same_bits(_sweep(gray, candidates, "native", window=7, chunks=4),
               _sweep(gray, candidates, "numba", window=7, chunks=4))


def test_the_sweep_checks_what_the_c_kernel_reads():
    from recon.sweep import sweep_least_cost, view_offsets

    require_native("sweep")
    gray = np.zeros((3, 3, 8, 8), np.float32)
    offsets = view_offsets((3, 3))
    with pytest.raises(ValueError, match="within the 3x3 grid"):
        sweep_least_cost(gray, np.zeros(2), offsets=offsets, indices=(offsets + 2).astype(np.int64), window=3,
                         kernel="native")
    state = _sweep(gray, np.zeros(2), "native", window=3)
    state["best"] = state["best"][:, ::2]
    with pytest.raises(ValueError, match="state\\['best'\\]"):
        sweep_least_cost(gray, np.zeros(2), offsets=offsets, indices=(offsets + 1).astype(np.int64), window=3,
                         state=state, kernel="native")
    for kernel in ("native", "numba"):
        with pytest.raises(ValueError, match="the same views, at least one"):
            sweep_least_cost(gray, np.zeros(2), offsets=offsets[:0], indices=np.zeros((0, 2), np.int64), window=3,
                             kernel=kernel)
        empty = sweep_least_cost(gray, np.zeros(0), offsets=offsets, indices=(offsets + 1).astype(np.int64),
                                 window=3, kernel=kernel)
        assert (empty["best_index"] == -2).all()  # no candidate swept
    with pytest.raises(ValueError, match="kernel must be"):
        sweep_least_cost(gray, np.zeros(2), offsets=offsets, indices=(offsets + 1).astype(np.int64), window=3,
                         kernel="fortran")


def test_the_library_is_named_by_its_source_and_built_whole(tmp_path, monkeypatch):
    import recon.native as native

    require_native("sweep")
    cc = native.compiler()
    for header in native.HERE.glob("*.h"):
        (tmp_path / header.name).write_bytes(header.read_bytes())
    source = tmp_path / "sweep.c"
    source.write_bytes((native.HERE / "sweep.c").read_bytes())
    monkeypatch.setattr(native, "HERE", tmp_path)
    monkeypatch.setattr(native, "BUILD", tmp_path / "build")
    monkeypatch.setattr(native, "_loaded", {})
    first = native.library_path("sweep", cc)
    assert native.library("sweep") is not None and first.is_file()
    assert [p.name for p in (tmp_path / "build").iterdir()] == [first.name]  # no temporary file left
    source.write_text(source.read_text() + "\n/* changed */\n")
    assert native.library_path("sweep", cc) != first  # an edited source builds anew
    monkeypatch.setattr(native, "_loaded", {})
    assert native.library("sweep") is not None
    assert [p.name for p in (tmp_path / "build").iterdir()] == [native.library_path("sweep", cc).name]
    (tmp_path / "rows.h").write_text((tmp_path / "rows.h").read_text() + "\n/* changed */\n")
    assert native.library_path("sweep", cc).name not in [p.name for p in (tmp_path / "build").iterdir()]  # a header too


def test_a_link_where_the_build_folder_goes_is_not_followed(tmp_path, monkeypatch):
    import recon.native as native

    if native.compiler() is None:
        pytest.skip("no C compiler here")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "build").symlink_to(elsewhere)
    monkeypatch.setattr(native, "BUILD", tmp_path / "build")
    monkeypatch.setattr(native, "_loaded", {})
    monkeypatch.setattr(native, "_why", {})
    assert native.library("sweep") is None
    assert "symbolic link" in native.unavailable("sweep")
    assert list(elsewhere.iterdir()) == []


def _run(code: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT), **env})


BASELINE_IN_A_PROCESS = """
import json, sys
import numpy as np
from recon.baseline import estimate_baseline
from recon.native import unavailable
from recon.synthetic import occluding_square_scene
lf, _ = occluding_square_scene(24, back=-0.5, front=1.0)
d = estimate_baseline(lf, window=5, step=0.1, disparity_range=(-1.0, 1.5)).disparity
print(json.dumps({"why": unavailable("sweep"), "numba": "numba" in sys.modules, "digest": d.tobytes().hex()}))
"""


def test_without_the_c_kernel_the_baseline_runs_numbas_with_the_same_result():
    require_native("sweep")
    native = json.loads(_run(BASELINE_IN_A_PROCESS).stdout)
    assert native["why"] is None and not native["numba"]  # the C sweep: numba is never loaded
    for env, why in (({"LFRIG_NATIVE": "0"}, "LFRIG_NATIVE=0"), ({"CC": "false"}, "could not be built")):
        # CC=false: a compiler that fails; the build goes to a temporary folder of its own
        run = _run(BASELINE_IN_A_PROCESS.replace("from recon.native import unavailable",
                                                 "import recon.native, tempfile\n"
                                                 "recon.native.BUILD = recon.native.Path(tempfile.mkdtemp())\n"
                                                 "from recon.native import unavailable"), **env)
        other = json.loads(run.stdout)
        assert why in other["why"] and other["numba"]
        assert other["digest"] == native["digest"]


def test_a_compiler_that_is_not_there_is_named(monkeypatch):
    import recon.native as native

    monkeypatch.setattr(native, "_loaded", {})
    monkeypatch.setattr(native, "_why", {})
    monkeypatch.setenv("CC", "no-such-compiler-here")
    assert native.library("sweep") is None
    assert native.unavailable("sweep") == "no C compiler: CC=no-such-compiler-here is not on the PATH"
    assert native.status() == {"sweep": "numba: no C compiler: CC=no-such-compiler-here is not on the PATH"}


def test_the_c_kernel_that_cannot_be_had_says_why():
    run = _run("from recon.sweep import sweep_least_cost, view_offsets\n"
               "import numpy as np\n"
               "o = view_offsets((3, 3))\n"
               "sweep_least_cost(np.zeros((3, 3, 6, 6), np.float32), np.zeros(1), offsets=o,\n"
               "                 indices=(o + 1).astype(np.int64), window=1, kernel='native')", LFRIG_NATIVE="0")
    assert run.returncode != 0 and "the C sweep is not available: LFRIG_NATIVE=0" in run.stderr


def test_a_process_forks_after_the_c_sweep_and_the_child_sweeps_too():
    # The C sweep's threads live for one call: a child forked after it (the fault tests' runner,
    # multiprocessing's fork) runs it again. A thread pool kept by the parent (OpenMP's) hangs there.
    require_native("sweep")
    code = ("import os, sys, numpy as np\n"
            "from recon.sweep import sweep_least_cost, view_offsets\n"
            "o = view_offsets((3, 3)); g = np.random.default_rng(1).random((3, 3, 40, 40)).astype(np.float32)\n"
            "run = lambda: sweep_least_cost(g, np.linspace(-1, 1, 5), offsets=o, indices=(o + 1).astype(np.int64),\n"
            "                              window=3, bands=4, kernel='native')['best'].sum()\n"
            "parent = run()\n"
            "pid = os.fork()\n"
            "if pid == 0:\n"
            "    os._exit(0 if run() == parent else 3)\n"
            "print(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]))")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert run.stdout.split() == ["0"], run.stderr


@pytest.mark.hci
def test_the_benchmark_times_both_kernels_and_finds_the_same_bits():
    scene = require_hci_scene()
    from recon.native import SIGNATURES

    for name in SIGNATURES:
        require_native(name)
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "native_kernels.py"), "--scene", str(scene),
                          "--runs", "1"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "sweep 121 candidates, initial 51" in run.stdout and run.stdout.count("the same bits: True") == 3
    assert "C (recon/native/sweep.c)" in run.stdout and "numba (costvolume._sweep_kernel)" in run.stdout
    assert "C (recon/native/initial.c)" in run.stdout
    assert "estimate's steps, C, median wall s: load" in run.stdout and "matching" in run.stdout


def _window_inputs(rng, grid, H, W, trial):
    from recon.entropy.cost import set_view_counts
    from recon.entropy.initial import initial_view_mask
    from recon.entropy.windows import window_rect

    mask = initial_view_mask(grid) if trial % 2 else None
    counts = set_view_counts(grid, mask)
    windows = [(s, int(rng.choice([3, 5, 7])), s) for s in (range(9) if trial % 3 else [0])]
    sets = np.unique([w[2] for w in windows])
    lookup = {int(s): i for i, s in enumerate(sets)}
    if trial % 4 == 3:  # a window gate per pixel, the square everywhere
        allowed = rng.random((len(windows), H, W)) < 0.7
        allowed[0] = True
    else:
        allowed = np.ones((len(windows), 1, 1), np.bool_)
        allowed[1:2] = trial % 5 != 0  # a window offered nowhere
    return dict(sets=sets, window_set=np.array([lookup[w[2]] for w in windows], np.int64),
                rects=np.array([window_rect(w[0], w[1]) for w in windows], np.int64),
                counts=np.array([counts[w[2]] for w in windows], np.float64), allowed=allowed, view_mask=mask)


def test_the_first_phases_c_kernels_give_numbas_bits_on_random_inputs():
    # recon/native/initial.c: the nine-view search's window costs (square and shaped windows, view
    # masks, a gate per pixel or a window offered nowhere), the sub-step arg-min and the ambiguity
    # count (NaN costs among them), the range discovery's downsampling (factors 1-7).
    from recon.entropy.cost import cost_ambiguity, min_window_costs
    from recon.entropy.initial import downsample_views
    from recon.entropy.matching import subpixel_argmin

    require_native("initial")
    rng = np.random.default_rng(3)
    for trial in range(24):
        grid = [(9, 9), (5, 5), (3, 4), (7, 7)][trial % 4]
        H, W = int(rng.integers(8, 40)), int(rng.integers(8, 40))
        gray = rng.random(grid + (H, W)).astype(np.float32)
        inputs = _window_inputs(rng, grid, H, W, trial)
        candidates = np.sort(rng.uniform(-3, 3, int(rng.integers(1, 6)))).astype(np.float32)
        native = min_window_costs(gray, candidates, **inputs, kernel="native")
        twin = min_window_costs(gray, candidates, **inputs, kernel="numba")
        assert np.array_equal(native.view(np.uint32), twin.view(np.uint32))
        costs = rng.random((int(rng.integers(1, 9)), H, W)).astype(np.float32)
        if trial % 3 == 0:
            costs[rng.integers(0, len(costs)), 2:4, 3:5] = np.nan
        values = np.sort(rng.uniform(-2, 2, len(costs)))
        for a, b in zip(subpixel_argmin(costs, values, kernel="native"),
                        subpixel_argmin(costs, values, kernel="numba")):
            assert np.array_equal(a.view(np.uint32), b.view(np.uint32))
        assert np.array_equal(cost_ambiguity(costs, 0.05, kernel="native"), cost_ambiguity(costs, 0.05, kernel="numba"))
        factor = int(rng.integers(1, 8))
        if W // factor >= 2:
            assert np.array_equal(downsample_views(gray, factor, kernel="native").view(np.uint32),
                                  downsample_views(gray, factor, kernel="numba").view(np.uint32))


def test_the_nine_view_costs_give_numbas_bits_on_wide_rows():
    # rows of whole tiles of the sets' sums (64 pixels), and of whole tiles and a part
    from recon.entropy.cost import min_window_costs

    require_native("initial")
    rng = np.random.default_rng(12)
    for trial, W in enumerate((64, 65, 128, 150, 201)):
        grid = [(9, 9), (5, 5), (3, 4), (7, 7)][trial % 4]
        gray = rng.random(grid + (9, W)).astype(np.float32)
        inputs = _window_inputs(rng, grid, 9, W, trial + 1)
        candidates = np.sort(rng.uniform(-3, 3, 2)).astype(np.float32)
        native = min_window_costs(gray, candidates, **inputs, kernel="native")
        twin = min_window_costs(gray, candidates, **inputs, kernel="numba")
        assert np.array_equal(native.view(np.uint32), twin.view(np.uint32))


def test_the_nine_view_costs_give_numbas_bits_with_any_view_counts():
    # windows of one denominator share a division where it is positive and finite; view counts of 0,
    # negative, inf or NaN (each window then divides alone), and of equal denominators across
    # windows of other shapes
    from recon.entropy.cost import min_window_costs

    require_native("initial")
    rng = np.random.default_rng(21)
    odd = np.array([0.0, -2.0, np.inf, np.nan, 0.5, 3.0, 1e-300, 6.0])
    for trial in range(12):
        W = int(rng.integers(3, 90))
        gray = rng.random((3, 3, 7, W)).astype(np.float32)
        if trial % 4 == 3:
            gray[1, 1, 2:4, 1:3] = np.nan  # NaN sums
        if trial % 3 == 1:
            gray[:, :, :, : W // 2] = 0.5  # sums of 0 (costs of -0 with a negative count)
        inputs = _window_inputs(rng, (3, 3), 7, W, trial)
        inputs["counts"] = rng.choice(odd if trial % 2 else np.array([2.0, 3.0, 4.0, 6.0]), len(inputs["counts"]))
        candidates = np.sort(rng.uniform(-2, 2, 2)).astype(np.float32)
        native = min_window_costs(gray, candidates, **inputs, kernel="native")
        twin = min_window_costs(gray, candidates, **inputs, kernel="numba")
        assert np.array_equal(native.view(np.uint32), twin.view(np.uint32))
    for trial in range(6):  # every sum 0: costs of +0 and -0, the first window taken at a pixel decides
        W = int(rng.integers(8, 30))
        inputs = _window_inputs(rng, (3, 3), 7, W, 1)
        inputs["allowed"] = rng.random((len(inputs["counts"]), 7, W)) < 0.5
        inputs["counts"] = rng.choice(np.array([-3.0, 2.0, -6.0, 4.0]), len(inputs["counts"]))
        gray = np.full((3, 3, 7, W), 0.25, np.float32)
        native = min_window_costs(gray, np.array([0.0, 0.5], np.float32), **inputs, kernel="native")
        twin = min_window_costs(gray, np.array([0.0, 0.5], np.float32), **inputs, kernel="numba")
        assert np.array_equal(native.view(np.uint32), twin.view(np.uint32))


def test_the_first_phases_c_kernels_without_avx512_give_numbas_bits(monkeypatch, tmp_path):
    # initial.c built without AVX-512 (its loops over 256-bit registers or fewer, as on a CPU without
    # it; with it they take 512) gives the same bits
    import recon.native as native
    from recon.entropy.cost import min_window_costs
    from recon.entropy.matching import subpixel_argmin

    require_native("initial")
    use_native_build("initial", monkeypatch, tmp_path, flags=("-mno-avx512f",))
    rng = np.random.default_rng(8)
    for trial in range(8):
        grid = [(9, 9), (5, 5), (3, 4), (7, 7)][trial % 4]
        H, W = int(rng.integers(8, 40)), int(rng.integers(8, 70))
        gray = rng.random(grid + (H, W)).astype(np.float32)
        inputs = _window_inputs(rng, grid, H, W, trial)
        candidates = np.sort(rng.uniform(-3, 3, int(rng.integers(1, 4)))).astype(np.float32)
        native_costs = min_window_costs(gray, candidates, **inputs, kernel="native")
        twin = min_window_costs(gray, candidates, **inputs, kernel="numba")
        assert np.array_equal(native_costs.view(np.uint32), twin.view(np.uint32))
        values = np.sort(rng.uniform(-2, 2, len(candidates)))
        for a, b in zip(subpixel_argmin(native_costs, values, kernel="native"),
                        subpixel_argmin(native_costs, values, kernel="numba")):
            assert np.array_equal(a.view(np.uint32), b.view(np.uint32))


ESTIMATE_IN_A_PROCESS = """
import hashlib, json
import numpy as np
from recon.entropy import estimate_disparity
from recon.lf.lightfield import LightField
from recon.native import status
from recon.synthetic import occluding_square_scene
lf, _ = occluding_square_scene(48, seed=4, back=-0.7, front=0.9)
found = LightField(views=lf.views)  # no range: the coarse search finds it (the downsampling)
out = {}
for name, field in (("known", lf), ("found", found)):
    r = estimate_disparity(field)
    out[name] = {k: hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest()
                 for k, v in vars(r).items() if isinstance(v, np.ndarray)}
print(json.dumps({"maps": out, "kernels": status()}))
"""


def test_an_estimate_with_its_c_kernels_makes_numbas_maps():
    from recon.entropy.preload import C_TWINS

    libraries = sorted(set(C_TWINS.values()))
    for name in libraries:
        require_native(name)
    native = json.loads(_run(ESTIMATE_IN_A_PROCESS).stdout.strip().splitlines()[-1])
    twins = json.loads(_run(ESTIMATE_IN_A_PROCESS, LFRIG_NATIVE="0").stdout.strip().splitlines()[-1])
    assert native["kernels"] == dict.fromkeys(libraries, "C")
    assert twins["kernels"] == dict.fromkeys(libraries, "numba: LFRIG_NATIVE=0")
    assert native["maps"] == twins["maps"] and len(native["maps"]["found"]) >= 8
