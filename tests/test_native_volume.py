"""The C readers of the sparse volume (recon/native/volume.c) give the bits of their numba twins
(recon.entropy.volume._take_kernel, _window_major_kernel): SparseVolume.take and
SparseVolume.window_major on random volumes that reach every branch (tiny and one-row or one-column
volumes, K on and off a byte's bounds, NaN, inf and entries whose scaled value overflows), on the
volumes of the window selection and on the reads of a whole backgammon estimate."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy import volume
from recon.entropy.volume import SparseVolume
from tests.conftest import require_hci_scene, require_native


def _same_bits(a: np.ndarray, b: np.ndarray, what: str = "") -> None:
    assert a.dtype == b.dtype and a.shape == b.shape, what
    assert np.array_equal(a.view(np.uint8), b.view(np.uint8)), what


def _random_volume(rng, H, W, K, *, kept=0.3, fill=-np.inf) -> np.ndarray:
    """(H, W, K) float32: ``fill`` but at ``kept`` of the entries, which are ordinary values, huge ones
    (their scaled value overflows), subnormal ones, zeros of either sign, NaN and inf of either sign."""
    dense = rng.standard_normal((H, W, K)).astype(np.float32) * np.float32(3)
    kind = rng.integers(0, 20, (H, W, K))
    dense[kind == 0] *= np.float32(1e37)
    dense[kind == 1] = np.float32(1e-42) * rng.integers(-9, 9, int((kind == 1).sum()))
    for k, special in enumerate((np.nan, np.inf, -np.inf, -0.0, 0.0)):
        dense[kind == 2 + k] = special
    dense[rng.random((H, W, K)) >= kept] = np.float32(fill)
    return dense


SHAPES = ((1, 1, 1), (1, 1, 8), (1, 17, 9), (19, 1, 7), (2, 3, 16), (5, 6, 77), (9, 12, 99), (33, 21, 24),
          (4, 70, 63), (12, 5, 1))


def _both_take(v: SparseVolume, index: np.ndarray) -> np.ndarray:
    c = v.take(index, kernel="native")
    _same_bits(c, v.take(index, kernel="numba"), "take")
    return c


def _both_window_major(v: SparseVolume, a: int, b: int, scale: float) -> np.ndarray:
    c = v.window_major(a, b, scale=scale, kernel="native")
    _same_bits(c, v.window_major(a, b, scale=scale, kernel="numba"), f"window_major {a} {b} {scale}")
    return c


def test_the_c_take_gives_numbas_bits_on_random_volumes():
    require_native("volume")
    rng = np.random.default_rng(31)
    reached = kept = 0
    for trial in range(60):
        H, W, K = SHAPES[trial % len(SHAPES)] if trial < 2 * len(SHAPES) else rng.integers(1, 40, 3)
        fill = (-np.inf, 0.0, 2.5, -np.inf)[trial % 4]
        v = SparseVolume.pack(_random_volume(rng, H, W, K, kept=(0.3, 0.05, 0.9, 1.0, 0.0)[trial % 5], fill=fill),
                              fill=fill)
        index = rng.integers(-K, K, (H, W))
        if trial % 3 == 0:  # the first and last windows, from either end
            index[: H // 2] = rng.choice([0, K - 1, -1, -K], (H // 2, W))
        out = _both_take(v, index)
        _same_bits(out, v.take_reference(index), "take_reference")
        reached += out.size
        kept += int((out.view(np.uint32) != np.float32(fill).view(np.uint32)).sum())
        _both_take(v, index.astype(np.int32))  # another index dtype, made int64 for both
    assert reached > 5_000 and kept > 1_000  # entries kept and not, over many pixels


def test_the_c_window_major_gives_numbas_bits_on_random_volumes():
    require_native("volume")
    rng = np.random.default_rng(32)
    finite = 0
    for trial in range(60):
        H, W, K = SHAPES[trial % len(SHAPES)] if trial < 2 * len(SHAPES) else rng.integers(1, 40, 3)
        fill = (-np.inf, 0.0, np.inf)[trial % 3]
        v = SparseVolume.pack(_random_volume(rng, H, W, K, kept=(0.3, 0.05, 0.9, 1.0, 0.0)[trial % 5], fill=fill),
                              fill=fill)
        for scale in (-1.7, 1.0, float(rng.standard_normal()), 1e30, 1e-30, 0.0, -0.0, np.inf, np.nan, 0.1):
            out = _both_window_major(v, 0, H, scale)
            finite += int(np.isfinite(out).sum())
        a = int(rng.integers(-2, H + 1))
        b = int(rng.integers(max(a, 0), H + 3))
        _both_window_major(v, a, b, -0.37)  # rows a..b, clipped to the volume's (none when b == a)
        _both_window_major(v, H - 1, H, 3.0)
        _same_bits(_both_window_major(v, 0, 0, 1.0), np.empty((0, K, W), np.float32))
    assert finite > 20_000


def test_the_c_readers_ignore_a_masks_padding_bits():
    # bits of the last byte beyond window K - 1 (packbits leaves them 0): neither kernel reads them
    require_native("volume")
    rng = np.random.default_rng(33)
    for K in (1, 5, 13):
        v = SparseVolume.pack(_random_volume(rng, 6, 7, K, kept=0.5))
        v.mask[..., -1] |= np.uint8(0xFF >> (K % 8 or 8))
        index = rng.integers(-K, K, (6, 7))
        _same_bits(_both_take(v, index), v.take_reference(index))
        _both_window_major(v, 0, 6, -1.0)


def test_the_c_readers_give_numbas_bits_on_the_window_selections_volumes():
    # the volumes select_windows packs (sparse) on the twin tests' inputs, read at the chosen windows
    # and as the joint search's penalty
    from recon.entropy.entropy import select_windows
    from tests.kernel_inputs import seeded
    from tests.test_twins_entropy import _window_inputs

    require_native("volume")
    grey, disp, labels, kw = _window_inputs(seeded())
    for strips in (True, False):
        shape, size, _, v = select_windows(grey, disp, labels, **{**kw, "strips": strips}, return_all="sparse",
                                           kernel="numba")
        sizes = sorted(kw["sizes"])
        k = shape * len(sizes) + np.searchsorted(sizes, size)
        taken = _both_take(v, k)
        assert np.isfinite(taken).all()  # every pixel's chosen window is one of its offered
        _same_bits(taken, v.take_reference(k))
        H = v.shape[0]
        for a, b in ((0, H), (0, 5), (H // 3, H // 3 + 7), (H - 2, H)):
            out = _both_window_major(v, a, b, -0.05)
            assert np.isfinite(out).sum() == v.start[b * v.shape[1]] - v.start[a * v.shape[1]]


def test_the_c_readers_are_the_same_on_any_number_of_threads(monkeypatch):
    require_native("volume")
    rng = np.random.default_rng(34)
    v = SparseVolume.pack(_random_volume(rng, 23, 31, 44))
    index = rng.integers(-44, 44, (23, 31))
    taken = v.take(index, kernel="native")
    major = v.window_major(2, 21, scale=-0.5, kernel="native")
    for threads in (1, 2, 3, 64):
        monkeypatch.setattr(volume, "thread_count", lambda: threads)
        _same_bits(v.take(index, kernel="native"), taken)
        _same_bits(v.window_major(2, 21, scale=-0.5, kernel="native"), major)


def test_the_c_path_calls_no_numba(monkeypatch):
    require_native("volume")
    rng = np.random.default_rng(35)
    v = SparseVolume.pack(_random_volume(rng, 9, 8, 20))
    index = rng.integers(-20, 20, (9, 8))
    taken, major = v.take(index, kernel="numba"), v.window_major(1, 7, scale=0.25, kernel="numba")

    def numba_called(*args, **kwargs):
        raise AssertionError("the C path called numba")

    monkeypatch.setattr(volume, "_take_kernel", numba_called)
    monkeypatch.setattr(volume, "_window_major_kernel", numba_called)
    monkeypatch.setattr(volume, "numba", None)
    _same_bits(v.take(index), taken)
    _same_bits(v.window_major(1, 7, scale=0.25), major)


def test_the_c_readers_check_what_they_read():
    require_native("volume")
    rng = np.random.default_rng(36)
    v = SparseVolume.pack(_random_volume(rng, 4, 5, 12))
    index = np.zeros((4, 5), np.int64)
    bad = {"mask": v.mask[..., :1].copy(), "start": v.start.astype(np.int32),
           "values": v.values.astype(np.float64)}
    for name, array in bad.items():
        broken = SparseVolume(v.shape, v.fill, **{**{"mask": v.mask, "start": v.start, "values": v.values},
                                                  name: array})
        with pytest.raises(ValueError, match=f"volume's {name}"):
            broken.take(index, kernel="native")
        with pytest.raises(ValueError, match=f"volume's {name}"):
            broken.window_major(0, 4, scale=1.0, kernel="native")
    strided = SparseVolume(v.shape, v.fill, v.mask, v.start, np.repeat(v.values, 2)[::2])
    with pytest.raises(ValueError, match="C-contiguous"):
        strided.take(index, kernel="native")
    with pytest.raises(ValueError, match="index must be"):  # as before, on both paths
        v.take(np.full((4, 5), 12), kernel="native")
    with pytest.raises(ValueError, match="kernel must be"):
        v.take(index, kernel="fortran")


def test_the_c_kernels_do_nothing_for_no_rows():
    from recon.native import call

    require_native("volume")
    out = np.full(6, 7.0, np.float32)
    mask, start, values = np.zeros(1, np.uint8), np.zeros(2, np.int64), np.zeros(1, np.float32)
    call("volume", "lfrig_take", mask, 1, start, values, np.zeros(1, np.int64), 0, 1, 1, -1.0, out, 2)
    call("volume", "lfrig_take", mask, 1, start, values, np.zeros(1, np.int64), 1, 0, 1, -1.0, out, 2)
    call("volume", "lfrig_window_major", mask, 1, start, values, 0, 0, 1, 1, 1.0, out, 2)
    assert (out == 7.0).all()


@pytest.mark.hci
def test_the_c_readers_give_numbas_bits_on_a_backgammon_estimate(monkeypatch):
    # every read of the volume in a whole backgammon estimate (default options): the C kernel's
    # output, as the estimate called it, against numba's on the same inputs
    from recon.entropy.estimate import estimate_disparity
    from recon.lf.io import read_lightfield

    require_native("volume")
    real_call, seen = volume.call, {"lfrig_take": 0, "lfrig_window_major": 0}

    def call(name, function, *args):
        real_call(name, function, *args)
        mask, _, start, values = args[:4]
        if function == "lfrig_take":
            index, K, fill, out = args[4], args[7], args[8], args[9]
            twin = np.empty_like(out)
            volume._take_kernel(mask, start, values, index, K, np.float32(fill), twin)
        else:
            a, W, scale, out = args[4], args[6], args[8], args[9]
            twin = np.empty_like(out)
            volume._window_major_kernel(mask, start, values, a, W, np.float32(scale), twin)
        _same_bits(out, twin, function)
        seen[function] += out.size

    monkeypatch.setattr(volume, "call", call)
    lf = read_lightfield(require_hci_scene(), grey=True)
    estimate_disparity(lf)
    assert seen["lfrig_take"] == 512 * 512  # the chosen windows' entropies
    assert seen["lfrig_window_major"] >= 512 * 512 * 77  # the joint search's penalty, band by band
