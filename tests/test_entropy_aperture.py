"""The strip windows' aperture test (recon/entropy/aperture.py): a strip is offered only where the
centre view varies along it (a thin textureless pole matches at every disparity along it)."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy.aperture import NOISE_ABS_DIFF, along_strip_variation, informative_strips
from recon.entropy.matching import disparity_candidates, min_window_line_search
from recon.entropy.scenes import natural_texture
from recon.entropy.windows import STRIP_SHAPES


def test_along_strip_variation_is_the_mean_absolute_step_along_the_strip():
    image = np.zeros((5, 9))
    image[:, :] = np.arange(9) * 0.5  # a ramp along x: every step 0.5
    image[2, :] = 0.0  # one constant row
    horizontal = along_strip_variation(image, size=5, axis=1)
    vertical = along_strip_variation(image, size=5, axis=0)
    assert horizontal[0, 4] == pytest.approx(0.5) and horizontal[2, 4] == pytest.approx(0.0)
    assert horizontal[0, 0] == pytest.approx(0.5)  # cut at the image edge, still a mean of steps
    # Column 4 reads 2, 2, 0, 2, 2 down the strip around row 2: steps 0, 2, 2, 0.
    assert vertical[2, 4] == pytest.approx(1.0)
    assert vertical[2, 0] == pytest.approx(0.0)  # column 0 is zero in every row
    with pytest.raises(ValueError, match="odd and at least 3"):
        along_strip_variation(image, size=4, axis=1)


def test_a_vertical_strip_on_a_vertical_pole_is_not_informative():
    rng = np.random.default_rng(0)
    sigma = 0.002
    image = natural_texture((60, 60), seed=1)
    image[:, 26:34] = 0.9  # a thin bright pole, constant along y
    image = image + rng.normal(0, sigma, image.shape)
    sizes = (3, 5, 9, 15)
    ok = informative_strips(image, sizes=sizes, noise_sigma=sigma, factor=2.0)
    assert ok.shape == (60, 60, 2, len(sizes))
    pole = (slice(10, 50), slice(27, 33))
    # Vertical strips: the pole is noise along y (pure noise passes factor 2 at 7 % of 3-px strips,
    # 3 % of 5-px ones and hardly ever longer ones).
    assert ok[pole][..., 1, 0].mean() < 0.12 and ok[pole][..., 1, 1].mean() < 0.06
    assert ok[pole][..., 1, 2:].mean() < 0.02
    assert ok[pole][..., 0, 1:].mean() > 0.5  # horizontal strips reach the pole's edges
    texture = (slice(10, 50), slice(2, 20))
    assert ok[texture].mean() > 0.95  # a textured background varies along both
    assert informative_strips(image, sizes=sizes, noise_sigma=sigma, factor=0.0).all()
    # The estimator's default: a lower factor over a 31-px test strip gates the pole as surely.
    long = informative_strips(image, sizes=sizes, noise_sigma=sigma, factor=1.5, length=31)
    assert (long == long[..., :1]).all()  # every size is judged over the same 31 px
    assert long[pole][..., 1, :].mean() < 0.01 and long[texture].mean() > 0.95
    # The threshold is the noise's own mean absolute step times the factor.
    flat = np.random.default_rng(1).normal(0, sigma, (200, 200))
    share = informative_strips(flat, sizes=(15,), noise_sigma=sigma, factor=1.0).mean()
    assert 0.2 < share < 0.8  # pure noise sits at NOISE_ABS_DIFF * sigma
    # A 31-px test decides far more surely than the strip's own 5 px: pure noise passes factor 1.5
    # at about 13 % of 5-px strips, hardly ever over 31 px, while a texture of 4 sigma passes.
    short = informative_strips(flat, sizes=(5,), noise_sigma=sigma, factor=1.5).mean()
    longer = informative_strips(flat, sizes=(5,), noise_sigma=sigma, factor=1.5, length=31).mean()
    assert short > 0.05 and longer < 0.005
    texture_4 = flat + 4 * sigma * np.sin(np.arange(200) * 2 * np.pi / 8)[None, :]
    assert informative_strips(texture_4, sizes=(5,), noise_sigma=sigma, factor=1.5, length=31)[..., 0, 0].mean() > 0.95
    assert NOISE_ABS_DIFF == pytest.approx(1.1284, abs=1e-4)


def test_min_window_search_honours_the_allowed_windows():
    rng = np.random.default_rng(3)
    tex = natural_texture((40, 80), seed=5)
    U = V = 5
    views = np.zeros((U, V, 24, 40), np.float32)
    for u in range(U):  # a plane at disparity 2: view (u, v) shows the centre's q = p + 2 (du, dv)
        for v in range(V):
            y0, x0 = 8 + 2 * (u - 2), 20 + 2 * (v - 2)
            views[u, v] = tex[y0:y0 + 24, x0:x0 + 40]
    views += rng.normal(0, 0.001, views.shape).astype(np.float32)
    candidates = disparity_candidates(-3.0, 3.0, 0.25)
    windows = [(s, 5, s) for s in (0, *STRIP_SHAPES)]
    _, cost_all = min_window_line_search(views, candidates, windows=windows)
    allowed = np.zeros((24, 40, 3), bool)
    allowed[..., 0] = True
    _, cost_square = min_window_line_search(views, candidates, windows=windows, allowed=allowed)
    _, cost_ref = min_window_line_search(views, candidates, windows=windows[:1])
    np.testing.assert_array_equal(cost_square, cost_ref)
    assert (cost_all <= cost_square + 1e-7).all() and (cost_all < cost_square - 1e-4).any()
    with pytest.raises(ValueError, match="a window at every pixel"):
        min_window_line_search(views, candidates, windows=windows, allowed=np.zeros((24, 40, 3), bool))
