"""What made lfrig's intrinsics less accurate than plain OpenCV's (issue 12), pinned on small cases.

The full comparison is ``bench/calibration.py`` (figures in ``docs/calibration.md``). Here:

- a board OpenCV's classic detector finds but ``findChessboardCornersSB`` does not (strongly
  foreshortened squares) is found, and its corners are refined to the truth;
- refined corners on the issue's setup (f = 7000 px, blur 0.6 px, noise 2 grey levels) are within
  hundredths of a pixel of the truth (larger refinement windows where the squares allow);
- the solve on exact corners reproduces the true lens (mrcal's regularisation, sized for corners
  with about a pixel of noise, biased it by 0.05 px before the corners were weighted by their noise),
  and reports residuals in pixels.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.intrinsics import (Board, calibrate_intrinsics, detect_corners, projection_difference, refine_corners,
                              refine_radii)
from rig.fakecam import FakeCamera, FakeRig, calibration_poses
from rig.render import board_corners_world, chessboard_scene

BOARD = Board(10, 7, 10.0)  # 11x8 squares of 10 mm


@pytest.fixture(scope="module")
def camera() -> FakeCamera:
    """The issue's camera: 1280x980, f = 7000 px, OPENCV8 (~3 px of barrel distortion in the corners)."""
    rig = FakeRig(focal_mm=7000 * 4.8e-3, rotation_deg=(0.0, 0.0, 0.0))
    return FakeCamera(rig=rig, colour=False, supersample=2, blur_px=0.6, noise_sigma=2 / 255, seed=3)


def corner_errors(camera: FakeCamera, scene, corners: np.ndarray) -> np.ndarray:
    truth = camera.project(board_corners_world(scene), camera.rig.ref_mm)
    if np.linalg.norm(corners[0, 0, :2] - truth[0, 0]) > np.linalg.norm(corners[0, 0, :2] - truth[-1, -1]):
        truth = truth[::-1, ::-1]
    return np.linalg.norm(corners[..., :2] - truth, axis=-1)


def test_a_foreshortened_board_the_sector_detector_misses_is_found(camera):
    # Tilted 55 deg: the squares are thin rhombi (bench/calibration.py, case "steep", board 13).
    scene = chessboard_scene(inner=(BOARD.cols, BOARD.rows), square_mm=BOARD.square_mm,
                             centre_mm=(-37.36, 0.43, 1006.07), rotation_deg=(-43.58, 54.66, -9.53))
    image = camera.frame(camera.rig.ref_mm, scene=scene)
    found_sb, _ = cv2.findChessboardCornersSB(image, (BOARD.cols, BOARD.rows), flags=cv2.CALIB_CB_EXHAUSTIVE)
    assert not found_sb, "precondition: OpenCV's sector-based detector misses this board"
    corners = detect_corners(image, BOARD)
    assert corners is not None
    err = corner_errors(camera, scene, corners)
    assert np.sqrt(np.mean(err**2)) < 0.03 and err.max() < 0.1


def test_refined_corners_are_within_a_hundredth_of_a_pixel(camera):
    scene = chessboard_scene(inner=(BOARD.cols, BOARD.rows), square_mm=BOARD.square_mm,
                             centre_mm=(12.0, -8.0, 950.0), rotation_deg=(22.0, -18.0, 6.0))
    corners = detect_corners(camera.frame(camera.rig.ref_mm, scene=scene), BOARD)
    err = corner_errors(camera, scene, corners)
    # 6 px windows (the old cap) give 0.015 px RMS here; the noise sets the floor
    assert np.sqrt(np.mean(err**2)) < 0.011 and err.max() < 0.035


def test_refinement_windows_follow_the_squares():
    square = np.stack(np.meshgrid(np.arange(4) * 60.0, np.arange(3) * 60.0), axis=-1)
    assert np.all(refine_radii(square) == 16)                  # capped
    assert np.all(refine_radii(square * 0.2) == 4)             # 12 px squares: a third
    sheared = square.copy()
    sheared[..., 0] += square[..., 1] * 3.0                    # rhombi 60 px high, 190 px long
    assert np.all(refine_radii(sheared) == 6)                  # height / 3, not side / 3
    partial = square.copy()
    partial[0, 0] = np.nan                                     # ChArUco: a corner not seen
    assert refine_radii(partial).shape == (12,) and np.all(refine_radii(partial) == 16)


@pytest.fixture(scope="module")
def exact_views(camera):
    """``(N, rows, cols, 3)`` exact projections of 25 board poses (no images rendered)."""
    poses = calibration_poses(camera, count=25, inner=(BOARD.cols, BOARD.rows), square_mm=BOARD.square_mm, seed=0)
    views = []
    for centre, rot in poses:
        scene = chessboard_scene(inner=(BOARD.cols, BOARD.rows), square_mm=BOARD.square_mm, centre_mm=centre,
                                 rotation_deg=rot)
        q = camera.project(board_corners_world(scene), camera.rig.ref_mm)
        views.append(np.concatenate([q, np.ones(q.shape[:2] + (1,))], axis=-1))
    return np.stack(views)


def test_the_solve_on_exact_corners_reproduces_the_lens(camera, exact_views):
    result = calibrate_intrinsics(exact_views, board=BOARD, image_size=camera.image_size, working_distance_mm=950.0)
    diff = projection_difference(result.model, camera.model, distance_mm=950.0)
    assert np.median(diff) < 0.004 and diff.max() < 0.006  # regularisation at weight 1: 0.011 / 0.052


def test_noisy_corners_are_weighted_and_residuals_stay_in_pixels(camera, exact_views):
    rng = np.random.default_rng(5)
    noisy = exact_views.copy()
    noisy[..., :2] += rng.normal(0.0, 0.02, noisy[..., :2].shape)
    result = calibrate_intrinsics(noisy, board=BOARD, image_size=camera.image_size, working_distance_mm=950.0)
    assert result.rms_px == pytest.approx(0.02, rel=0.15)
    assert np.all(result.observations[..., 2][result.observations[..., 2] > 0] > 10)  # weight ~ 1 / 0.02 px
    # within a few sigma of mrcal's own uncertainty (0.018 px here), which is in pixels too
    assert 0.012 < result.uncertainty_px["median"] < 0.025
    diff = projection_difference(result.model, camera.model, distance_mm=950.0)
    assert np.median(diff) < 0.05 and diff.max() < 0.15


def test_windows_shrink_near_the_image_edge():
    # an ideal X-junction at (4.3, 40.6), 4 px from the left edge: a 16 px window does not fit
    from scipy.special import erf

    y, x = np.mgrid[0:80, 0:80].astype(float)
    image = np.rint(120 + 80 * erf((x - 4.3) / 1.2) * erf((y - 40.6) / 1.2)).astype(np.uint8)
    refined = refine_corners(image, np.array([[5.0, 41.0]]), radius=16)
    # a 3 px window fits: 0.05 px (a 16 px window would not, and the start, 0.76 px off, was kept)
    assert np.linalg.norm(refined[0] - (4.3, 40.6)) < 0.08
