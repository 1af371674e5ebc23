"""The C median filter (recon/native/median.c) gives the bits of its numba twin
(recon.entropy.median._median_kernel) through median_filter_nearest, on float32 and float64 images
that reach every branch (one pixel, one row or one column, rows wider than a block of columns,
footprints larger than the image, even counts, ties, infinities and subnormals) and on the medians
of a whole backgammon estimate."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy import median
from recon.entropy.median import MEDIAN_COLUMNS, median_filter_nearest, median_filter_nearest_reference
from tests.conftest import require_hci_scene, require_native


def _same_bits(a: np.ndarray, b: np.ndarray, what: str = "") -> None:
    assert a.dtype == b.dtype and a.shape == b.shape, what
    assert np.array_equal(a.view(np.uint8), b.view(np.uint8)), what


def _both(image, **kw) -> np.ndarray:
    c = median_filter_nearest(image, kernel="native", **kw)
    _same_bits(c, median_filter_nearest(image, kernel="numba", **kw), str(kw))
    return c


def _image(rng, H, W, dtype, kind) -> np.ndarray:
    """(H, W) of ``dtype``: normal values (kind 0), few levels, many ties (1), or normal values with
    infinities of either sign, huge and subnormal values among them (2); no NaN and no -0.0 (those
    go to scipy on both paths)."""
    image = rng.standard_normal((H, W))
    if kind == 1:
        image = np.round(image * 2) / 2 + 0.125
    image = image.astype(dtype)
    if kind == 2:
        pick = rng.integers(0, 12, (H, W))
        tiny = np.finfo(dtype).smallest_subnormal
        image[pick == 0] = np.inf
        image[pick == 1] = -np.inf
        image[pick == 2] = np.finfo(dtype).max
        image[pick == 3] = tiny * rng.integers(1, 5, int((pick == 3).sum()))
        image[pick == 4] = -tiny
    return image


FOOTPRINTS = (np.ones((1, 1), bool), np.ones((3, 3), bool), np.ones((5, 5), bool), np.ones((1, 3), bool),
              np.ones((3, 1), bool), np.ones((4, 4), bool), np.ones((2, 5), bool), np.ones((40, 3), bool),
              np.ones((3, 300), bool), np.eye(5, dtype=bool), np.zeros((13, 13), bool))
FOOTPRINTS[-1][::3, ::3] = True  # the curvature cap's sparse footprint


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_c_median_gives_numbas_bits_on_random_images(dtype):
    require_native("median")
    rng = np.random.default_rng(61)
    shapes = ((1, 1), (1, 9), (11, 1), (2, 3), (7, 8), (23, 31), (5, MEDIAN_COLUMNS), (6, MEDIAN_COLUMNS + 1),
              (9, 2 * MEDIAN_COLUMNS + 37), (3, 3 * MEDIAN_COLUMNS - 1))
    compared = 0
    for trial, (H, W) in enumerate(shapes):
        for f, footprint in enumerate(FOOTPRINTS):
            image = _image(rng, H, W, dtype, (trial + f) % 3)
            out = _both(image, footprint=footprint)
            if (trial + f) % 4 == 0:  # and scipy's, the map both twins stand for
                _same_bits(out, median_filter_nearest_reference(image, footprint=footprint), "scipy")
            compared += out.size
        _both(image, size=3)
        _both(image, size=(1, 3))
    assert compared > 20_000


def test_the_c_median_gives_numbas_bits_on_random_footprints():
    require_native("median")
    rng = np.random.default_rng(62)
    for trial in range(40):
        H, W = int(rng.integers(1, 30)), int(rng.integers(1, 3 * MEDIAN_COLUMNS))
        footprint = rng.random((int(rng.integers(1, 10)), int(rng.integers(1, 10)))) < 0.5
        footprint.flat[int(rng.integers(footprint.size))] = True  # at least one sample
        image = _image(rng, H, W, (np.float32, np.float64)[trial % 2], trial % 3)
        _both(image, footprint=footprint)
        _both(image[:, ::-1], footprint=footprint)  # a strided view, made contiguous for both


def test_the_c_median_leaves_nan_and_negative_zero_to_scipy():
    # as before on both paths: images holding NaN or -0.0 never reach either kernel
    require_native("median")
    rng = np.random.default_rng(63)
    for special in (np.nan, -0.0):
        image = _image(rng, 12, 14, np.float32, 1)
        image[3, 4] = special
        image[7:9, 1:3] = 0.0
        out = _both(image, size=5)
        _same_bits(out, median_filter_nearest_reference(image, footprint=np.ones((5, 5), bool)))


def test_the_c_median_is_the_same_on_any_number_of_threads(monkeypatch):
    require_native("median")
    image = _image(np.random.default_rng(64), 37, 2 * MEDIAN_COLUMNS + 5, np.float64, 2)
    first = median_filter_nearest(image, size=5, kernel="native")
    for threads in (1, 2, 3, 64):
        monkeypatch.setattr(median, "thread_count", lambda: threads)
        _same_bits(median_filter_nearest(image, size=5, kernel="native"), first)


def test_the_c_path_calls_no_numba(monkeypatch):
    require_native("median")
    image = _image(np.random.default_rng(65), 19, 23, np.float32, 0)
    expected = median_filter_nearest(image, size=5, kernel="numba")

    def numba_called(*args, **kwargs):
        raise AssertionError("the C path called numba")

    monkeypatch.setattr(median, "_median_kernel", numba_called)
    monkeypatch.setattr(median, "numba", None)
    _same_bits(median_filter_nearest(image, size=5), expected)


def test_the_c_median_checks_its_kernel_name():
    require_native("median")
    with pytest.raises(ValueError, match="kernel must be"):
        median_filter_nearest(np.zeros((4, 4)), size=3, kernel="fortran")
    with pytest.raises(ValueError, match="kernel must be"):  # an image that scipy's filter takes
        median_filter_nearest(np.full((4, 4), np.nan), size=3, kernel="fortran")


def test_the_c_kernel_does_nothing_for_no_rows_or_samples():
    from recon.native import call

    require_native("median")
    out = np.full(4, 7.0, np.float32)
    image, d, pairs = np.zeros(4, np.float32), np.zeros(1, np.int64), np.zeros((0, 2), np.int64)
    call("median", "lfrig_median", image, 0, 0, 4, d, d, 1, pairs, 0, 0, out, 2)
    call("median", "lfrig_median", image, 0, 1, 0, d, d, 1, pairs, 0, 0, out, 2)
    call("median", "lfrig_median", image, 0, 1, 4, d, d, 0, pairs, 0, 0, out, 2)
    assert (out == 7.0).all()


@pytest.mark.hci
def test_the_c_median_gives_numbas_bits_on_a_backgammon_estimate(monkeypatch):
    # every median of a whole backgammon estimate (default options) that reaches the kernel: the C
    # kernel's output, as the estimate called it, against numba's on the same inputs
    from recon.entropy.estimate import estimate_disparity
    from recon.lf.io import read_lightfield

    require_native("median")
    real_call, seen = median.call, []

    def call(name, function, image, wide, H, W, dy, dx, n, pairs, n_pairs, rank, out, threads):
        real_call(name, function, image, wide, H, W, dy, dx, n, pairs, n_pairs, rank, out, threads)
        twin = np.empty_like(out)
        median._median_kernel(image, dy, dx, pairs, rank, twin)
        _same_bits(out, twin, f"{image.dtype} {n} samples")
        seen.append((image.dtype, n))

    monkeypatch.setattr(median, "call", call)
    lf = read_lightfield(require_hci_scene(), grey=True)
    estimate_disparity(lf)
    assert len(seen) >= 4 and (np.float32, 25) in seen  # the regions' and the confidence's 5x5 at least
