"""The report's 3D model: the PLY reader (against open3d's files), decimation, the browser payload."""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest

from recon.camera import Camera
from recon.errors import ReconError
from recon.report.model import ViewerModel, decimate, model_payload, read_ply, write_viewer_files

CAMERA = Camera(focal_px=100.0, pitch_mm=1.0)


def _exported(tmp_path, *, kind="mesh", ascii=False, size=(40, 50)):
    from recon.export import export_ply

    height, width = size
    ys, xs = np.indices(size)
    depth = 500.0 + xs + 0.5 * ys
    depth[10:25, 10:30] = 380.0
    image = np.stack([xs * 5, ys * 5, np.full_like(xs, 7)], -1).astype(np.uint8)
    confidence = (xs / width).astype(np.float32)
    path = tmp_path / f"{kind}{'_ascii' if ascii else ''}.ply"
    export_ply(path, disparity_px=CAMERA.disparity_px(depth), image=image, camera=CAMERA, kind=kind, ascii=ascii,
               confidence=confidence, min_confidence=0.0)
    return path


@pytest.mark.parametrize("kind", ["mesh", "points"])
@pytest.mark.parametrize("ascii", [False, True])
def test_read_ply_agrees_with_open3d(tmp_path, kind, ascii):
    import open3d as o3d

    path = _exported(tmp_path, kind=kind, ascii=ascii)
    model = read_ply(path)
    if kind == "mesh":
        reference = o3d.io.read_triangle_mesh(str(path))
        np.testing.assert_array_equal(model.triangles, np.asarray(reference.triangles))
        vertices, colours = np.asarray(reference.vertices), np.asarray(reference.vertex_colors)
    else:
        reference = o3d.io.read_point_cloud(str(path))
        assert model.triangles is None
        vertices, colours = np.asarray(reference.points), np.asarray(reference.colors)
    np.testing.assert_allclose(model.vertices_mm, vertices, rtol=1e-6)
    np.testing.assert_array_equal(model.colours, np.round(colours * 255).astype(np.uint8))
    # the confidence property lfrig adds is the x position here: the vertex's column / width
    column = model.vertices_mm[:, 0] * CAMERA.focal_px / model.vertices_mm[:, 2] + (50 - 1) / 2
    np.testing.assert_allclose(model.confidence, np.round(column) / 50, atol=1e-5)


def test_read_ply_refuses_what_is_not_a_ply(tmp_path):
    (tmp_path / "x.ply").write_text("hello")
    with pytest.raises(ReconError, match="x.ply: not a PLY"):
        read_ply(tmp_path / "x.ply")
    with pytest.raises(ReconError, match="missing.ply: cannot read"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "quad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                                       "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                       "end_header\n0 0 1\n1 0 1\n1 1 1\n0 1 1\n4 0 1 2 3\n")
    with pytest.raises(ReconError, match="not triangles"):
        read_ply(tmp_path / "quad.ply")


def test_decimation_keeps_the_shape_and_meets_the_budget(tmp_path):
    model = read_ply(_exported(tmp_path, size=(120, 160)))
    small = decimate(model, max_triangles=4000)
    assert 2000 < len(small.triangles) <= 4000
    assert small.original == model.original
    assert small.triangles.max() < len(small.vertices_mm) and len(np.unique(small.triangles)) == len(small.vertices_mm)
    assert np.all(small.triangles[:, 0] != small.triangles[:, 1])
    # every simplified vertex lies near the original surface: the box at 380 mm or the wall behind it
    lo, hi = model.vertices_mm.min(axis=0), model.vertices_mm.max(axis=0)
    assert np.all((small.vertices_mm >= lo - 1e-3) & (small.vertices_mm <= hi + 1e-3))
    near = np.abs(small.vertices_mm[:, 2] - 380.0) < 3.0
    far = small.vertices_mm[:, 2] > 480.0
    assert np.all(near | far), "vertex clustering must not merge the box with the wall behind it"
    # faces keep facing the camera (counter-clockwise seen from it): normals . position < 0
    v = small.vertices_mm.astype(np.float64)[small.triangles]
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert np.mean(np.einsum("ij,ij->i", normals, v.mean(axis=1)) < 0) > 0.99
    assert decimate(model, max_triangles=10**9) is model


def test_decimating_a_cloud_samples_it_reproducibly(tmp_path):
    model = read_ply(_exported(tmp_path, kind="points"))
    a, b = decimate(model, max_points=500), decimate(model, max_points=500)
    assert len(a.vertices_mm) == 500 and a.original == (2000, 0)
    np.testing.assert_array_equal(a.vertices_mm, b.vertices_mm)


def test_payload_decodes_to_the_model(tmp_path):
    model = ViewerModel(vertices_mm=np.array([[0, 0, 100], [1, 0, 100], [0, 1, 120.0]]), triangles=np.array([[0, 1, 2]]),
                        colours=np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9]]), confidence=np.array([0.0, 0.5, 1.0]),
                        name="t")
    names = write_viewer_files(tmp_path, model)
    text = (tmp_path / names[1]).read_text()
    assert text.startswith("window.LFRIG_MODEL = ") and text.rstrip().endswith(";")
    payload = json.loads(text[len("window.LFRIG_MODEL = "):].rstrip().rstrip(";"))
    assert payload == json.loads(json.dumps(model_payload(model)))
    positions = np.frombuffer(base64.b64decode(payload["positions"]), "<f4").reshape(-1, 3)
    np.testing.assert_array_equal(positions, model.vertices_mm)
    np.testing.assert_array_equal(np.frombuffer(base64.b64decode(payload["indices"]), "<u4"), [0, 1, 2])
    assert set(payload["colourings"]) == {"image", "depth", "confidence"}
    np.testing.assert_array_equal(np.frombuffer(base64.b64decode(payload["colourings"]["image"]["rgb"]), "u1"),
                                  np.arange(1, 10))
    assert "clipped to the 1st–99th percentile" in payload["colourings"]["depth"]["legend"]
