"""Depth and PLY export on the benchmark scene backgammon (its ground-truth disparity)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from recon.depth import benchmark_camera, benchmark_disparity_to_depth
from recon.export import export_ply
from recon.lf.imageio import read_image
from recon.lf.params import read_parameters
from recon.lf.pfm import read_pfm

# backgammon's camera as the benchmark publishes it in parameters.cfg
BACKGAMMON = {
    "intrinsics": {"focal_length_mm": 100.0, "sensor_size_mm": 35.0,
                   "image_resolution_x_px": 512, "image_resolution_y_px": 512},
    "extrinsics": {"baseline_mm": 30.0, "focus_distance_m": 8.300000190734863},
}


@pytest.mark.hci
def test_backgammon_truth_becomes_a_clean_metric_mesh(hci_scene_dir, tmp_path):
    cfg = hci_scene_dir / "parameters.cfg"
    parameters = read_parameters(cfg) if cfg.is_file() else BACKGAMMON
    camera = benchmark_camera(parameters)
    assert camera == benchmark_camera(BACKGAMMON)  # our copy of the scene is the published one
    truth = read_pfm(hci_scene_dir / "gt_disp_lowres.pfm")
    depth = camera.camera().depth_mm(truth)
    np.testing.assert_allclose(depth, benchmark_disparity_to_depth(truth, camera=camera), rtol=1e-5)
    # the scene spans disp_min..disp_max = -1.7..0.7 px, i.e. roughly 7.3 m .. 12.3 m from the cameras
    assert 7000 < np.nanmin(depth) < np.nanmax(depth) < 12500

    image = read_image(hci_scene_dir / "input_Cam040.png")
    summary = export_ply(tmp_path / "backgammon.ply", disparity_px=truth, image=image,
                         camera=camera.camera())
    mesh = o3d.io.read_triangle_mesh(str(summary.path))
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert summary.pixels_used == 512 * 512  # the truth is defined everywhere
    # vertices: every pixel joined to a neighbour (a few one-pixel slivers of the thin tongues are not)
    assert 0.99 * 512 * 512 < len(vertices) == summary.points <= 512 * 512
    assert 0.9 * 2 * 511 * 511 < len(triangles) == summary.triangles < 2 * 511 * 511
    z = vertices[triangles][..., 2]
    assert np.all(z.max(axis=1) <= 1.05 * z.min(axis=1)), "a triangle spans a depth jump"
    mesh.compute_triangle_normals()
    centres = vertices[triangles].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", np.asarray(mesh.triangle_normals), centres) < 0)
