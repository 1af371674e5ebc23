"""The fake camera renders what its truth says: mrcal projection, parallax, occlusion, seeded noise."""

from __future__ import annotations

import json

import cv2
import mrcal
import numpy as np
import pytest

from rig.errors import RigError
from rig.fakecam import FakeCamera, FakeRig, rectified_geometry
from rig.render import (
    NoiseTexture,
    Rect,
    Scene,
    board_corners_world,
    chessboard_scene,
    default_scene,
    pack_scene,
    render_rays_numba,
    render_rays_numpy,
)
from rig.protocols import Camera


@pytest.fixture(scope="module")
def cam4():
    """The default (lightly misaligned, distorted) rig at binning 4: 320x245."""
    return FakeCamera(binning=4)


def test_is_a_camera_and_reports_settings(cam4):
    assert isinstance(cam4, Camera)
    settings = cam4.settings()
    json.dumps(settings)
    assert (settings["width"], settings["height"]) == (320, 245)
    assert settings["pixel_size_um"] == pytest.approx(4.8 * 4)


def test_default_geometry_is_the_papers_rig():
    rig = FakeRig()
    assert rig.sensor_size_px == (1280, 980)
    assert rig.focal_px == pytest.approx(35 / 0.0048)
    cam = FakeCamera()
    assert cam.image_size == (1280, 980)


def test_model_is_an_mrcal_model_consistent_with_rendered_depth(cam4):
    """Every pixel's ray, cut at the rendered depth, projects back onto that pixel."""
    position = (0.7, -1.1, 0.0)
    depth = cam4.depth_map(position)
    h, w = depth.shape
    assert np.all(np.isfinite(depth)) and 899.0 < depth.min() and depth.max() < 1001.0
    ys, xs = np.mgrid[0:h:7, 0:w:7]
    q = np.stack([xs, ys], axis=-1).reshape(-1, 2).astype(float)
    model = cam4.model
    assert model.intrinsics()[0] == "LENSMODEL_OPENCV8"
    v = mrcal.unproject(q, *model.intrinsics())
    p_cam = v / v[:, 2:] * depth[ys, xs].reshape(-1, 1)
    world = p_cam @ cam4.R_cam_stage + cam4.rig.camera_centre(position)
    np.testing.assert_allclose(cam4.project(world, position), q, atol=1e-6)


def test_binning_and_roi_describe_the_same_rays():
    full = FakeCamera()
    binned = FakeCamera(binning=2)
    roi = FakeCamera(binning=2, roi=(100, 50, 200, 150))
    points = np.array([[10.0, -20.0, 950.0], [-60.0, 40.0, 1000.0]])
    q_full = full.project(points, (0, 0, 0))
    q_bin = binned.project(points, (0, 0, 0))
    np.testing.assert_allclose(q_bin, (q_full + 0.5) / 2 - 0.5, atol=1e-9)
    np.testing.assert_allclose(roi.project(points, (0, 0, 0)), q_bin - [100, 50], atol=1e-9)
    assert roi.trigger().shape == (150, 200, 3)


def test_board_corners_render_where_the_model_projects_them():
    """OpenCV finds the rendered chessboard's corners within a few hundredths of a pixel of truth."""
    scene = chessboard_scene(inner=(9, 6), square_mm=12.0, centre_mm=(3.0, -4.0, 900.0),
                             rotation_deg=(8.0, -12.0, 4.0))
    cam = FakeCamera(binning=2, scene=scene, colour=False)
    image = cam.trigger()
    found, corners = cv2.findChessboardCornersSB(image, (9, 6), flags=cv2.CALIB_CB_ACCURACY)
    assert found
    corners = corners.reshape(6, 9, 2)
    truth = cam.project(board_corners_world(scene), cam.rig.ref_mm)
    if np.linalg.norm(corners[0, 0] - truth[0, 0]) > np.linalg.norm(corners[0, 0] - truth[-1, -1]):
        corners = corners[::-1, ::-1]  # OpenCV may start from the opposite corner
    err = np.linalg.norm(corners - truth, axis=-1)
    assert err.max() < 0.1
    assert np.sqrt(np.mean(err**2)) < 0.04


@pytest.mark.parametrize("z_mm", [900.0, 1000.0])
def test_point_at_depth_moves_by_the_expected_disparity(z_mm):
    """Ideal rig: one pitch along stage x (y) shifts a point at depth Z by -f p / Z in image x (y)."""
    cam = FakeCamera(rig=FakeRig.ideal(), binning=2)
    f, pitch = cam.focal_px, 0.5
    point = np.array([[12.0, -7.0, z_mm]])
    q0 = cam.project(point, (0, 0, 0))
    np.testing.assert_allclose(cam.project(point, (pitch, 0, 0)) - q0, [[-f * pitch / z_mm, 0]], atol=1e-9)
    np.testing.assert_allclose(cam.project(point, (0, 2 * pitch, 0)) - q0, [[0, -2 * f * pitch / z_mm]], atol=1e-9)
    truth = cam.rectified_truth(pitch_mm=pitch)
    assert truth["pitch_mm"] == pytest.approx(pitch)
    assert np.nanmax(truth["disparity_px"]) == pytest.approx(f * pitch / 900.0, rel=1e-6)  # the rod
    assert np.nanmin(truth["disparity_px"]) == pytest.approx(f * pitch / 1000.0, rel=1e-6)  # the backdrop


def test_rendered_images_show_the_disparity():
    """Corners of a fronto-parallel board at 950 mm, found in two rendered views 2 mm apart, move by
    f * 2 / 950 px (ideal rig)."""
    z = 950.0
    scene = chessboard_scene(inner=(7, 5), square_mm=10.0, centre_mm=(0.0, 0.0, z))
    cam = FakeCamera(rig=FakeRig.ideal(), binning=2, scene=scene, colour=False)
    found0, c0 = cv2.findChessboardCornersSB(cam.frame((0, 0, 0)), (7, 5), flags=cv2.CALIB_CB_ACCURACY)
    found1, c1 = cv2.findChessboardCornersSB(cam.frame((2.0, 0, 0)), (7, 5), flags=cv2.CALIB_CB_ACCURACY)
    assert found0 and found1
    shift = (c1 - c0).reshape(-1, 2)
    assert np.mean(shift[:, 0]) == pytest.approx(-cam.focal_px * 2.0 / z, abs=0.02)
    assert np.abs(np.mean(shift[:, 1])) < 0.02


def test_rectified_geometry_makes_steps_pure_translations():
    rig = FakeRig.misaligned()
    cam = FakeCamera(rig=rig, binning=4)
    su, sv = cam.grid_steps_cam(pitch_mm=0.5)
    geo = rectified_geometry(su, sv, focal_px=cam.focal_px, centre_px=(160.0, 122.0))
    rng = np.random.default_rng(3)
    points = rng.uniform([-50, -40, 900], [50, 40, 1000], (20, 3))  # camera frame at the centre view
    z_rect = (points @ geo.R_rect_cam.T)[:, 2]
    d = geo.focal_px * geo.pitch_mm / z_rect

    def pix(p):
        r = p @ geo.R_rect_cam.T @ geo.K_rect.T
        return r[:, :2] / r[:, 2:]

    q0 = pix(points)
    for ku, kv in [(1, 0), (0, 1), (-3, 4), (4, -4)]:
        q = pix(points - ku * su - kv * sv)
        np.testing.assert_allclose(q, q0 - np.stack([kv * d, ku * d], axis=1), atol=1e-9)
    # the misalignment is really there: without rectification the step has a cross component
    step_raw = cam.project(np.array([[0.0, 0.0, 950.0]]), (0.5, 0, 0)) - cam.project(np.array([[0.0, 0.0, 950.0]]), (0, 0, 0))
    assert abs(step_raw[0, 1]) > 0.01


def test_rig_errors_are_what_they_say():
    rig = FakeRig.misaligned()
    A = rig.stage_matrix
    assert np.linalg.norm(A[:, 0]) == pytest.approx(1.004)
    assert np.linalg.norm(A[:, 1]) == pytest.approx(0.997)
    angle = np.degrees(np.arccos(A[:, 0] @ A[:, 1] / np.linalg.norm(A[:, 0]) / np.linalg.norm(A[:, 1])))
    assert angle == pytest.approx(90 - 0.3)
    R = rig.R_cam_stage
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.degrees(np.arccos(R[2, 2])) == pytest.approx(np.hypot(0.45, 0.6), rel=0.01)  # tilt


def test_occlusion_order(cam4):
    """The rod (900 mm) hides box A (930 mm), which hides the backdrop (1000 mm); nearer surfaces
    shift more between views."""
    scene = default_scene()
    rod = scene.find("rod")
    on_rod = np.array([[rod.centre_mm[0], -18.0, 900.0]])  # the rod crosses box A at y = -18
    behind = np.array([[rod.centre_mm[0], -18.0, 930.0]])
    x, y = np.rint(cam4.project(on_rod, (0, 0, 0))[0]).astype(int)
    depth = cam4.depth_map((0, 0, 0))
    assert depth[y, x] == pytest.approx(900.0, abs=0.5)
    image = cam4.render((0, 0, 0))
    rod_colour = pack_scene(scene).shade[scene.rects.index(rod)] * np.array(rod.texture.colour)
    np.testing.assert_allclose(image[y, x], rod_colour, atol=1e-9)
    # one millimetre to the right, the rod moves 8 % further left than box A behind it
    shift_rod = cam4.project(on_rod, (1.0, 0, 0)) - cam4.project(on_rod, (0, 0, 0))
    shift_box = cam4.project(behind, (1.0, 0, 0)) - cam4.project(behind, (0, 0, 0))
    assert shift_rod[0, 0] < shift_box[0, 0] < 0
    # box A's front face at the box centre, backdrop far right
    xb, yb = np.rint(cam4.project(np.array([[48.0, -18.0, 930.0]]), (0, 0, 0))[0]).astype(int)
    assert depth[yb, xb] == pytest.approx(930.0, abs=1.0)
    assert depth[5, -5] == pytest.approx(1000.0, abs=1.0)
    # moving the stage right makes the rod's pixel see box A again, never the backdrop
    depth_moved = cam4.depth_map((1.0, 0, 0))
    assert depth_moved[y, x] == pytest.approx(930.0, abs=1.0)


def test_noise_is_seeded_by_seed_and_position():
    kwargs = dict(binning=8, noise_sigma=0.01, seed=7)
    a = FakeCamera(**kwargs).frame((0.5, 0, 0))
    b = FakeCamera(**kwargs).frame((0.5, 0, 0))
    np.testing.assert_array_equal(a, b)
    c = FakeCamera(**{**kwargs, "seed": 8}).frame((0.5, 0, 0))
    d = FakeCamera(**kwargs).frame((1.0, 0, 0))
    clean = FakeCamera(binning=8).frame((0.5, 0, 0))
    assert not np.array_equal(a, c) and not np.array_equal(a, d)
    noise = a.astype(float) - clean
    assert np.std(noise) == pytest.approx(0.01 * 255, rel=0.1)


def test_trigger_follows_the_stage_and_refuses_while_moving():
    position = [0.0, 0.0, 0.0]
    moving = [False]
    cam = FakeCamera(lambda: tuple(position), binning=8, is_moving=lambda: moving[0], bit_depth=16, colour=False)
    first = cam.trigger()
    assert first.dtype == np.uint16 and first.shape == (122, 160)
    position[0] = 2.0
    second = cam.trigger()
    assert not np.array_equal(first, second)
    np.testing.assert_array_equal(second, cam.frame((2.0, 0.0, 0.0)))
    moving[0] = True
    with pytest.raises(RigError, match="moving"):
        cam.trigger()
    cam.close()
    moving[0] = False
    with pytest.raises(RigError, match="closed"):
        cam.trigger()


def test_numba_and_numpy_engines_agree(cam4):
    scene = Scene(default_scene().rects + chessboard_scene(centre_mm=(0, 0, 1200)).rects)
    packed = pack_scene(scene)
    rng = np.random.default_rng(0)
    dirs = cam4._centre_dirs_world().reshape(-1, 3)[rng.choice(320 * 245, 4000, replace=False)]
    origin = np.array([0.3, -0.2, 0.0])
    for blur_angle in (0.0, 2e-4):
        ref = render_rays_numpy(origin, dirs, 1e-3, packed, blur_angle)
        fast = render_rays_numba(origin, dirs, 1e-3, packed, blur_angle)
        np.testing.assert_array_equal(ref[2], fast[2])
        np.testing.assert_allclose(ref[1], fast[1], rtol=1e-12)
        np.testing.assert_allclose(ref[0], fast[0], atol=1e-9)
    slow_cam = FakeCamera(binning=8, engine="numpy")
    fast_cam = FakeCamera(binning=8)
    np.testing.assert_allclose(slow_cam.render((1, 2, 0)), fast_cam.render((1, 2, 0)), atol=1e-9)


def test_texture_filtering_keeps_a_flat_region_flat_and_supersampling_only_touches_edges():
    """A uniform plane renders as a constant; supersampling changes only pixels near edges."""
    flat = Scene((Rect("wall", (0, 0, 1000.0), (1, 0, 0), (0, 1, 0), (500, 500),
                       NoiseTexture(contrast=0.0, colour0=(0.5, 0.5, 0.5), colour1=(0.5, 0.5, 0.5))),),
                 ambient=1.0)
    img = FakeCamera(binning=8, scene=flat).render((0, 0, 0))
    assert np.ptp(img) < 1e-12
    a = FakeCamera(binning=8, supersample=1).render((0, 0, 0))
    b = FakeCamera(binning=8, supersample=3).render((0, 0, 0))
    changed = np.abs(a - b).max(axis=-1) > 1e-9
    assert 0 < changed.mean() < 0.15
