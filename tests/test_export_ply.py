"""PLY files written through open3d: they load back with the expected points, faces and attributes."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d  # a declared dependency: if it is missing these tests must fail, not skip
import pytest

from recon.camera import Camera, depth_to_disparity
from recon.export import ExportError, export_ply, export_result
from recon.result import read_result
from recon.lf.pfm import write_pfm

CAMERA = {"focal_px": 120.0, "pitch_mm": 2.0, "disparity_offset": 0.1}
CAM = Camera(**CAMERA)
HEIGHT, WIDTH, SPLIT = 14, 18, 8
NEAR, FAR = 900.0, 1400.0


def step_scene():
    """Disparity of a near plane (x < SPLIT) before a far one, a hole, and a striped colour image."""
    depth = np.full((HEIGHT, WIDTH), FAR)
    depth[:, :SPLIT] = NEAR
    disparity = depth_to_disparity(depth, **CAMERA).astype(np.float32)
    disparity[5, 12] = np.nan  # no trustworthy value here
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    image[..., 1] = 200
    image[:, :SPLIT, 0] = 255
    return disparity, image


def header(path) -> str:
    data = path.read_bytes()
    return data[: data.index(b"end_header")].decode("ascii")


@pytest.mark.parametrize("ascii", [False, True])
def test_point_cloud_ply_loads_with_every_trusted_pixel(tmp_path, ascii):
    disparity, image = step_scene()
    summary = export_ply(tmp_path / "cloud.ply", disparity_px=disparity, image=image, kind="points", ascii=ascii, camera=CAM)
    text = header(summary.path)
    assert ("format ascii 1.0" in text) == ascii and ("binary_little_endian" in text) != ascii
    pcd = o3d.io.read_point_cloud(str(summary.path))
    assert len(pcd.points) == summary.points == HEIGHT * WIDTH - 1
    assert pcd.has_normals() and pcd.has_colors()
    points, normals, colours = np.asarray(pcd.points), np.asarray(pcd.normals), np.asarray(pcd.colors)
    assert np.all(np.einsum("ij,ij->i", normals, points) < 0), "normals must face the camera"
    near = points[:, 2] < (NEAR + FAR) / 2
    np.testing.assert_allclose(points[near, 2], NEAR, rtol=1e-6)
    np.testing.assert_allclose(points[~near, 2], FAR, rtol=1e-6)
    np.testing.assert_allclose(colours[near], np.tile([1.0, 200 / 255, 0.0], (near.sum(), 1)), atol=1e-6)


def test_a_mesh_export_computes_the_point_cloud_once(tmp_path, monkeypatch):
    """The mesh reuses the cloud the export counts its pixels with: the same mesh as depth_mesh's own."""
    import recon.cloud
    import recon.export

    disparity, image = step_scene()
    mesh = recon.cloud.depth_mesh(CAM.depth_mm(disparity.astype(np.float64)), image, focal_px=CAM.focal_px)
    calls = []
    real = recon.cloud.point_cloud

    def counted(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(recon.cloud, "point_cloud", counted)
    monkeypatch.setattr(recon.export, "point_cloud", counted)
    summary = export_ply(tmp_path / "mesh.ply", disparity_px=disparity, image=image, kind="mesh", camera=CAM)
    assert len(calls) == 1
    written = o3d.io.read_triangle_mesh(str(summary.path))
    assert np.array_equal(np.asarray(written.triangles), mesh.triangles)
    assert np.allclose(np.asarray(written.vertices), mesh.vertices_mm, rtol=1e-6)


@pytest.mark.parametrize("ascii", [False, True])
def test_mesh_ply_loads_and_has_no_face_across_the_jump(tmp_path, ascii):
    disparity, image = step_scene()
    summary = export_ply(tmp_path / "mesh.ply", disparity_px=disparity, image=image, kind="mesh", ascii=ascii, camera=CAM)
    assert "element face" in header(summary.path)
    mesh = o3d.io.read_triangle_mesh(str(summary.path))
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    # near block: full grid; far block: full grid, but each of the 4 cells around the hole at
    # (5, 12) keeps only the one triangle over its other three corners
    expected = 2 * (HEIGHT - 1) * (SPLIT - 1) + 2 * (HEIGHT - 1) * (WIDTH - SPLIT - 1) - 4
    assert len(triangles) == summary.triangles == expected
    assert len(vertices) == summary.points == HEIGHT * WIDTH - 1
    z = vertices[triangles][..., 2]
    near = z < (NEAR + FAR) / 2
    assert np.all(near.all(axis=1) | (~near).all(axis=1)), "a face joins foreground and background"
    assert mesh.has_vertex_normals() and mesh.has_vertex_colors()
    assert np.all(np.einsum("ij,ij->i", np.asarray(mesh.vertex_normals), vertices) < 0)
    mesh.compute_triangle_normals()
    centres = vertices[triangles].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", np.asarray(mesh.triangle_normals), centres) < 0), "faces must face the camera"


def test_mask_leaves_pixels_out(tmp_path):
    disparity, image = step_scene()
    mask = np.ones(disparity.shape, bool)
    mask[:, -3:] = False
    summary = export_ply(tmp_path / "c.ply", disparity_px=disparity, image=image, kind="points", mask=mask, camera=CAM)
    assert summary.points == HEIGHT * WIDTH - 1 - 3 * HEIGHT
    assert len(o3d.io.read_point_cloud(str(summary.path)).points) == summary.points


def test_poisson_mesh_covers_the_plane(tmp_path):
    ys, xs = np.indices((40, 40), dtype=float)
    depth = 1000.0 + 2.0 * xs
    disparity = depth_to_disparity(depth, **CAMERA)
    summary = export_ply(tmp_path / "p.ply", disparity_px=disparity, image=None, kind="mesh", poisson=True,
                         poisson_depth=6, camera=CAM)
    mesh = o3d.io.read_triangle_mesh(str(summary.path))
    vertices = np.asarray(mesh.vertices)
    assert summary.kind == "poisson" and len(mesh.triangles) > 100
    assert vertices[:, 2].min() > 990 and vertices[:, 2].max() < 1090  # stays on the plane's extent


def test_poisson_with_points_is_refused(tmp_path):
    disparity, image = step_scene()
    with pytest.raises(ExportError, match="--mesh"):
        export_ply(tmp_path / "x.ply", disparity_px=disparity, image=image, kind="points", poisson=True, camera=CAM)


def test_wrong_suffix_and_missing_folder_are_named(tmp_path):
    disparity, image = step_scene()
    with pytest.raises(ExportError, match=r"\.ply"):
        export_ply(tmp_path / "x.obj", disparity_px=disparity, image=image, camera=CAM)
    with pytest.raises(ExportError, match="does not exist"):
        export_ply(tmp_path / "no" / "x.ply", disparity_px=disparity, image=image, camera=CAM)


def write_result(folder, *, record=None, with_centre=True):
    import cv2

    disparity, image = step_scene()
    folder.mkdir()
    write_pfm(folder / "disparity.pfm", disparity)
    if with_centre:
        cv2.imwrite(str(folder / "centre_view.png"), image[..., ::-1])
    record = {**CAMERA, "source": "nowhere"} if record is None else record
    (folder / "result.json").write_text(json.dumps(record))
    return folder


def test_export_result_reads_the_folder(tmp_path):
    folder = write_result(tmp_path / "run")
    result = read_result(folder)
    assert result.focal_px == CAMERA["focal_px"] and result.disparity_offset == CAMERA["disparity_offset"]
    assert result.image is not None and result.image.shape == (HEIGHT, WIDTH, 3)
    summary = export_result(folder, tmp_path / "out.ply", kind="points")
    pcd = o3d.io.read_point_cloud(str(summary.path))
    assert len(pcd.points) == HEIGHT * WIDTH - 1 and pcd.has_colors()


def test_export_result_without_camera_asks_for_it(tmp_path):
    folder = write_result(tmp_path / "run", record={"focal_px": None, "pitch_mm": 2.0}, with_centre=False)
    with pytest.raises(ExportError, match="--focal-px"):
        export_result(folder, tmp_path / "out.ply")
    summary = export_result(folder, tmp_path / "out.ply", focal_px=120.0, disparity_offset=0.1)
    assert summary.points == HEIGHT * WIDTH - 1


def test_export_result_errors_name_the_file(tmp_path):
    with pytest.raises(ExportError, match="no such reconstruction folder"):
        read_result(tmp_path / "missing")
    folder = write_result(tmp_path / "run", record={"focal_px": -3, "pitch_mm": 2.0})
    with pytest.raises(ExportError, match="focal_px"):
        read_result(folder)
    (folder / "result.json").unlink()
    with pytest.raises(ExportError, match="result.json"):
        read_result(folder)


def test_binary_mesh_is_plain_ply_that_any_reader_can_parse(tmp_path):
    """Read the file with nothing but its header, as MeshLab or CloudCompare would."""
    disparity, image = step_scene()
    summary = export_ply(tmp_path / "mesh.ply", disparity_px=disparity, image=image, camera=CAM)
    data = summary.path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    properties = [line.split()[-1] for line in lines if line.startswith("property ") and "list" not in line]
    assert properties == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    assert [line for line in lines if line.startswith("property float ")] == [
        f"property float {n}" for n in properties[:6]]  # float32 vertices and normals
    assert "property list uchar uint vertex_indices" in lines
    vertex = np.dtype([(n, "<f4") for n in properties[:6]] + [(n, "u1") for n in properties[6:]])
    face = np.dtype([("n", "u1"), ("v", "<u4", 3)])
    vertices = np.frombuffer(data, vertex, count=summary.points, offset=end)
    faces = np.frombuffer(data, face, count=summary.triangles, offset=end + vertex.itemsize * summary.points)
    assert end + vertex.itemsize * summary.points + face.itemsize * summary.triangles == len(data)
    assert np.all(faces["n"] == 3) and faces["v"].max() < summary.points
    assert set(np.unique(vertices["red"])) == {0, 255} and np.all(vertices["green"] == 200)
