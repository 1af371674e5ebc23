"""Window shapes W1..W8 (+ strips) and their visible-viewpoint sets, checked on a rendered occluder."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy.cost import view_blocks
from recon.entropy.windows import (N_SHAPES, SET_BLOCKS, visible_view_mask, window_mask,
                                   window_rect)
from recon.synthetic import Layer, noise_texture, render


def test_side_windows_contain_centre_and_halve_the_square():
    for size in (3, 7, 15):
        r = size // 2
        assert window_mask(0, size).sum() == size * size
        for shape in range(1, 5):
            m = window_mask(shape, size)
            assert m[r, r] and m.sum() == size * (r + 1)
        for shape in range(5, 9):
            m = window_mask(shape, size)
            assert m[r, r] and m.sum() == (r + 1) ** 2
    assert window_rect(1, 5) == (-2, 2, -2, 0)  # W1 extends left
    assert window_rect(4, 5) == (0, 2, -2, 2)   # W4 extends down
    assert window_rect(9, 5) == (0, 0, -2, 2)   # row strip


def test_set_blocks_agree_with_view_masks():
    blocks = view_blocks((9, 9))
    for shape in range(N_SHAPES):
        expected = visible_view_mask(shape, (9, 9))
        assert np.array_equal(SET_BLOCKS[shape][blocks], expected)
    assert visible_view_mask(0, (9, 9)).all()
    assert visible_view_mask(1, (9, 9)).sum() == 45


def test_bad_window_arguments_raise():
    with pytest.raises(ValueError):
        window_rect(11, 5)
    with pytest.raises(ValueError):
        window_rect(1, 4)


@pytest.mark.parametrize("side", ["right", "left", "below", "above"])
def test_visible_set_sees_a_background_pixel_next_to_an_occluder(side):
    """Render a closer half-plane on one side of a background pixel; every view of the set of the
    window that extends away from the occluder must see the pixel, and some view outside must not."""
    n, back, front = 48, -0.5, 1.0
    c = n // 2
    tests = {"right": (lambda y, x: x >= c + 2, (c, c), 1),
             "left": (lambda y, x: x < c - 1, (c, c), 2),
             "below": (lambda y, x: y >= c + 2, (c, c), 3),
             "above": (lambda y, x: y < c - 1, (c, c), 4)}
    mask, (py, px), shape = tests[side]
    bg = Layer(noise_texture((n, n), seed=3), back)
    fg = Layer(noise_texture((n, n), seed=4, contrast=0.8), front, mask=mask)
    both, _ = render([bg, fg])
    only_bg, _ = render([bg])
    U, V = 9, 9
    seen = np.zeros((U, V), bool)
    for u in range(U):
        for v in range(V):
            y, x = py - (u - 4) * back, px - (v - 4) * back
            yi, xi = int(round(y)), int(round(x))
            seen[u, v] = abs(both.views[u, v, yi, xi] - only_bg.views[u, v, yi, xi]) < 1e-6
    visible = visible_view_mask(shape, (U, V))
    assert seen[visible].all()
    assert not seen[~visible].all()


def test_curvature_size_cap_is_the_same_on_any_number_of_threads():
    """The cap made with a size's box filters to a thread (2 to 5 threads) is the one thread's, bit
    for bit: with and without unmeasured pixels and the noise tolerance, on a map with creases and
    noise, a tiny one and one size alone."""
    from recon.entropy.windows import curvature_size_cap

    rng = np.random.default_rng(4)
    y, x = np.mgrid[:70, :90]
    layers = (np.abs(x - 45) * 0.03 + np.where(y > 30, 0.4, 0.0) + rng.normal(scale=0.02, size=x.shape))
    layers = layers.astype(np.float32)
    measured = rng.random(layers.shape) > 0.2
    measured[10:30, 20:50] = False
    initial = layers + rng.normal(scale=0.05, size=layers.shape).astype(np.float32)
    cases = [dict(), dict(measured=measured), dict(measured=measured, initial=initial, noise_factor=2.0)]
    for sizes in ((3, 5, 7, 9, 11, 13, 15), (5,), (3, 9)):
        for image in (layers, layers[:4, :3]):
            for case in cases:
                case = {k: (v[:image.shape[0], :image.shape[1]] if isinstance(v, np.ndarray) else v)
                        for k, v in case.items()}
                one = curvature_size_cap(image, sizes, tolerance=0.01, threads=1, **case)
                assert one.dtype == np.int64 and set(np.unique(one)) <= set(sizes)
                if len(sizes) > 2 and image is layers:
                    assert len(np.unique(one)) > 1
                for threads in (2, 3, 5):
                    np.testing.assert_array_equal(curvature_size_cap(image, sizes, tolerance=0.01, threads=threads,
                                                                     **case), one)
