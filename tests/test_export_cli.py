"""``lfrig export``: the thin command over recon.export, recon.depth and recon.report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rig.main import main
from recon.camera import depth_to_disparity
from recon.depth import read_depth
from recon.lf.pfm import write_pfm

CAMERA = {"focal_px": 150.0, "pitch_mm": 2.0, "disparity_offset": 0.0}


@pytest.fixture
def result_dir(tmp_path):
    """A reconstruction folder as lfrig reconstruct writes it, with a light field that has a truth."""
    import cv2

    depth = np.full((24, 32), 1200.0)
    depth[6:18, 8:20] = 800.0
    disparity = depth_to_disparity(depth, **CAMERA).astype(np.float32)
    source = tmp_path / "scene"
    source.mkdir()
    write_pfm(source / "gt_disp_lowres.pfm", disparity)
    folder = tmp_path / "run"
    folder.mkdir()
    write_pfm(folder / "disparity.pfm", disparity)
    image = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    cv2.imwrite(str(folder / "centre_view.png"), image)
    (folder / "result.json").write_text(json.dumps({**CAMERA, "source": str(source), "method": "baseline"}))
    return folder


def test_export_mesh_depth_and_report(result_dir, tmp_path, capsys):
    import open3d as o3d
    status = main(["export", str(result_dir), "--ply", str(tmp_path / "m.ply"), "--depth", str(tmp_path / "d.png"),
                   "--depth", str(tmp_path / "d.npy"), "--report", str(tmp_path / "report")])
    assert status == 0
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    assert len(mesh.vertices) == 24 * 32
    z = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)][..., 2]
    assert np.all((z < 1000).all(axis=1) | (z > 1000).all(axis=1))
    np.testing.assert_allclose(np.nanmax(read_depth(tmp_path / "d.npy")), 1200.0, rtol=1e-5)
    assert abs(np.nanmin(read_depth(tmp_path / "d.png")) - 800.0) < 0.01
    page = (tmp_path / "report" / "index.html").read_text()
    assert "error.png" in page and "depth.png" in page  # the truth was found through "source"
    out = capsys.readouterr().out
    assert "m.ply" in out and "768 points" in out


def test_export_points_ascii(result_dir, tmp_path):
    assert main(["export", str(result_dir), "--ply", str(tmp_path / "p.ply"), "--points", "--ascii"]) == 0
    assert b"format ascii 1.0" in (tmp_path / "p.ply").read_bytes()[:100]


@pytest.mark.parametrize(
    "extra, message",
    [
        ([], "nothing to do"),
        (["--ply", "x.ply", "--points", "--poisson"], "--poisson"),
        (["--ply", "x.ply", "--max-jump", "0"], "--max-jump"),
    ],
)
def test_user_mistakes_are_one_line_errors(result_dir, capsys, extra, message):
    assert main(["export", str(result_dir), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lfrig: error:") and message in err and "Traceback" not in err


def test_mesh_and_points_are_exclusive(result_dir):
    assert main(["export", str(result_dir), "--ply", "x.ply", "--mesh", "--points"]) == 2


def test_unknown_camera_asks_for_flags(result_dir, tmp_path, capsys):
    record = json.loads((result_dir / "result.json").read_text())
    record.update(focal_px=None, pitch_mm=None)
    (result_dir / "result.json").write_text(json.dumps(record))
    assert main(["export", str(result_dir), "--ply", str(tmp_path / "a.ply")]) == 2
    assert "--focal-px and --pitch-mm" in capsys.readouterr().err
    assert main(["export", str(result_dir), "--ply", str(tmp_path / "a.ply"), "--focal-px", "150",
                 "--pitch-mm", "2"]) == 0
