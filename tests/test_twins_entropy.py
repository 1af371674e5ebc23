"""recon.entropy.entropy: the matching entropy's terms, and the compiled window choice gives its
readable twin's."""

from __future__ import annotations

import numpy as np
import pytest

from recon.entropy import entropy
from recon.entropy.entropy import matching_entropy_reference, select_windows, select_windows_reference
from recon.entropy.labels import OCCLUDED, OCCLUDING, SMOOTH, TEXTURE
from recon.entropy.volume import SparseVolume
from kernel_inputs import seeded


def test_matching_entropy_terms():
    grey = np.zeros((9, 9), np.int64)
    disp = np.zeros((9, 9), np.int64)
    labels = np.full((9, 9), TEXTURE, np.uint8)
    # constant window: all terms zero
    assert matching_entropy_reference(grey, disp, labels, 4, 4, 0, 3, alpha1=1, alpha2=1) == 0
    # two equally likely grey levels: ln 2 of texture richness
    grey[:, 4:] = 1
    e = matching_entropy_reference(grey, disp, labels, 4, 4, 0, 9, alpha1=1, alpha2=0)
    np.testing.assert_allclose(e, -(4 / 9 * np.log(4 / 9) + 5 / 9 * np.log(5 / 9)))
    # the same split in disparity cancels it
    disp[:, 4:] = 1
    assert abs(matching_entropy_reference(grey, disp, labels, 4, 4, 0, 9, alpha1=1, alpha2=0)) < 1e-12
    # mismatched pixels lower the score of an occluded pixel's window
    labels[:, 6:] = OCCLUDING
    labels[4, 4] = OCCLUDED
    with_occ = matching_entropy_reference(grey, disp, labels, 4, 4, 0, 9, alpha1=1, alpha2=1)
    assert with_occ < 0


def _assert_select_windows_matches_reference(grey, disp, labels):
    kw = dict(sizes=(3, 5, 7), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0)
    s_ref, z_ref, e_ref = select_windows_reference(grey, disp, labels, **kw)
    s_f, z_f, e_f = select_windows(grey, disp, labels, **kw)
    np.testing.assert_allclose(e_f, e_ref, atol=1e-5)
    assert np.array_equal(s_f, s_ref) and np.array_equal(z_f, z_ref)


def test_select_windows_fast_matches_reference():
    rng = seeded()
    grey = rng.integers(0, 16, (14, 12))
    disp = np.where(np.arange(12)[None] < 6, 0, 3) + rng.integers(0, 2, (14, 12))
    labels = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH], (14, 12)).astype(np.uint8)
    _assert_select_windows_matches_reference(grey, disp, labels)


def test_select_windows_with_many_bins_matches_reference():
    # 256 grey levels and 40 disparity bins: the three histograms of a window lie one after the
    # other in one array, and after a window only the bins its pixels took are cleared
    rng = seeded()
    labels = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH], (17, 19)).astype(np.uint8)
    _assert_select_windows_matches_reference(rng.integers(0, 256, (17, 19)),
                                             rng.integers(0, 40, (17, 19)), labels)


def test_select_windows_with_bins_beyond_16_bits_matches_reference():
    # 2 n_grey + n_disp > 2**16: the bins are held in 32 bits, not 16
    rng = seeded()
    labels = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH], (17, 19)).astype(np.uint8)
    grey = rng.integers(0, 256, (17, 19))
    grey[0, 0] = 40_000
    _assert_select_windows_matches_reference(grey, rng.integers(0, 40, (17, 19)), labels)


def test_window_avoids_a_disparity_edge():
    rng = seeded()
    grey = rng.integers(0, 8, (31, 31))  # texture whose grey entropy saturates (ln 8)
    disp = np.zeros((31, 31), np.int64)
    disp[:, 16:] = 5  # a depth edge two pixels right of the centre column 14
    labels = np.full((31, 31), TEXTURE, np.uint8)
    labels[:, 14] = OCCLUDED
    shape, size, _ = select_windows(grey, disp, labels, sizes=(3, 5, 7, 9, 11, 13, 15),
                                    alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0)
    assert shape[15, 14] in (1, 5, 7)  # a window that extends left, away from the edge
    assert size[15, 14] >= 11
    assert size[15, 12] <= 7  # square windows shrink near the edge (it is 4 px away)
    assert size[15, 3] >= 11  # and large far from it


SIZES = (3, 5, 7, 9, 11, 13, 15)


def _window_inputs(rng, H=44, W=43):
    """Grey and disparity bins, labels in patches (windows straddle them), a two-layer map with a
    slant, side radii and size caps: every window rule of select_windows at work."""
    y, x = np.mgrid[0:H, 0:W]
    layers = np.where(x + y // 3 < 20, 0.0, 1.0) + 0.004 * x
    grey = rng.integers(0, 6, (H, W)) + (x > 25) * 3  # few levels: counts grow, sums round
    disp = (layers * 10).astype(np.int64) + rng.integers(0, 3, (H, W))
    patch = rng.choice([OCCLUDING, OCCLUDED, TEXTURE, SMOOTH, TEXTURE], (H // 4 + 1, W // 4 + 1))
    labels = patch.repeat(4, 0).repeat(4, 1)[:H, :W].astype(np.uint8)
    labels[rng.random((H, W)) < 0.1] = OCCLUDED
    return grey, disp, labels, dict(
        sizes=SIZES, alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0,
        side_radius=rng.integers(0, 9, (H, W)), layers=layers.astype(np.float32), layer_gap=0.25,
        max_size=rng.choice(SIZES, (H, W)))


@pytest.mark.parametrize("variant", ["default", "no strips", "no layers"])
def test_unclipped_windows_sum_as_the_clipped_ones(monkeypatch, variant):
    # Pixels whose windows the image does not clip add their pixels along ring_order; summed the
    # clipped way instead (every pixel treated as near the border), every bit stays.
    grey, disp, labels, kw = _window_inputs(seeded())
    if variant == "no strips":
        kw["strips"] = False
    if variant == "no layers":
        kw["layers"] = None
    ring = select_windows(grey, disp, labels, return_all=True, **kw)
    monkeypatch.setattr(entropy, "_ring_margin", lambda sizes: 10 ** 6)
    clipped = select_windows(grey, disp, labels, return_all=True, **kw)
    assert np.isfinite(ring[3]).sum() > 10 * grey.size  # many windows offered
    for a, b in zip(ring, clipped):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_sparse_entropies_are_the_packed_dense_ones():
    grey, disp, labels, kw = _window_inputs(seeded(), H=23, W=29)
    dense = select_windows(grey, disp, labels, return_all=True, **kw)
    sparse = select_windows(grey, disp, labels, return_all="sparse", **kw)
    for a, b in zip(dense[:3], sparse[:3]):
        assert a.tobytes() == b.tobytes()
    packed, got = SparseVolume.pack(dense[3]), sparse[3]
    assert got.shape == packed.shape and got.fill == packed.fill
    assert np.array_equal(got.mask, packed.mask) and np.array_equal(got.start, packed.start)
    assert got.values.dtype == np.float32 and got.values.tobytes() == packed.values.tobytes()
    assert got.rows(0, 23).tobytes() == dense[3].tobytes()
    with pytest.raises(ValueError, match="return_all"):
        select_windows(grey, disp, labels, return_all="dense", **kw)


def test_sparse_entropies_in_bands_of_rows_are_the_whole_images(monkeypatch):
    # bands of 2 rows (and one of 1 at the end) give the one band's volume and maps bit for bit
    grey, disp, labels, kw = _window_inputs(seeded(), H=23, W=29)
    whole = select_windows(grey, disp, labels, return_all="sparse", **kw)
    monkeypatch.setattr(entropy, "SELECT_BAND_MIB", 2 * 29 * 77 * 4 / 2 ** 20)
    banded = select_windows(grey, disp, labels, return_all="sparse", **kw)
    for a, b in zip(whole[:3], banded[:3]):
        assert a.tobytes() == b.tobytes()
    for name in ("mask", "start", "values"):
        assert getattr(whole[3], name).tobytes() == getattr(banded[3], name).tobytes()


def test_select_windows_refuses_negative_bins():
    grey = np.zeros((9, 9), np.int64)
    disp = np.zeros((9, 9), np.int64)
    disp[4, 4] = -1  # a disparity below the bins' origin
    labels = np.full((9, 9), TEXTURE, np.uint8)
    with pytest.raises(ValueError, match="bin indices >= 0"):
        select_windows(grey, disp, labels, sizes=(3, 5), alpha1=1.0, alpha2_occlusion=1.0, alpha2_other=0.0)
