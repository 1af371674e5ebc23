"""Points, normals and the cut mesh from depth maps (pure numpy; no open3d here)."""

from __future__ import annotations

import numpy as np
import pytest

from recon.cloud import (
    depth_mesh,
    depth_to_points,
    grid_triangles,
    jump_residual,
    neighbour_links,
    point_cloud,
    surface_breaks,
    triangle_normals,
)

FOCAL_PX = 100.0


def step_depth(height=12, width=16, near=1000.0, far=1500.0, split=7):
    """A fronto-parallel plane at ``near`` on the left (x < split) in front of one at ``far``."""
    depth = np.full((height, width), far)
    depth[:, :split] = near
    return depth


def test_back_projection_is_the_pinhole_model():
    depth = np.full((5, 7), 2000.0)
    points = depth_to_points(depth, focal_px=FOCAL_PX)
    # image centre (cx, cy) = (3, 2) lies on the optical axis
    np.testing.assert_allclose(points[2, 3], [0.0, 0.0, 2000.0])
    # one pixel right is + Z / f in X, one pixel down + Z / f in Y (x right, y down, z forward)
    np.testing.assert_allclose(points[2, 4], [20.0, 0.0, 2000.0])
    np.testing.assert_allclose(points[3, 3], [0.0, 20.0, 2000.0])
    shifted = depth_to_points(depth, focal_px=FOCAL_PX, principal_point_px=(0.0, 0.0))
    np.testing.assert_allclose(shifted[0, 0], [0.0, 0.0, 2000.0])


def test_cloud_leaves_out_untrustworthy_pixels():
    depth = step_depth()
    depth[2, 3] = np.nan
    depth[4, 5] = -1.0
    mask = np.ones(depth.shape, bool)
    mask[6, 6] = False
    image = np.zeros(depth.shape + (3,), np.uint8)
    image[..., 0] = 255
    cloud = point_cloud(depth, image, focal_px=FOCAL_PX, mask=mask)
    assert len(cloud) == depth.size - 3
    pixels = {tuple(p) for p in cloud.pixels}
    assert (2, 3) not in pixels and (4, 5) not in pixels and (6, 6) not in pixels
    assert cloud.points_mm.shape == cloud.normals.shape == cloud.colours.shape == (len(cloud), 3)
    np.testing.assert_allclose(cloud.colours, np.tile([1.0, 0.0, 0.0], (len(cloud), 1)))
    assert np.isfinite(cloud.points_mm).all() and np.isfinite(cloud.normals).all()


def test_normals_face_the_camera_and_match_a_slanted_plane():
    # plane Z = 1000 + 0.5 * X: normal proportional to (0.5, 0, -1) when facing the camera
    height, width = 9, 11
    ys, xs = np.indices((height, width), dtype=float)
    x_over_z = (xs - (width - 1) / 2) / FOCAL_PX
    depth = 1000.0 / (1.0 - 0.5 * x_over_z)
    cloud = point_cloud(depth, focal_px=FOCAL_PX)
    expected = np.array([0.5, 0.0, -1.0]) / np.sqrt(1.25)
    np.testing.assert_allclose(cloud.normals, np.tile(expected, (len(cloud), 1)), atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", cloud.normals, cloud.points_mm) < 0)


def test_normals_on_a_step_come_from_each_pixels_own_surface():
    cloud = point_cloud(step_depth(), focal_px=FOCAL_PX)
    np.testing.assert_allclose(cloud.normals, np.tile([0.0, 0.0, -1.0], (len(cloud), 1)), atol=1e-9)


def test_isolated_pixel_gets_the_line_of_sight_normal():
    depth = np.full((5, 5), np.nan)
    depth[1, 3] = 800.0
    cloud = point_cloud(depth, focal_px=FOCAL_PX)
    point = cloud.points_mm[0]
    np.testing.assert_allclose(cloud.normals[0], -point / np.linalg.norm(point))


def test_links_cut_at_the_step():
    right, down = neighbour_links(step_depth(split=7), max_relative_jump=0.05)
    assert not right[:, 6].any()  # pixel x = 6 (near) and x = 7 (far) are not connected
    assert right[:, :6].all() and right[:, 7:].all() and down.all()


def test_mesh_has_no_triangle_across_the_depth_jump():
    height, width, split = 12, 16, 7
    rng = np.random.default_rng(3)
    depth = step_depth(height, width, split=split) * (1 + 0.002 * rng.standard_normal((height, width)))
    mesh = depth_mesh(depth, focal_px=FOCAL_PX)
    z = mesh.vertices_mm[mesh.triangles][..., 2]  # (M, 3) vertex depths
    near = z < 1250.0
    assert np.all(near.all(axis=1) | (~near).all(axis=1)), "a triangle joins foreground and background"
    # both sides are fully triangulated otherwise
    assert len(mesh.triangles) == 2 * (height - 1) * (split - 1) + 2 * (height - 1) * (width - split - 1)
    assert len(mesh.vertices_mm) == height * width


def test_mesh_triangles_face_the_camera():
    ys, xs = np.indices((8, 10), dtype=float)
    depth = 1000.0 + 3.0 * xs + 2.0 * ys
    mesh = depth_mesh(depth, focal_px=FOCAL_PX)
    faces = triangle_normals(mesh.vertices_mm, mesh.triangles)
    centres = mesh.vertices_mm[mesh.triangles].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", faces, centres) < 0)
    assert len(mesh.triangles) == 2 * 7 * 9
    # and the vertex normals agree with the faces around them
    assert np.all(np.einsum("ij,ij->i", faces, mesh.normals[mesh.triangles[:, 0]]) > 0.99)


def test_a_missing_corner_still_leaves_one_triangle():
    depth = np.full((2, 2), 1000.0)
    depth[0, 0] = np.nan
    triangles = grid_triangles(depth)
    assert triangles.tolist() == [[1, 2, 3]]  # b c d


def test_mesh_drops_isolated_pixels_but_cloud_keeps_them():
    depth = np.full((6, 6), 1000.0)
    depth[:, 3] = np.nan
    depth[2, 5] = 3000.0  # floats alone in the far distance
    mesh = depth_mesh(depth, focal_px=FOCAL_PX)
    cloud = point_cloud(depth, focal_px=FOCAL_PX)
    assert len(cloud) == 36 - 6
    assert (2, 5) not in {tuple(p) for p in mesh.pixels}
    assert mesh.triangles.max() == len(mesh.vertices_mm) - 1
    assert len(mesh.vertices_mm) == len(cloud) - 1


@pytest.mark.parametrize("bad", [np.zeros(5), np.zeros((2, 3, 3))])
def test_depth_must_be_a_map(bad):
    with pytest.raises(ValueError, match="depth_mm"):
        point_cloud(bad, focal_px=FOCAL_PX)


# --------------------------------------------------------------------------------------------------
# breaks judged on the disparity against its local slope (issue 23: the estimate's edges ramp)

RIG_FOCAL_PX, RIG_PITCH_MM = 3000.0, 0.6  # focal_px * pitch_mm = 1800, as the simulated rig's


def ramped_step(height=10, width=24, far_px=1.9, near_px=2.0, ramp=(0.025, 0.05, 0.075), start=10, seed=None):
    """Depth (mm) of a far plane (x < start) and a near one, the disparity between them spread over
    ``len(ramp)`` pixels as an estimate spreads an edge: each one-pixel step far below 5 % of depth."""
    disparity = np.full((height, width), near_px)
    disparity[:, :start] = far_px
    for k, fraction in enumerate(ramp):
        disparity[:, start + k] = far_px + fraction / 0.1 * (near_px - far_px)
    if seed is not None:
        disparity += 0.0002 * np.random.default_rng(seed).standard_normal(disparity.shape)
    return RIG_FOCAL_PX * RIG_PITCH_MM / disparity


@pytest.mark.parametrize("ramp", [(0.05,), (0.033, 0.067), (0.025, 0.05, 0.075)])
def test_an_edge_ramped_over_a_few_pixels_is_cut(ramp):
    depth = ramped_step(ramp=ramp, seed=5)
    steps = np.abs(np.diff(depth, axis=1)) / np.minimum(depth[:, 1:], depth[:, :-1])
    assert steps.max() < 0.05  # the relative depth test alone joins every pixel
    mesh = depth_mesh(depth, focal_px=RIG_FOCAL_PX)
    z = mesh.vertices_mm[mesh.triangles][..., 2]
    # far 947.4 mm, near 900 mm: no triangle spans even a third of that
    assert (z.max(axis=1) - z.min(axis=1)).max() < 5.0, "a triangle hangs across the edge"
    # both planes stay meshed up to the ramp: the far side's x < 10, the near side's x >= 10 + len(ramp)
    far_cells = 2 * (depth.shape[0] - 1) * (10 - 1)
    near_cells = 2 * (depth.shape[0] - 1) * (depth.shape[1] - 10 - len(ramp) - 1)
    assert len(mesh.triangles) >= far_cells + near_cells
    # the normals beside the cut come from each pixel's own plane (fronto-parallel: straight at the camera)
    cloud = point_cloud(ramped_step(ramp=ramp), focal_px=RIG_FOCAL_PX)  # without noise
    flat = (cloud.pixels[:, 1] < 10) | (cloud.pixels[:, 1] >= 10 + len(ramp))
    assert np.all(cloud.normals[flat] @ np.array([0.0, 0.0, -1.0]) > 0.999)


@pytest.mark.parametrize("tilt", [0.0, 6.0, 20.0])
def test_a_steep_plane_stays_whole(tilt):
    """Z = Z0 + tilt * X (+ tilt / 2 * Y): each pixel steps ``tilt`` footprints deeper, up to 87 deg
    from facing the camera, with a little noise; nothing is cut."""
    height, width = 16, 20
    ys, xs = np.indices((height, width), dtype=float)
    slope = tilt * (xs - (width - 1) / 2) / RIG_FOCAL_PX + tilt / 2 * (ys - (height - 1) / 2) / RIG_FOCAL_PX
    depth = 1000.0 / (1.0 - slope)
    depth *= 1 + 1e-5 * np.random.default_rng(1).standard_normal(depth.shape)
    mesh = depth_mesh(depth, focal_px=RIG_FOCAL_PX)
    assert len(mesh.triangles) == 2 * (height - 1) * (width - 1)
    right, down = surface_breaks(depth, focal_px=RIG_FOCAL_PX)
    assert not right.any() and not down.any()


def test_a_band_two_pixels_wide_stays_joined_along_itself():
    depth = np.full((12, 14), 1000.0)
    depth[5:7, :] = 900.0  # a thin rod in front of a wall
    right, down = neighbour_links(depth, focal_px=RIG_FOCAL_PX)
    assert right.all()
    assert down[5].all()  # the rod's two rows
    assert not down[4].any() and not down[6].any()  # rod and wall are not joined


def test_a_spike_off_the_surface_is_not_joined():
    depth = np.full((9, 9), 1000.0)
    depth[4, 4] = 1010.0  # 30 footprints behind its neighbours, 1 % of depth
    right, down = neighbour_links(depth, focal_px=RIG_FOCAL_PX)
    assert not right[4, 3] and not right[4, 4] and not down[3, 4] and not down[4, 4]
    assert right.sum() == right.size - 2 and down.sum() == down.size - 2


def test_jump_residual_is_zero_on_any_plane_and_the_step_at_an_edge():
    ys, xs = np.indices((14, 12), dtype=float)
    plane = 0.3 * xs - 0.2 * ys + 1.0
    for axis in (0, 1):
        for span in (1, 3, 5):
            residual = jump_residual(plane, axis=axis, span_links=span)
            assert np.isfinite(residual).all()
            np.testing.assert_allclose(residual, 0.0, atol=1e-12)
    ys, xs = np.indices((7, 12), dtype=float)
    step = np.where(xs < 6, 1.0, 1.5)
    residual = jump_residual(step, axis=1, span_links=3)
    np.testing.assert_allclose(residual[:, 5], 0.5)
    np.testing.assert_allclose(np.delete(residual, 5, axis=1), 0.0)  # flat links beside a sharp step stay
