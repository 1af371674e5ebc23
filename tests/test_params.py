"""``parameters.cfg``: parameters_for and camera_from_parameters are one inverse pair."""

from __future__ import annotations

import pytest

from recon.lf.params import camera_from_parameters, parameters_for, read_parameters, write_parameters


@pytest.mark.parametrize("camera", [
    {"pitch_mm": 0.5, "focal_px": 3645.8, "disparity_offset": 1.25, "disparity_range": (-0.5, 2.5),
     "principal_point_px": (301.5, 240.25)},
    {"pitch_mm": 0.5, "focal_px": None, "disparity_offset": 0.0, "disparity_range": None, "principal_point_px": None},
])
def test_written_parameters_read_back_as_the_same_camera(tmp_path, camera):
    path = tmp_path / "parameters.cfg"
    write_parameters(path, parameters_for(grid=(9, 7), image_shape=(490, 640), **camera))
    num_cams, found = camera_from_parameters(read_parameters(path), path=path)
    assert num_cams == (9, 7)
    assert found == camera  # floats are written as repr, which reads back exactly


def test_benchmark_focal_length_and_focus_give_the_offset(tmp_path):
    path = tmp_path / "parameters.cfg"
    path.write_text("[intrinsics]\nfocal_length_mm = 100\nsensor_size_mm = 35\nimage_resolution_x_px = 512\n"
                    "image_resolution_y_px = 512\n[extrinsics]\nbaseline_mm = 90\nfocus_distance_m = 8.3\n")
    _, camera = camera_from_parameters(read_parameters(path), path=path)
    assert camera["focal_px"] == pytest.approx(100 / 35 * 512)
    assert camera["disparity_offset"] == pytest.approx(camera["focal_px"] * 90 / 8300)
