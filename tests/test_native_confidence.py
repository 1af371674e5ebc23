"""The C kernel of recon/native/confidence.c against its reference (scipy's distance transform),
byte for byte: recon.entropy.calibration.jump_distance."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy.calibration import JUMP_PX, JUMP_REACH_PX, jump_distance, jump_distance_reference
from tests.conftest import require_native, use_native_build

pytestmark = pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")


@pytest.fixture(autouse=True)
def _native():
    require_native("confidence")


def _maps(rng):
    """Disparity-like maps of 1x1 to 60x70 pixels: smooth with steps, pure noise (jumps everywhere),
    flat (none), steps of exactly JUMP_PX, NaN and infinities."""
    for trial in range(300):
        H, W = (int(v) for v in rng.integers(1, 61, 2)) if trial % 4 else (int(rng.integers(1, 4)), 70)
        kind = trial % 6
        if kind == 0:
            d = rng.normal(size=(H, W))
        elif kind == 1:
            d = np.zeros((H, W))
        elif kind == 2:  # steps of exactly the threshold and just over it
            d = np.cumsum(rng.choice([0.0, JUMP_PX, np.nextafter(JUMP_PX, 1)], size=(H, W)), axis=1)
        else:
            d = np.cumsum(rng.normal(scale=0.05, size=(H, W)), axis=0)
            d[rng.random((H, W)) < 0.01 * kind] += 1.0
        if trial % 5 == 0:
            d[rng.random((H, W)) < 0.03] = np.nan
        if trial % 7 == 0:
            d[rng.random((H, W)) < 0.03] = np.inf
        yield d


def test_jump_distance_c_gives_the_references_bits():
    rng = np.random.default_rng(11)
    for i, d in enumerate(_maps(rng)):
        expected = jump_distance_reference(d)
        got = jump_distance(d, kernel="native")
        assert got.dtype == np.float64 and got.tobytes() == expected.tobytes(), (i, d.shape)
        H = d.shape[0]
        r0 = int(rng.integers(0, H))
        r1 = int(rng.integers(r0, H + 1))
        part = jump_distance(d, rows=(r0, r1), kernel="native")
        assert part.shape == (r1 - r0, d.shape[1]) and part.tobytes() == expected[r0:r1].tobytes(), (i, r0, r1)
        assert jump_distance(d, rows=(r0, r1), kernel="numba").tobytes() == expected[r0:r1].tobytes()


def test_jump_distance_reaches_its_cap_exactly():
    """One jump in a wide flat map: distances sqrt(dy^2 + dx^2) up to the cap and the cap beyond,
    from brute force over the marked pixels."""
    d = np.zeros((41, 45))
    d[20, 22] = 1.0  # marks itself and its 4 neighbours
    got = jump_distance(d, kernel="native")
    ys, xs = np.array([20, 19, 21, 20, 20]), np.array([22, 22, 22, 21, 23])
    y, x = np.mgrid[:41, :45]
    brute = np.sqrt(((y[..., None] - ys) ** 2 + (x[..., None] - xs) ** 2).min(axis=-1).astype(np.float64))
    np.testing.assert_array_equal(got, np.minimum(brute, JUMP_REACH_PX))
    assert (got == JUMP_REACH_PX).any() and (got < JUMP_REACH_PX).any()


@pytest.mark.parametrize("flags", [("-mno-avx512f",), ("-mno-avx2", "-mno-avx512f")])
def test_jump_distance_portable_build_gives_the_same_bits(monkeypatch, tmp_path, flags):
    """Built as for a CPU without AVX-512 (or AVX2), the same bits."""
    use_native_build("confidence", monkeypatch, tmp_path, flags=flags)
    rng = np.random.default_rng(12)
    for i, d in enumerate(_maps(rng)):
        if i % 3 == 0:
            assert jump_distance(d, kernel="native").tobytes() == jump_distance_reference(d).tobytes(), i
    from recon.entropy.calibration import neighbours_and_slope

    for i, d in enumerate(_finite_maps(rng)):
        if i % 3 == 0:
            got, expected = (neighbours_and_slope(d, (0, d.shape[0]), kernel=k) for k in ("native", "numba"))
            assert all(g.tobytes() == e.tobytes() for g, e in zip(got, expected)), i


def _finite_maps(rng):
    """Finite maps of 1x1 to 50x60 pixels: noise, steps of exactly TOLERANCE_PX (0 and 0.07), large
    and tiny values, a flat one."""
    from recon.entropy.calibration import TOLERANCE_PX

    for trial in range(300):
        H, W = int(rng.integers(1, 51)), int(rng.integers(1, 61))
        if trial % 9 == 0:
            H, W = (1, W) if trial % 2 else (H, 1)
        kind = trial % 4
        if kind == 0:
            d = rng.normal(size=(H, W))
        elif kind == 1:
            d = rng.choice([0.0, TOLERANCE_PX, -TOLERANCE_PX, 2 * TOLERANCE_PX], size=(H, W))
        elif kind == 2:
            d = rng.normal(size=(H, W)) * 10.0 ** rng.integers(-300, 300, size=(H, W)).astype(np.float64)
        else:
            d = np.full((H, W), 0.3)
        yield d


def test_neighbours_and_slope_c_gives_numpys_bits():
    """The C neighbours and slope of any rows of a finite map equal numpy's (neighbour_agreement,
    np.gradient, np.hypot) byte for byte, and so does the slope alone (the heuristic's
    ``slope_rows``); a map with a NaN or an infinity takes numpy's."""
    from recon.entropy.calibration import neighbours_and_slope
    from recon.entropy.confidence import slope_rows

    rng = np.random.default_rng(13)
    for i, d in enumerate(_finite_maps(rng)):
        H = d.shape[0]
        r0 = int(rng.integers(0, H))
        r1 = int(rng.integers(r0, H + 1)) if i % 3 else H
        r0 = 0 if i % 3 == 0 else r0
        got = neighbours_and_slope(d, (r0, r1), kernel="native")
        expected = neighbours_and_slope(d, (r0, r1), kernel="numba")
        for name, g, e in zip(("nearest", "agreeing", "slope"), got, expected):
            assert g.dtype == e.dtype and g.shape == e.shape, (i, name)
            assert g.tobytes() == e.tobytes(), (i, name, d.shape, r0, r1)
        slope = slope_rows(d, r0, r1, kernel="native")  # the heuristic's: the slope alone
        assert slope.tobytes() == expected[2].tobytes() == slope_rows(d, r0, r1, kernel="numba").tobytes(), i
    d = rng.normal(size=(9, 11))
    for bad in (np.nan, np.inf):
        d[4, 5] = bad
        got, expected = neighbours_and_slope(d, (2, 8)), neighbours_and_slope(d, (2, 8), kernel="numba")
        assert all(g.tobytes() == e.tobytes() for g, e in zip(got, expected))
