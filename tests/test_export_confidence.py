"""The export's confidence filter, the search-range filter and the PLY ``confidence`` vertex property."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d  # a declared dependency: if it is missing these tests must fail, not skip
import pytest

from recon.camera import Camera
from recon.export import MIN_CONFIDENCE, export_ply, export_result, trusted_pixels
from recon.lf.pfm import write_pfm
from rig.main import main

CAM = Camera(focal_px=120.0, pitch_mm=2.0, disparity_offset=0.0)
H, W = 12, 16


def scene():
    disparity = np.full((H, W), 0.24, np.float32)  # 1000 mm
    confidence = np.full((H, W), 0.9, np.float32)
    confidence[2:4, 3:7] = 0.1  # 8 unsure pixels
    disparity[6, 9] = 0.6  # a flying point, outside the search range
    image = np.zeros((H, W, 3), np.uint8)
    return disparity, confidence, image


def read_vertices(path) -> tuple[list[str], np.ndarray]:
    """Header property names and the vertex table of a binary PLY, read with nothing but its header."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    count = int(next(line for line in lines if line.startswith("element vertex")).split()[2])
    kinds = {"double": "<f8", "float": "<f4", "uchar": "u1"}
    props = [line.split() for line in lines if line.startswith("property ") and "list" not in line]
    dtype = np.dtype([(p[2], kinds[p[1]]) for p in props])
    return [p[2] for p in props], np.frombuffer(data, dtype, count=count, offset=end)


@pytest.mark.parametrize("kind", ["points", "mesh"])
def test_unsure_pixels_and_points_outside_the_range_are_left_out(tmp_path, kind):
    disparity, confidence, image = scene()
    summary = export_ply(tmp_path / "a.ply", disparity_px=disparity, image=image, camera=CAM, kind=kind,
                         confidence=confidence, search_range=(0.1, 0.4))
    assert summary.pixels_used == H * W - 9 and summary.pixels_unreliable == 9
    names, vertices = read_vertices(summary.path)
    assert names[-1] == "confidence" and names[:3] == ["x", "y", "z"]
    np.testing.assert_allclose(vertices["confidence"], 0.9, rtol=1e-6)
    np.testing.assert_allclose(vertices["z"], 1000.0, rtol=1e-5)  # the flying point is gone
    if kind == "mesh":
        mesh = o3d.io.read_triangle_mesh(str(summary.path))
        assert len(mesh.triangles) == summary.triangles  # faces survive the rewrite
    kept = export_ply(tmp_path / "b.ply", disparity_px=disparity, image=image, camera=CAM, kind=kind,
                      confidence=confidence, search_range=(0.1, 0.4), keep_all=True)
    assert kept.pixels_used == H * W and kept.pixels_unreliable == 0
    assert sorted(np.unique(read_vertices(kept.path)[1]["confidence"]).round(3)) == [0.1, 0.9]


def test_ascii_ply_carries_the_property_and_open3d_still_reads_it(tmp_path):
    disparity, confidence, image = scene()
    summary = export_ply(tmp_path / "a.ply", disparity_px=disparity, image=image, camera=CAM, kind="points",
                         confidence=confidence, ascii=True)
    text = summary.path.read_text()
    assert "property float confidence" in text
    first = text.split("end_header\n")[1].splitlines()[0].split()
    assert float(first[-1]) == pytest.approx(0.9)
    assert len(o3d.io.read_point_cloud(str(summary.path)).points) == summary.points


def test_trusted_pixels():
    disparity, confidence, _ = scene()
    disparity[0, 0] = np.nan
    keep = trusted_pixels(disparity, confidence=confidence, search_range=(0.1, 0.4))
    assert keep.sum() == H * W - 10 and not keep[0, 0] and not keep[6, 9] and not keep[2, 3]
    assert trusted_pixels(disparity).sum() == H * W - 1
    assert MIN_CONFIDENCE == 0.5  # a probability of being right: more likely right than wrong


def test_export_command_filters_by_default_and_keeps_all_on_request(tmp_path, capsys):
    disparity, confidence, _ = scene()
    folder = tmp_path / "run"
    folder.mkdir()
    write_pfm(folder / "disparity.pfm", disparity)
    write_pfm(folder / "confidence.pfm", confidence)
    (folder / "result.json").write_text(json.dumps({"focal_px": 120.0, "pitch_mm": 2.0, "method": "entropy",
                                                   "options": {"disparity_range": [0.1, 0.4]}}))
    assert main(["export", str(folder), "--ply", str(tmp_path / "a.ply"), "--points"]) == 0
    out = capsys.readouterr().out
    assert "left out 9 unreliable pixels" in out
    assert f"kept {H * W - 9} of {H * W} pixels" in out and "confidence >= 0.5" in out
    assert len(o3d.io.read_point_cloud(str(tmp_path / "a.ply")).points) == H * W - 9
    assert main(["export", str(folder), "--ply", str(tmp_path / "b.ply"), "--points", "--keep-all"]) == 0
    assert f"kept {H * W} of {H * W} pixels (every finite one: --keep-all)" in capsys.readouterr().out
    assert len(o3d.io.read_point_cloud(str(tmp_path / "b.ply")).points) == H * W
    assert main(["export", str(folder), "--ply", str(tmp_path / "c.ply"), "--points", "--min-confidence", "0.05"]) == 0
    assert len(o3d.io.read_point_cloud(str(tmp_path / "c.ply")).points) == H * W - 1
    assert main(["export", str(folder), "--ply", str(tmp_path / "d.ply"), "--min-confidence", "2"]) != 0
    assert "--min-confidence 2" in capsys.readouterr().err
    summary = export_result(folder, tmp_path / "e.ply", kind="points")
    assert summary.pixels_unreliable == 9
