"""recon.entropy.regions.box_extreme: OpenCV's erosion and dilation where they give scipy's bits,
scipy's minimum and maximum filters (``mode="nearest"``) elsewhere."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from recon.entropy.regions import box_extreme


def _scipy(image, size, maximum):
    return (ndimage.maximum_filter if maximum else ndimage.minimum_filter)(image, size, mode="nearest")


def _assert_same(got, expected, message):
    assert got.dtype == expected.dtype and got.shape == expected.shape, message
    assert got.tobytes() == expected.tobytes(), message


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_box_extreme_is_scipys_on_any_map(dtype):
    """Random maps of 1x1 to 40x40 pixels, boxes of 1 to 49 (odd and even, wider than the map),
    ties, infinities, NaN and zeros of both signs: the bits of scipy's filters, also where
    OpenCV's would differ (NaN, -0.0: scipy's then)."""
    rng = np.random.default_rng(7)
    for trial in range(600):
        H, W = (int(v) for v in rng.integers(1, 41, 2))
        size = int(rng.integers(1, 50)) if trial % 2 else tuple(int(v) for v in rng.integers(1, 50, 2))
        a = rng.normal(size=(H, W)).astype(dtype)
        if trial % 3 == 0:
            a = np.round(a * 2) / 2  # ties
        a[rng.random((H, W)) < 0.05] = np.inf
        a[rng.random((H, W)) < 0.05] = -np.inf
        kind = trial % 5
        if kind == 1:
            a[rng.random((H, W)) < 0.03] = np.nan
        elif kind == 2:
            a[rng.random((H, W)) < 0.2] = -0.0
        else:
            a[a == 0] = 0.0
        for maximum in (False, True):
            _assert_same(box_extreme(a, size, maximum=maximum), _scipy(a, size, maximum),
                         f"trial {trial}, {a.shape}, box {size}, maximum {maximum}")


def test_box_extreme_on_the_estimators_maps():
    """A disparity-like map (the shapes of the boundary test's 3x3 and the occlusion box), with a
    view that is not contiguous, and other dtypes (scipy's path)."""
    rng = np.random.default_rng(3)
    d = np.cumsum(rng.normal(scale=0.1, size=(97, 131)), axis=1).astype(np.float32)
    for image in (d, d[::2, 1::3], d.T, d.astype(np.int32), d > 0):
        for size in (3, (37, 5), (4, 2), 63):
            for maximum in (False, True):
                _assert_same(box_extreme(image, size, maximum=maximum), _scipy(image, size, maximum),
                             f"{image.dtype} {image.shape}, box {size}")


def test_box_extreme_takes_opencv_where_it_is_exact(monkeypatch):
    """The fast path is the one taken on a clean float map, not on one with NaN or -0.0."""
    import cv2

    calls = []
    erode = cv2.erode
    monkeypatch.setattr(cv2, "erode", lambda *a, **k: calls.append(1) or erode(*a, **k))
    a = np.linspace(-1, 1, 60, dtype=np.float32).reshape(6, 10)
    box_extreme(a, 3, maximum=False)
    assert calls == [1]
    for bad in (np.nan, -0.0):
        b = a.copy()
        b[2, 3] = bad
        box_extreme(b, 3, maximum=False)
    assert calls == [1]
    with pytest.raises(ValueError, match="kernel"):
        box_extreme(a, 3, maximum=False, kernel="numba")
    _assert_same(box_extreme(a, 3, maximum=True, kernel="scipy"), _scipy(a, 3, True), "scipy's")
