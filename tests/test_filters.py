"""recon.entropy.filters gives scipy.ndimage's bytes, and recon.entropy.laplace spsolve's, on inputs
that reach every edge: tiny images, windows longer than the image, both modes, both float types,
NaN and inf (which go to scipy), and masks whose distances reach thousands of pixels."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from recon.entropy import filters, laplace
from tests.conftest import require_native, use_native_build

ROOT = Path(__file__).resolve().parents[1]


def same(a: np.ndarray, b: np.ndarray) -> bool:
    return (a.dtype == b.dtype and a.shape == b.shape
            and np.array_equal(np.ascontiguousarray(a).view(np.uint8), np.ascontiguousarray(b).view(np.uint8)))


def images(seed: int, count: int = 120):
    """Random (H, W) float32 / float64 images, 1-29 px a side, over six decades, some with NaN and inf."""
    rng = np.random.default_rng(seed)
    for i in range(count):
        H, W = (int(v) for v in rng.integers(1, 30, 2))
        image = (rng.normal(size=(H, W)) * 10 ** rng.uniform(-3, 3)).astype((np.float32, np.float64)[i % 2])
        if i % 5 == 0:
            image[rng.random(image.shape) < 0.1] = np.nan
        if i % 7 == 0:
            image[rng.random(image.shape) < 0.1] = -np.inf
        yield rng, image


@pytest.mark.parametrize("mode", ["nearest", "reflect"])
def test_the_uniform_filters_give_scipys_bytes(mode):
    require_native("filters")
    for rng, image in images(1):
        size = int(rng.integers(1, 40))  # up to longer than the image: the extension repeats
        for axis in (0, 1, -1, -2):
            assert same(filters.uniform_filter1d(image, size, axis=axis, mode=mode, kernel="native"),
                        ndimage.uniform_filter1d(image, size, axis=axis, mode=mode)), (image.shape, size, axis)
        box = size if rng.random() < 0.5 else tuple(int(v) for v in rng.integers(1, 9, 2))
        assert same(filters.uniform_filter(image, box, mode=mode, kernel="native"),
                    ndimage.uniform_filter(image, box, mode=mode)), (image.shape, box)


def test_the_uniform_filter_on_a_whole_image_and_the_kernels_plain_loops(monkeypatch, tmp_path):
    require_native("filters")
    rng = np.random.default_rng(2)
    image = rng.random((512, 517)).astype(np.float32)
    wide = rng.normal(size=(300, 211))
    for flags in ((), ("-mno-avx512f", "-mno-avx2", "-mno-avx")):
        if flags:
            use_native_build("filters", monkeypatch, tmp_path, flags=flags)
        for picture in (image, wide):
            for size in (3, 5, 31):
                for mode in ("nearest", "reflect"):
                    assert same(filters.uniform_filter(picture, size, mode=mode, kernel="native"),
                                ndimage.uniform_filter(picture, size, mode=mode)), (flags, size, mode)


def test_the_chessboard_distance_gives_scipys_bytes():
    rng = np.random.default_rng(4)
    for _ in range(150):
        H, W = (int(v) for v in rng.integers(1, 40, 2))
        mask = rng.random((H, W)) < rng.uniform(0.3, 1.0)
        mask.flat[rng.integers(0, mask.size)] = False
        assert same(filters.chessboard_distance(mask), ndimage.distance_transform_cdt(mask, metric="chessboard"))
    for H, W, zeros in ((512, 512, 1), (1500, 2000, 3), (1500, 2000, 3000), (3000, 40, 1)):
        mask = np.ones((H, W), bool)
        mask[rng.integers(0, H, zeros), rng.integers(0, W, zeros)] = False  # distances up to ~2500 px
        assert same(filters.chessboard_distance(mask), ndimage.distance_transform_cdt(mask, metric="chessboard"))


def test_a_filter_can_fail():
    # the comparison sees one value off by one unit in the last place
    image = np.random.default_rng(5).random((20, 20))
    ours = filters.uniform_filter(image, 5)
    ours[3, 4] = np.nextafter(ours[3, 4], 2.0)
    assert not same(ours, ndimage.uniform_filter(image, 5))


def test_the_kernel_argument_is_checked():
    for call in (lambda: filters.uniform_filter(np.zeros((3, 3)), 3, kernel="numba"),
                 lambda: filters.chessboard_distance(np.zeros((3, 3), bool), kernel="C")):
        with pytest.raises(ValueError, match="kernel must be"):
            call()


def test_the_laplace_solve_gives_spsolves_bytes():
    import scipy.sparse.linalg

    from recon.entropy.refine import _laplace_system

    rng = np.random.default_rng(6)
    for trial in range(150):
        H, W = (int(v) for v in rng.integers(1, 40, 2))
        values = rng.normal(size=(H, W)).astype(np.float32).astype(np.float64)
        holes = rng.random((H, W)) < rng.uniform(0.05, 0.97)
        if trial % 10 == 0:
            values[rng.random((H, W)) < 0.05] = np.nan
        if not holes.any() or holes.all():
            continue
        ys, xs = np.nonzero(holes)
        A, b = _laplace_system(values, holes, ys, xs)
        data, indices, indptr, rhs = laplace.laplace_system(values, holes, ys, xs)
        csc = A.tocsc()
        assert same(csc.indptr, indptr) and same(csc.indices, indices) and same(csc.data, data) and same(b, rhs)
        assert same(laplace.solve(data, indices, indptr, rhs), scipy.sparse.linalg.spsolve(csc, b)), trial


def test_the_laplace_solve_loads_no_scipy_package():
    probe = ("import sys, numpy as np\n"
             "from recon.entropy import laplace\n"
             "holes = np.zeros((9, 9), bool); holes[3:6, 2:7] = True\n"
             "values = np.add.outer(np.arange(9.0), 2 * np.arange(9.0))\n"
             "ys, xs = np.nonzero(holes)\n"
             "x = laplace.solve(*laplace.laplace_system(values, holes, ys, xs))\n"
             "assert laplace._gssv() is not None\n"
             "assert np.allclose(x, values[ys, xs], atol=1e-9), x\n"  # a plane is reproduced
             "print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))\n")
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
