"""``lfrig export --poses``: the views' cameras as a COLMAP text model and a NeRF-style transforms.json.

COLMAP's model is read back by pycolmap (a reader nobody here wrote); its camera centres and its
projections must follow ``docs/conventions.md``: view (u, v) sits at ((v - v0) * pitch, (u - u0) *
pitch, 0) mm in the centre camera's frame, and a point with disparity d at pixel (y, x) of the
centre view appears in view (u, v) at (y - (u - u0) d, x - (v - v0) d) (plus COLMAP's half-pixel
origin).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from recon.camera import Camera
from recon.lf.pfm import write_pfm
from rig.main import main

GRID = (5, 7)  # rows, cols: not square, so that u and v cannot be swapped unnoticed
SIZE = (40, 30)  # W, H


def _result(tmp_path, *, disparity_offset: float, layout: str = "benchmark"):
    """A reconstruction folder of a slanted wall with a box, and its light-field folder (file names only)."""
    camera = Camera(focal_px=200.0, pitch_mm=1.5, disparity_offset=disparity_offset, principal_point_px=(19.0, 14.25))
    height, width = SIZE[1], SIZE[0]
    ys, xs = np.indices((height, width))
    depth = 600.0 + 3.0 * xs + ys
    depth[8:20, 10:25] = 450.0
    disparity = camera.disparity_px(depth).astype(np.float32)
    source = tmp_path / "scene"
    rows, cols = GRID
    if layout == "benchmark":
        source.mkdir()
        for k in range(rows * cols):
            (source / f"input_Cam{k:03d}.png").write_bytes(b"")
    folder = tmp_path / "run"
    folder.mkdir()
    write_pfm(folder / "disparity.pfm", disparity)
    image = np.stack([xs * 6, ys * 8, np.full_like(xs, 90)], axis=-1).astype(np.uint8)
    cv2.imwrite(str(folder / "centre_view.png"), image[..., ::-1])
    record = {**camera.as_dict(), "source": str(source), "method": "baseline", "grid": [rows, cols],
              "image": [width, height]}
    (folder / "result.json").write_text(json.dumps(record))
    return folder, camera, disparity


@pytest.mark.parametrize("disparity_offset", [0.0, 0.75])
def test_colmap_model_round_trips_through_pycolmap(tmp_path, capsys, disparity_offset):
    import pycolmap

    folder, camera, disparity = _result(tmp_path, disparity_offset=disparity_offset)
    out = tmp_path / "poses"
    assert main(["export", str(folder), "--poses", str(out)]) == 0
    assert "35 views" in capsys.readouterr().out
    model = pycolmap.Reconstruction(str(out))
    rows, cols = GRID
    u0, v0 = rows // 2, cols // 2
    assert len(model.images) == rows * cols
    assert len(model.cameras) == (1 if disparity_offset == 0 else rows * cols)
    centres = {}
    for image in model.images.values():
        number = int(image.name[len("input_Cam"):-len(".png")])
        u, v = divmod(number, cols)
        centres[u, v] = image.projection_center()
        np.testing.assert_allclose(centres[u, v], [(v - v0) * camera.pitch_mm, (u - u0) * camera.pitch_mm, 0.0],
                                   atol=1e-9)
        intrinsics = model.cameras[image.camera_id]
        assert intrinsics.model.name == "PINHOLE" and (intrinsics.width, intrinsics.height) == SIZE
        fx, fy, cx, cy = intrinsics.params
        assert fx == fy == pytest.approx(camera.focal_px)
        assert (cx, cy) == pytest.approx((19.5 + (v - v0) * disparity_offset, 14.75 + (u - u0) * disparity_offset))
    # the points are the disparity map's pixels: each projects into every view where the disparity says
    assert len(model.points3D) == disparity.size
    for point in list(model.points3D.values())[::37]:
        xyz = point.xyz
        # back to the centre pixel it came from, and its disparity
        x_c = camera.focal_px * xyz[0] / xyz[2] + 19.0
        y_c = camera.focal_px * xyz[1] / xyz[2] + 14.25
        d = float(disparity[int(round(y_c)), int(round(x_c))])
        for image in model.images.values():
            u, v = divmod(int(image.name[9:12]), cols)
            seen = model.cameras[image.camera_id].img_from_cam(image.cam_from_world() * xyz)
            np.testing.assert_allclose(seen, [x_c - (v - v0) * d + 0.5, y_c - (u - u0) * d + 0.5], atol=1e-3)


def test_transforms_json_schema_and_agreement_with_colmap(tmp_path):
    import pycolmap

    folder, camera, _ = _result(tmp_path, disparity_offset=0.75)
    out = tmp_path / "poses"
    assert main(["export", str(folder), "--poses", str(out)]) == 0
    data = json.loads((out / "transforms.json").read_text())
    for key, kind in (("camera_angle_x", float), ("camera_angle_y", float), ("fl_x", float), ("fl_y", float),
                      ("cx", float), ("cy", float), ("w", int), ("h", int), ("frames", list)):
        assert isinstance(data[key], kind), key
    assert (data["w"], data["h"]) == SIZE
    assert data["camera_angle_x"] == pytest.approx(2 * np.arctan(SIZE[0] / (2 * camera.focal_px)))
    assert (data["cx"], data["cy"]) == pytest.approx((19.5, 14.75))  # the centre view's
    assert data["lfrig"]["units"] == "mm"
    model = pycolmap.Reconstruction(str(out))
    by_id = {image.image_id: image for image in model.images.values()}
    assert len(data["frames"]) == GRID[0] * GRID[1]
    for frame in data["frames"]:
        assert isinstance(frame["file_path"], str) and (out / frame["file_path"]).resolve().is_file()
        matrix = np.asarray(frame["transform_matrix"], dtype=float)
        assert matrix.shape == (4, 4)
        np.testing.assert_array_equal(matrix[3], [0, 0, 0, 1])
        rotation = matrix[:3, :3]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        image = by_id[frame["colmap_im_id"]]
        assert (out / frame["file_path"]).name == image.name
        np.testing.assert_allclose(matrix[:3, 3], image.projection_center(), atol=1e-9)
        # OpenGL camera axes: the camera looks along its -z, which is COLMAP's (OpenCV's) +z
        np.testing.assert_allclose(-rotation[:, 2], image.viewing_direction(), atol=1e-12)
        np.testing.assert_allclose(rotation[:, 1], -image.cam_from_world().rotation.matrix()[1], atol=1e-12)
        cam = model.cameras[image.camera_id]
        assert (frame["cx"], frame["cy"]) == pytest.approx(tuple(cam.params[2:]))


def test_poses_need_the_camera_and_name_the_flags(tmp_path, capsys):
    folder, _, _ = _result(tmp_path, disparity_offset=0.0)
    record = json.loads((folder / "result.json").read_text())
    del record["focal_px"]
    (folder / "result.json").write_text(json.dumps(record))
    assert main(["export", str(folder), "--poses", str(tmp_path / "poses")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lfrig: error:") and "--focal-px" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "poses").exists()
    assert main(["export", str(folder), "--poses", str(tmp_path / "poses"), "--focal-px", "200"]) == 0


@pytest.mark.hci
def test_backgammon_views_agree_with_the_exported_poses(hci_scene_dir, tmp_path):
    """The benchmark's own renderings (shifted sensors, d0 = 5.29) against the exported cameras: the
    centre view's colour of each exported 3D point (from the true disparity) is found where COLMAP's
    model projects that point in the corner views, and not where the mirrored grid would put it."""
    import pycolmap

    from recon.depth import benchmark_camera
    from recon.lf.imageio import read_image
    from recon.lf.params import read_parameters
    from recon.lf.pfm import read_pfm

    camera = benchmark_camera(read_parameters(hci_scene_dir / "parameters.cfg")).camera()
    folder = tmp_path / "run"
    folder.mkdir()
    write_pfm(folder / "disparity.pfm", read_pfm(hci_scene_dir / "gt_disp_lowres.pfm"))
    cv2.imwrite(str(folder / "centre_view.png"), cv2.imread(str(hci_scene_dir / "input_Cam040.png")))
    (folder / "result.json").write_text(json.dumps({**camera.as_dict(), "source": str(hci_scene_dir),
                                                    "grid": [9, 9], "image": [512, 512]}))
    out = tmp_path / "poses"
    assert main(["export", str(folder), "--poses", str(out)]) == 0
    model = pycolmap.Reconstruction(str(out))
    points = list(model.points3D.values())[::10]
    xyz = np.array([p.xyz for p in points])
    colour = np.array([p.color for p in points], dtype=float)
    for image in model.images.values():
        if image.name not in ("input_Cam000.png", "input_Cam008.png", "input_Cam080.png"):
            continue
        view = read_image(hci_scene_dir / image.name).astype(np.float32)
        intrinsics = model.cameras[image.camera_id]
        seen = np.array([intrinsics.img_from_cam(image.cam_from_world() * p) for p in xyz]) - 0.5
        centre = np.array([camera.focal_px * p[:2] / p[2] for p in xyz]) + 255.5  # lfrig pixel in the centre view
        mirrored = 2 * centre - seen  # the grid mirrored through the centre view
        errors = []
        for where in (seen, mirrored):
            sampled = cv2.remap(view, where[:, :1].astype(np.float32), where[:, 1:].astype(np.float32),
                                cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)[:, 0]
            errors.append(float(np.median(np.abs(sampled - colour))))
        assert errors[0] < 4.0 and errors[1] > 3 * errors[0], (image.name, errors)


def test_poses_without_a_recorded_grid_fail_before_anything_is_written(tmp_path, capsys):
    folder, _, _ = _result(tmp_path, disparity_offset=0.0)
    record = json.loads((folder / "result.json").read_text())
    del record["grid"]
    (folder / "result.json").write_text(json.dumps(record))
    assert main(["export", str(folder), "--ply", str(tmp_path / "m.ply"), "--poses", str(tmp_path / "poses")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lfrig: error:") and "records no grid" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "m.ply").exists() and not (tmp_path / "poses").exists()


def test_a_rectified_capture_header_is_recorded_and_a_damaged_one_is_not_fatal(tmp_path):
    """A capture whose journal header records a rectification: transforms.json carries it and
    M_pose_rect = K_pose^-1 K_rect; a K_rect that is not a matrix of numbers is left out."""
    from recon.lf.capture import write_lightfield
    from recon.lf.lightfield import LightField

    folder, camera, _ = _result(tmp_path, disparity_offset=0.0, layout="capture")
    rows, cols = GRID
    views = np.zeros((rows, cols, SIZE[1], SIZE[0]), np.uint8)
    k_rect = [[200.5, -0.9, 19.0], [0.0, 199.4, 14.25], [0.0, 0.0, 1.0]]
    lf = LightField(views=views, pitch_mm=camera.pitch_mm, focal_px=camera.focal_px,
                    principal_point_px=camera.principal_point_px)
    write_lightfield(tmp_path / "scene", lf, header_extra={"rectification": {"K_rect": k_rect, "stage": "stage.json"}})
    out = tmp_path / "poses"
    assert main(["export", str(folder), "--poses", str(out)]) == 0
    record = json.loads((out / "transforms.json").read_text())
    assert record["frames"][0]["file_path"].endswith("scene/views/u00_v00.png")
    assert record["lfrig"]["rectification"]["stage"] == "stage.json"
    k_pose = np.array([[200.0, 0, 19.0], [0, 200.0, 14.25], [0, 0, 1]])
    np.testing.assert_allclose(record["lfrig"]["M_pose_rect"], np.linalg.inv(k_pose) @ np.array(k_rect))

    manifest = tmp_path / "scene" / "manifest.jsonl"
    lines = manifest.read_text().splitlines()
    header = json.loads(lines[0])
    header["rectification"]["K_rect"] = [["a", "b"]]
    manifest.write_text("\n".join([json.dumps(header)] + lines[1:]) + "\n")
    assert main(["export", str(folder), "--poses", str(out)]) == 0
    assert "M_pose_rect" not in json.loads((out / "transforms.json").read_text())["lfrig"]
