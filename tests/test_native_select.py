"""The C window selection (recon/native/select.c) gives the bits of its numba twin
(recon.entropy.entropy._select_kernel): the window maps, every offered window's entropy (dense and
sparse) and the volume's mask and offsets, on random inputs that reach every rule of the selection
and on the HCI backgammon scene's own inputs."""


import numpy as np
import pytest

from recon.entropy import entropy
from recon.entropy.entropy import select_windows
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH, TEXTURE
from tests.conftest import require_hci_scene, require_native, use_native_build


def _same_bits(a, b) -> None:
    assert len(a) == len(b)
    for name, x, y in zip(("shape", "size", "entropy", "all"), a, b):
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, name
            assert np.array_equal(x.view(np.uint8), y.view(np.uint8)), name
        else:  # a SparseVolume
            assert x.shape == y.shape and x.fill == y.fill
            for part in ("mask", "start", "values"):
                p, q = getattr(x, part), getattr(y, part)
                assert p.dtype == q.dtype and p.shape == q.shape, part
                assert np.array_equal(p.view(np.uint8), q.view(np.uint8)), part


def _both(grey, disp, labels, **kw):
    c = select_windows(grey, disp, labels, kernel="native", **kw)
    n = select_windows(grey, disp, labels, kernel="numba", **kw)
    _same_bits(c, n)
    return c


def _random_case(rng, trial):
    """Grey and disparity bins, labels, and options of one trial: tiny, one-row and one-column
    images (every window clipped), and larger ones (windows summed along the rings), with each
    option of select_windows on or off."""
    shapes = [(1, 1), (1, 17), (19, 1), (2, 3), (5, 6), (9, 12), (21, 19), (27, 33), (36, 31)]
    H, W = shapes[trial % len(shapes)]
    if trial >= len(shapes):
        H, W = int(rng.integers(1, 38)), int(rng.integers(1, 38))
    sizes = [(3, 5, 7), (1, 3), (5,), (3, 5, 7, 9, 11, 13, 15), (1, 5, 9), (3, 3, 7), (7, 9, 11)][trial % 7]
    y, x = np.mgrid[0:H, 0:W]
    levels = [2, 6, 40, 256][trial % 4]
    grey = rng.integers(0, levels, (H, W))
    layers = (np.where(x + y // 2 < W // 2, 0.0, 1.0) + 0.01 * rng.standard_normal((H, W))).astype(np.float32)
    disp = (layers * 7).astype(np.int64) + rng.integers(0, 3, (H, W))
    disp -= disp.min()
    if H > 6 and W > 6:  # a flat patch: windows of equal entropy (ties: the larger, then the lower shape)
        grey[: H // 2, : W // 2] = 1
        disp[: H // 2, : W // 2] = 2
    patch = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH, TEXTURE, 7], (H // 3 + 1, W // 3 + 1))
    labels = patch.repeat(3, 0).repeat(3, 1)[:H, :W].astype(np.uint8)
    labels[rng.random((H, W)) < 0.15] = OCCLUDED
    labels[rng.random((H, W)) < 0.1] = OCCLUDING
    kw = dict(sizes=sizes, alpha1=float(rng.choice([1.0, 0.5, 2.3])),
              alpha2_occlusion=float(rng.choice([1.0, 0.7, -0.4])), alpha2_other=float(rng.choice([0.0, 0.3])),
              strips=bool(trial % 3 != 1))
    side = trial % 4
    kw["side_radius"] = (None, np.zeros((H, W), np.int64), rng.integers(-1, 9, (H, W)), 3)[side]
    if trial % 5 != 4:
        if trial % 7 == 2:  # NaN and inf layers: never reaching another layer by the test
            layers[rng.random((H, W)) < 0.05] = np.nan
            layers[rng.random((H, W)) < 0.05] = np.inf
        kw["layers"] = layers
        kw["layer_gap"] = (0.25, None, 0.0, 0.5)[trial % 4]
    if trial % 3 != 2:
        kw["max_size"] = rng.choice(list(sizes) + [0, 99], (H, W))
    return grey, disp, labels, kw


def test_the_c_selection_gives_numbas_bits_on_random_inputs(monkeypatch):
    require_native("select")
    rng = np.random.default_rng(23)
    offered = 0
    for trial in range(100):
        grey, disp, labels, kw = _random_case(rng, trial)
        K = (11 if kw["strips"] else 9) * len(kw["sizes"])
        if trial % 4 == 3:  # bands of a few rows (one shorter at the end)
            rows = int(rng.integers(1, 4))
            monkeypatch.setattr(entropy, "SELECT_BAND_MIB", rows * grey.shape[1] * K * 4 / 2 ** 20)
        else:
            monkeypatch.setattr(entropy, "SELECT_BAND_MIB", 64)
        dense = _both(grey, disp, labels, return_all=True, **kw)
        _both(grey, disp, labels, return_all="sparse", **kw)
        if trial % 5 == 0:
            _both(grey, disp, labels, **kw)
        offered += int(np.isfinite(dense[3]).sum())
    assert offered > 100_000  # the trials offer many windows


@pytest.mark.parametrize("variant", ["default", "no strips", "no layers", "clipped"])
def test_the_c_selection_gives_numbas_bits_on_every_window_rule(monkeypatch, variant):
    # the twin tests' inputs (a two-layer map with a slant, side radii, size caps, occlusion patches)
    # at sizes 3..15: the pairs of side windows summed together along their rings, and (clipped)
    # every pixel summed as near the border
    require_native("select")
    from tests.test_twins_entropy import _window_inputs
    from tests.kernel_inputs import seeded

    grey, disp, labels, kw = _window_inputs(seeded())
    if variant == "no strips":
        kw["strips"] = False
    if variant == "no layers":
        kw["layers"] = None
    if variant == "clipped":
        monkeypatch.setattr(entropy, "_ring_margin", lambda sizes: 10 ** 6)
    dense = _both(grey, disp, labels, return_all=True, **kw)
    assert np.isfinite(dense[3]).sum() > 10 * grey.size
    _both(grey, disp, labels, return_all="sparse", **kw)


def test_the_c_selection_gives_numbas_bits_with_bins_beyond_16_bits():
    require_native("select")
    rng = np.random.default_rng(5)
    for H, W in ((17, 19), (3, 40)):
        grey = rng.integers(0, 2 ** 15 + 9, (H, W))
        grey[:, : W // 2] = rng.integers(0, 3, (H, W // 2))
        disp = rng.integers(0, 40, (H, W))
        labels = rng.choice(np.array([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH], np.uint8), (H, W))
        _both(grey, disp, labels, sizes=(3, 5, 7), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0,
              side_radius=rng.integers(0, 4, (H, W)), return_all=True)
        _both(grey, disp, labels, sizes=(1, 3, 5, 7), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0,
              return_all="sparse")


def test_the_c_selection_without_sse2_gives_numbas_bits(monkeypatch, tmp_path):
    # select.c built with its plain sums (two doubles, as where SSE2 is not there) gives the same bits
    require_native("select")
    use_native_build("select", monkeypatch, tmp_path, flags=("-U__SSE2__",))
    rng = np.random.default_rng(29)
    for trial in range(14):
        grey, disp, labels, kw = _random_case(rng, trial)
        _both(grey, disp, labels, return_all="sparse", **kw)


def test_the_c_selection_is_the_same_on_any_number_of_threads(monkeypatch):
    require_native("select")
    grey, disp, labels, kw = _random_case(np.random.default_rng(3), 8)
    first = select_windows(grey, disp, labels, kernel="native", return_all="sparse", **kw)
    for threads in (1, 2, 3, 64):
        monkeypatch.setattr(entropy, "thread_count", lambda: threads)
        _same_bits(select_windows(grey, disp, labels, kernel="native", return_all="sparse", **kw), first)


def test_the_c_path_calls_no_numba(monkeypatch):
    require_native("select")
    grey, disp, labels, kw = _random_case(np.random.default_rng(4), 7)
    expected = select_windows(grey, disp, labels, kernel="numba", return_all="sparse", **kw)

    def numba_called(*args, **kwargs):
        raise AssertionError("the C path called numba")

    monkeypatch.setattr(entropy, "_select_kernel", numba_called)
    monkeypatch.setattr(entropy, "row_order", numba_called)  # numba.get_num_threads
    monkeypatch.setattr(entropy, "numba", None)
    _same_bits(select_windows(grey, disp, labels, return_all="sparse", **kw), expected)


def test_the_c_selection_checks_what_it_reads():
    require_native("select")
    grey = np.zeros((9, 10), np.int64)
    kw = dict(sizes=(3, 5), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0, kernel="native")
    with pytest.raises(ValueError, match="labels and layers"):
        select_windows(grey, grey, np.zeros((10, 9), np.uint8), **kw)
    with pytest.raises(ValueError, match="labels and layers"):
        select_windows(grey, grey, np.zeros((9, 10), np.uint8), layers=np.zeros(90, np.float32), layer_gap=0.1,
                       **kw)
    for kernel in ("native", "numba"):  # an empty image: refused as before, on both paths
        with pytest.raises(ValueError, match="zero-size"):
            select_windows(np.zeros((0, 4), np.int64), np.zeros((0, 4), np.int64), np.zeros((0, 4), np.uint8),
                           **{**kw, "kernel": kernel})


def test_the_c_kernel_does_nothing_for_no_rows():
    from recon.native import call

    require_native("select")
    i64 = np.zeros(1, np.int64)
    out = np.full(4, 7, np.int64)
    # no rows (n_order 0): returns at once, without memory, writing nothing
    call("select", "lfrig_select", np.zeros(2, np.uint16), 0, np.zeros(1, np.uint8), 1, 1, np.zeros(4, np.int64), 1,
         1, np.array([1], np.int64), 1.0, 1.0, 0.0, 1, 1, np.zeros(3), 3, i64, np.zeros(1, np.float32), -1.0,
         i64, np.zeros(0, np.int64), 0, 0, np.zeros(1, np.uint64), 1, i64, np.zeros(1, np.bool_), out, out,
         np.zeros(1, np.float32), np.zeros(0, np.float32), 0, np.zeros(0, np.float32), 0, out, np.zeros(1, np.uint8),
         2)
    assert (out == 7).all()


@pytest.mark.hci
def test_the_c_selection_gives_numbas_bits_on_backgammon(monkeypatch):
    # the estimate's steps up to the window selection on backgammon (default options), whose inputs
    # then go to both kernels
    from recon.entropy import steps
    from recon.entropy.options import make_options
    from recon.entropy.plan import PLAN, run_step, start
    from recon.lf import read_lightfield

    require_native("select")
    lf = read_lightfield(require_hci_scene(), grey=True)
    state = start(lf, make_options(None))
    seen = []

    def select(*args, **kwargs):
        seen.append((args, kwargs))
        return select_windows(*args, **kwargs)

    monkeypatch.setattr(steps, "select_windows", select)
    done = False
    for phase in PLAN:
        for step in phase.steps:
            run_step(state, step)
            if step is steps.WINDOWS:
                done = True
                break
        if done:
            break
    assert len(seen) == 1
    (grey, disp, labels), kw = seen[0]
    assert kw["return_all"] == "sparse" and grey.shape == (512, 512)
    numba_result = select_windows(grey, disp, labels, **{**kw, "kernel": "numba"})
    w = state.windows  # the step's own (the C kernel's where it loads)
    _same_bits((w["shape"], w["size"], w["entropy"], w["all_entropy"]), numba_result)
    assert numba_result[3].values.size > 5_000_000
