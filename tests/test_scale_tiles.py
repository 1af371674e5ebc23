"""Tiles of the centre view with a halo: the plan partitions the image, and the stitched baseline
equals the untiled one (in this process and on a local Dask cluster)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from recon.methods import run_method
from recon.scale import ScaleError
from recon.scale.tiles import (
    TILE_RULES,
    Tile,
    crop_lightfield,
    max_view_offset,
    plan_tiles,
    stitch,
    tile_rule,
    tiled_disparity,
)
from recon.synthetic import occluding_square_scene

# The baseline's tiles are exact: each view's sampling fraction depends only on its shift, not on
# where the crop starts, and every window sum is taken directly in a fixed order.


@pytest.fixture(scope="module")
def scene():
    lf, _ = occluding_square_scene(48, seed=11, back=-0.6, front=1.1, grid=(5, 5))
    return lf


@pytest.fixture(scope="module")
def untiled(scene):
    return run_method("baseline", scene, window=5, step=0.05).disparity


@pytest.mark.parametrize("shape,tile,halo", [((48, 48), 16, 5), ((37, 50), 12, 7), ((20, 9), 64, 3), ((5, 5), 1, 0)])
def test_plan_partitions_the_image_and_crops_hold_the_halo(shape, tile, halo):
    tiles = plan_tiles(shape, tile=tile, halo=halo)
    cover = np.zeros(shape, int)
    for t in tiles:
        top, bottom, left, right = t.core
        assert 0 < bottom - top <= tile and 0 < right - left <= tile
        cover[top:bottom, left:right] += 1
        assert t.crop == (max(top - halo, 0), min(bottom + halo, shape[0]), max(left - halo, 0),
                          min(right + halo, shape[1]))
        rows, cols = t.inner
        assert (rows.stop - rows.start, cols.stop - cols.start) == (bottom - top, right - left)
    assert (cover == 1).all()
    sizes = {t.core[1] - t.core[0] for t in tiles}
    assert max(sizes) - min(sizes) <= 1  # balanced, no sliver tile


def test_plan_rejects_bad_sizes():
    with pytest.raises(ValueError, match="tile size"):
        plan_tiles((10, 10), tile=0, halo=2)
    with pytest.raises(ValueError, match="halo"):
        plan_tiles((10, 10), tile=4, halo=-1)


def test_crop_keeps_every_view_at_the_same_rectangle(scene):
    tile = plan_tiles(scene.image_shape, tile=20, halo=6)[4]
    crop = crop_lightfield(scene, tile)
    top, bottom, left, right = tile.crop
    assert crop.grid_shape == scene.grid_shape
    np.testing.assert_array_equal(crop.views, scene.views[:, :, top:bottom, left:right])
    assert crop.views.flags.c_contiguous and crop.disparity_range == scene.disparity_range


def test_stitch_puts_cores_back_and_checks_shapes():
    shape = (9, 11)
    whole = np.arange(99, dtype=np.float32).reshape(shape)
    tiles = plan_tiles(shape, tile=4, halo=2)
    crops = [whole[t.crop[0]:t.crop[1], t.crop[2]:t.crop[3]] for t in tiles]
    np.testing.assert_array_equal(stitch(shape, tiles, crops), whole)
    with pytest.raises(ScaleError, match="keep the crop's size"):
        stitch(shape, tiles[:1], [np.zeros((1, 1), np.float32)])


def test_baseline_halo_covers_window_and_largest_shift(scene):
    rule = tile_rule("baseline")
    options = rule.resolve(scene, {"window": 9})
    assert options["disparity_range"] == scene.disparity_range
    max_d = max(abs(v) for v in scene.disparity_range)
    assert rule.halo_px(scene, options) == 9 // 2 + int(np.ceil(max_d * max_view_offset(scene.grid_shape))) + 1
    assert rule.exact and TILE_RULES["entropy"].exact


def test_entropy_halo_covers_its_largest_window_and_shift(scene):
    """The entropy rule reads the estimator's own defaults (so it follows when they change)."""
    from recon.entropy import DEFAULTS

    rule = tile_rule("entropy")
    options = rule.resolve(scene, {})
    assert options["disparity_range"] == scene.disparity_range
    shift = max(abs(v) for v in scene.disparity_range) * max_view_offset(scene.grid_shape)
    assert rule.halo_px(scene, options) >= max(DEFAULTS.window_sizes) // 2 + 2 * shift


def test_unknown_method_has_no_tiling_rule():
    with pytest.raises(ScaleError, match="no tiling rule"):
        tile_rule("no-such-method")


@pytest.mark.parametrize("tile", [16, 13])
def test_tiled_baseline_equals_untiled(scene, untiled, tile):
    result = tiled_disparity(scene, method="baseline", options={"window": 5, "step": 0.05}, tile=tile)
    assert len(result.tiles) > 4
    np.testing.assert_array_equal(result.disparity, untiled)


def test_a_halo_too_small_shows_at_the_seams(scene, untiled):
    """The equality above is not luck: with only the window's radius as halo (no room for the views'
    shift) the seams are wrong."""
    result = tiled_disparity(scene, method="baseline", options={"window": 5, "step": 0.05}, tile=16, halo=2)
    error = np.abs(result.disparity - untiled)
    assert (error > 0.01).sum() > 50 and error.max() > 0.5
    wrong = error > 1e-6
    seams = np.zeros(scene.image_shape, bool)
    for t in result.tiles:
        top, bottom, left, right = t.core
        ring = np.ones((bottom - top, right - left), bool)
        ring[6:-6, 6:-6] = False
        seams[top:bottom, left:right] |= ring
    assert not (wrong & ~seams).any()  # away from the seams the tiles are still right


def test_tiled_baseline_on_a_local_cluster_equals_untiled(scene, untiled):
    import distributed
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,  # in-process, no ports
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        seen = []
        result = tiled_disparity(scene, method="baseline", options={"window": 5, "step": 0.05}, tile=16,
                                 client=client, progress=lambda fraction, message: seen.append(fraction))
    np.testing.assert_array_equal(result.disparity, untiled)
    assert len(seen) == len(result.tiles) and seen == sorted(seen) and seen[-1] == 1.0
    assert result.describe()["halo_px"] == result.halo and result.describe()["exact"] is True


def test_tile_dataclass_inner_is_relative_to_the_crop():
    t = Tile(index=0, core=(10, 20, 5, 15), crop=(7, 23, 2, 18))
    assert t.inner == (slice(3, 13), slice(3, 13))


# Tiled entropy equals untiled: every whole-image statistic is computed once and passed to the
# tiles, the whole-image solves (hole fill of the initial estimate, TV refinement) run once on the
# stitched maps, window sums are exact integer sums and the centroid correction sums each window
# directly. Measured bit-identical on the scene suite (128 px, tiles of 48); the tolerance leaves
# room for the numba fast-math kernels' rounding.
ENTROPY_ROUNDING = 1e-4


@pytest.fixture(scope="module")
def boxes():
    """Flat boxes over a textured wall: flat patches, black holes and occlusions, i.e. every
    whole-image step of the estimator has work to do. 224 px: the entropy halo (140 px with the
    strips' 31-px aperture test, the weak-texture filter's window test and warp and the boundary
    test's rays) must leave the corner tile of 75 px a real crop of the image."""
    from recon.entropy.scenes import make_scene

    return make_scene("boxes", size=224, seed=0).lf


def test_tiled_entropy_equals_untiled(boxes):
    from recon.entropy import estimate_disparity

    whole = estimate_disparity(boxes)
    assert whole.info["holes"].any() and (whole.labels == 3).any()  # the global steps matter here
    seen = []
    result = tiled_disparity(boxes, method="entropy", tile=75, progress=lambda fraction, message: seen.append(fraction))
    assert len(result.tiles) == 9 and result.exact
    corner = result.tiles[0].crop
    assert corner[1] < boxes.image_shape[0] and corner[3] < boxes.image_shape[1]  # a real crop
    np.testing.assert_allclose(result.disparity, whole.disparity, rtol=0, atol=ENTROPY_ROUNDING)
    assert len(seen) == 18 and seen[-1] == 1.0  # two rounds of tiles
    assert_same_maps(result.extras, whole)


#: The maps of an :class:`recon.entropy.EntropyResult` a tiled run must reproduce.
ENTROPY_MAPS = ("disparity", "initial_disparity", "matched_disparity", "labels", "window_size", "window_shape",
                "view_set", "entropy", "cost", "confidence")


def assert_same_maps(tiled, whole):
    """Every map of ``tiled`` (the tiled run's result) equals ``whole``'s bit for bit, dtype included:
    the confidence and the maps it is computed from, and the arrays and numbers of ``info``."""
    assert tiled is not None and tiled.confidence is not None
    for name in ENTROPY_MAPS:
        a, b = getattr(tiled, name), getattr(whole, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert tiled.info.keys() == whole.info.keys()
    for name, value in whole.info.items():
        if isinstance(value, np.ndarray):
            assert tiled.info[name].dtype == value.dtype, name
            np.testing.assert_array_equal(tiled.info[name], value, err_msg=name)
        else:
            assert tiled.info[name] == value, name


@pytest.mark.parametrize("name, preset", [("thin", None), ("slants", "paper")])
def test_tiled_entropy_confidence_equals_untiled_on_suite_scenes(name, preset, tmp_path):
    """The tiled run hands back the confidence of an untiled run, bit for bit, with the maps it is
    made from (cost, chosen window, entropy, ...): tiles of 40 px on a 96-px suite scene, through
    the estimator the batch plugs into the pipeline, which writes the same files."""
    from recon.entropy import estimate_disparity, write_outputs
    from recon.entropy.scenes import make_scene
    from recon.lf.pfm import read_pfm
    from recon.scale.tiles import tiled_estimator

    lf = make_scene(name, size=96).lf
    whole = estimate_disparity(lf, preset=preset)
    record = {}
    result = tiled_estimator(tile=40, record=record)(lf, "entropy", {"preset": preset}, None)
    assert record["tiles"] == 9
    assert_same_maps(result.extras, whole)
    assert 0 < float(np.mean(whole.confidence >= 0.5)) < 1  # a map with both kinds of pixel
    tiled_files = [p.relative_to(tmp_path / "tiled") for p in result.write_extras(tmp_path / "tiled")]
    whole_files = [p.relative_to(tmp_path / "whole") for p in write_outputs(whole, tmp_path / "whole")]
    assert tiled_files == whole_files and Path("confidence.pfm") in tiled_files
    for name in tiled_files:
        assert (tmp_path / "tiled" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name
    np.testing.assert_array_equal(read_pfm(tmp_path / "tiled" / "confidence.pfm"), whole.confidence)


def test_entropy_tiles_need_the_whole_image_steps(boxes):
    """Not luck either: the same tiles each running the whole estimator (noise sigma, bin origin,
    hole fill and TV refinement per crop) differ from the untiled map."""
    import dataclasses

    from recon.entropy import estimate_disparity

    whole = estimate_disparity(boxes).disparity
    naive = dataclasses.replace(TILE_RULES["entropy"], run=None)
    rule_table = dict(TILE_RULES)
    try:
        TILE_RULES["entropy"] = naive
        result = tiled_disparity(boxes, method="entropy", tile=75)
    finally:
        TILE_RULES.clear()
        TILE_RULES.update(rule_table)
    assert np.abs(result.disparity - whole).max() > 0.01


def test_window_sums_do_not_depend_on_the_table_origin():
    from recon.entropy.cost import FIXED_INV, set_integrals

    rng = np.random.default_rng(3)
    blocks = rng.random((9, 40, 50)).astype(np.float32) * 9
    whole = set_integrals(blocks, np.arange(11))
    crop = set_integrals(np.ascontiguousarray(blocks[:, 7:, 11:]), np.arange(11))

    def box(table, y0, y1, x0, x1):
        return table[:, y1, x1] - table[:, y0, x1] - table[:, y1, x0] + table[:, y0, x0]

    np.testing.assert_array_equal(box(whole, 10, 25, 15, 30), box(crop, 3, 18, 4, 19))
    direct = blocks[:, 10:25, 15:30].sum((1, 2), dtype=np.float64)
    from recon.entropy.windows import SET_BLOCKS

    np.testing.assert_allclose(box(whole, 10, 25, 15, 30) * FIXED_INV, SET_BLOCKS @ direct, rtol=1e-7)
