"""Disparity <-> depth as an inverse pair, the benchmark's conversion, and depth maps on disk."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon.camera import depth_to_disparity, disparity_to_depth
from recon.depth import (
    PNG_SCALE_KEY,
    BenchmarkCamera,
    DepthFormatError,
    benchmark_camera,
    benchmark_disparity_to_depth,
    png_sidecar_path,
    read_depth,
    write_depth,
)

CAMERA = {"focal_px": 1200.0, "pitch_mm": 2.5, "disparity_offset": 1.75}

# backgammon's parameters.cfg as published with the benchmark (our copy of the scene lacks the file).
BACKGAMMON_CFG = """\
[intrinsics]
focal_length_mm = 100.0
image_resolution_x_px = 512
image_resolution_y_px = 512
sensor_size_mm = 35.0
fstop = 100.0

[extrinsics]
num_cams_x = 9
num_cams_y = 9
baseline_mm = 30.0
focus_distance_m = 8.300000190734863

[meta]
disp_min = -1.7
disp_max = 0.7
"""


def test_depth_of_known_point():
    # 1200 px * 2.5 mm / 1000 mm = 3 px unshifted; the offset subtracts 1.75.
    assert disparity_to_depth(np.array(1.25), **CAMERA) == pytest.approx(1000.0)
    assert depth_to_disparity(np.array(1000.0), **CAMERA) == pytest.approx(1.25)


def test_round_trip_disparity_depth_disparity():
    rng = np.random.default_rng(0)
    disparity = rng.uniform(-1.7, 3.0, size=(17, 23))  # all effective disparities > 0
    depth = disparity_to_depth(disparity, **CAMERA)
    assert depth.shape == disparity.shape and np.isfinite(depth).all()
    np.testing.assert_allclose(depth_to_disparity(depth, **CAMERA), disparity, rtol=0, atol=1e-12)


def test_round_trip_depth_disparity_depth():
    rng = np.random.default_rng(1)
    depth = rng.uniform(200.0, 20_000.0, size=(5, 7, 3))
    back = disparity_to_depth(depth_to_disparity(depth, **CAMERA), **CAMERA)
    np.testing.assert_allclose(back, depth, rtol=1e-12)


def test_closer_points_have_larger_disparity():
    depth = np.array([500.0, 1000.0, 2000.0])
    disparity = depth_to_disparity(depth, **CAMERA)
    assert np.all(np.diff(disparity) < 0)


def test_non_positive_effective_disparity_is_nan():
    disparity = np.array([-1.75, -2.0, -1.7, np.nan, np.inf])
    depth = disparity_to_depth(disparity, **CAMERA)
    assert np.isnan(depth[0]) and np.isnan(depth[1]) and np.isnan(depth[3]) and np.isnan(depth[4])
    assert depth[2] == pytest.approx(1200 * 2.5 / 0.05)


def test_non_positive_depth_is_nan():
    out = depth_to_disparity(np.array([0.0, -5.0, np.nan, np.inf, 100.0]), **CAMERA)
    assert np.isnan(out[:4]).all() and np.isfinite(out[4])


def test_float32_stays_float32_and_ints_become_float64():
    assert disparity_to_depth(np.ones(3, np.float32), **CAMERA).dtype == np.float32
    assert disparity_to_depth(np.ones(3, np.int32), **CAMERA).dtype == np.float64
    assert depth_to_disparity(np.ones(3, np.float32), **CAMERA).dtype == np.float32


@pytest.mark.parametrize("bad", [{"focal_px": 0.0}, {"pitch_mm": -1.0}, {"disparity_offset": np.nan}])
def test_bad_camera_is_rejected_with_the_value(bad):
    with pytest.raises(ValueError, match=list(bad)[0]):
        disparity_to_depth(np.ones(2), **{**CAMERA, **bad})


def test_benchmark_camera_matches_the_toolkit_formula(tmp_path):
    cfg = tmp_path / "parameters.cfg"
    cfg.write_text(BACKGAMMON_CFG)
    camera = benchmark_camera(tmp_path)  # the scene folder works as well as the file
    assert camera == benchmark_camera(cfg)
    assert camera.focal_px == pytest.approx(100.0 * 512 / 35.0)
    assert camera.disparity_offset == pytest.approx(camera.focal_px * 30.0 / 8300.000190734863)
    disparity = np.linspace(-1.7, 0.7, 25)
    ours = camera.camera().depth_mm(disparity)
    theirs = benchmark_disparity_to_depth(disparity, camera=camera)
    np.testing.assert_allclose(ours, theirs, rtol=1e-12)
    # zero disparity is the focus plane; backgammon spans roughly 7.3 m .. 12.3 m from the cameras
    assert camera.camera().depth_mm(np.array(0.0)) == pytest.approx(8300.0, rel=1e-6)
    assert 7000 < ours.min() < ours.max() < 13000


def test_benchmark_camera_agrees_with_lightfield_reader(tmp_path):
    from recon.lf.params import camera_from_parameters, read_parameters

    cfg = tmp_path / "parameters.cfg"
    cfg.write_text(BACKGAMMON_CFG)
    parameters = read_parameters(cfg)
    _, theirs = camera_from_parameters(parameters, path=cfg)
    ours = benchmark_camera(parameters)
    assert ours.focal_px == pytest.approx(theirs["focal_px"])
    assert ours.disparity_offset == pytest.approx(theirs["disparity_offset"])


def test_benchmark_camera_missing_key_names_it(tmp_path):
    cfg = tmp_path / "parameters.cfg"
    cfg.write_text(BACKGAMMON_CFG.replace("baseline_mm = 30.0\n", ""))
    with pytest.raises(DepthFormatError, match="baseline_mm"):
        benchmark_camera(cfg)
    with pytest.raises(DepthFormatError, match="parameters.cfg"):
        benchmark_camera(tmp_path / "nowhere")


def _depth_map():
    rng = np.random.default_rng(2)
    depth = rng.uniform(800.0, 1300.0, size=(12, 9))
    depth[3, 4] = np.nan
    depth[0, 0] = np.nan
    return depth


@pytest.mark.parametrize("suffix", [".pfm", ".npy"])
def test_float_formats_round_trip(tmp_path, suffix):
    depth = _depth_map()
    path = write_depth(tmp_path / f"depth{suffix}", depth)
    back = read_depth(path)
    assert back.shape == depth.shape
    np.testing.assert_array_equal(np.isnan(back), np.isnan(depth))
    np.testing.assert_allclose(back, depth.astype(np.float32), rtol=0, atol=0)


def test_png_round_trip_within_half_a_step(tmp_path):
    depth = _depth_map()
    path = write_depth(tmp_path / "depth.png", depth)
    back = read_depth(path)
    meta = json.loads(png_sidecar_path(path).read_text())
    span = np.nanmax(depth) - np.nanmin(depth)
    assert meta["unit"] == "mm" and meta["scale_mm"] == pytest.approx(span / 65534)
    assert meta["offset_mm"] == pytest.approx(np.nanmin(depth))
    np.testing.assert_array_equal(np.isnan(back), np.isnan(depth))
    ok = ~np.isnan(depth)
    assert np.max(np.abs(back[ok] - depth[ok])) <= meta["scale_mm"] / 2 + 1e-9


def test_png_scale_is_in_the_file_itself(tmp_path):
    import cv2

    depth = _depth_map()
    path = write_depth(tmp_path / "depth.png", depth, scale_mm=0.1, offset_mm=0.0)
    assert PNG_SCALE_KEY.encode() in path.read_bytes()
    png_sidecar_path(path).unlink()  # the text chunk alone is enough
    back = read_depth(path)
    ok = ~np.isnan(depth)
    assert np.max(np.abs(back[ok] - depth[ok])) <= 0.05 + 1e-9
    stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # any PNG reader sees plain 16-bit grey
    assert stored.dtype == np.uint16 and stored.shape == depth.shape and stored[3, 4] == 0


def test_png_that_does_not_fit_is_refused(tmp_path):
    with pytest.raises(ValueError, match="scale_mm"):
        write_depth(tmp_path / "depth.png", _depth_map(), scale_mm=0.001, offset_mm=0.0)


def test_unknown_suffix_is_refused(tmp_path):
    with pytest.raises(DepthFormatError, match=".tif"):
        write_depth(tmp_path / "depth.tif", _depth_map())


def test_benchmark_camera_is_a_value():
    camera = BenchmarkCamera(100.0, 35.0, 512, 512, 30.0, 8.3)
    assert camera.pitch_mm == 30.0


def test_depth_error_scores():
    from recon.depth import depth_error_scores

    truth = np.full((10, 10), 1000.0)
    estimate = truth.copy()
    estimate[:, :5] *= 1.002  # 0.2 % too far on the left half
    estimate[:, 9] *= 1.02  # 2 % on the last column
    estimate[0, 0] = np.nan
    scores = depth_error_scores(estimate, truth)
    assert scores["pixels"] == 99
    assert scores["median_abs_rel_pct"] == pytest.approx(0.2)
    assert scores["within_pct"] == pytest.approx(100 * 89 / 99)
    inner = depth_error_scores(estimate, truth, border_px=1, mask=np.ones((10, 10), bool))
    assert inner["pixels"] == 64 and inner["within_pct"] == 100.0
    assert np.isnan(depth_error_scores(estimate, truth, mask=np.zeros((10, 10), bool))["median_abs_rel_pct"])


def test_writing_into_a_missing_folder_names_it(tmp_path):
    with pytest.raises(DepthFormatError, match="does not exist"):
        write_depth(tmp_path / "nope" / "depth.npy", _depth_map())
