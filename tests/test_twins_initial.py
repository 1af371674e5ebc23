"""recon.entropy.initial: the compiled box downsampling gives its readable twin's values, bit for
bit, on the sizes and factors it takes and on those it hands to the twin."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy.initial import _downsample_kernel, downsample_views, downsample_views_reference


@pytest.mark.parametrize("factor", range(1, 10))
def test_downsample_views_equals_its_twin_bit_for_bit(factor):
    rng = np.random.default_rng(factor)
    for _ in range(12):
        U, V = rng.integers(1, 4, size=2)
        H, W = rng.integers(factor, 6 * factor + 9, size=2)  # rows/columns left over, results 1 px wide
        gray = rng.random((U, V, H, W), dtype=np.float32)
        fast, reference = downsample_views(gray, factor), downsample_views_reference(gray, factor)
        assert fast.dtype == np.float32 and fast.shape == reference.shape
        np.testing.assert_array_equal(fast.view(np.uint32), reference.view(np.uint32))


def test_the_kernel_itself_runs_on_a_view_the_size_of_a_lab_capture():
    # the capture's case (1198x906, factor 4) through the kernel, not through the twin
    rng = np.random.default_rng(7)
    gray = rng.random((1, 2, 906, 1198), dtype=np.float32)
    out = np.empty((1, 2, 226, 299), np.float32)
    _downsample_kernel(gray, 4, out)
    np.testing.assert_array_equal(out.view(np.uint32), downsample_views_reference(gray, 4).view(np.uint32))


def test_downsample_views_of_other_dtypes_and_layouts_is_the_twin():
    gray = np.random.default_rng(1).random((2, 2, 13, 17))
    np.testing.assert_array_equal(downsample_views(gray, 2), downsample_views_reference(gray, 2))
    view = gray.astype(np.float32)[:, :, :, ::-1]
    np.testing.assert_array_equal(downsample_views(view, 3), downsample_views_reference(view, 3))
