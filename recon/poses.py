"""The views' cameras for other tools: a COLMAP text model and a NeRF-style ``transforms.json``.

A rectified light field is, by construction, a grid of identical pinhole cameras that only
translate (``docs/conventions.md``, ``docs/calibration.md``): view ``(u, v)`` has focal length
``focal_px`` (square pixels), no rotation against the centre view, and its optical centre at::

    C(u, v) = ((v - v0) * pitch_mm, (u - u0) * pitch_mm, 0)      mm, centre camera frame

(x right, y down, z forward: the frame of lfrig's PLY files, so the exported cloud and the poses
fit together). Its principal point is the centre view's ``(cx, cy)`` shifted by ``((v - v0) * d0,
(u - u0) * d0)``, where ``d0`` is the light field's refocusing offset (a benchmark scene's shifted
sensors; 0 for a capture). A point at depth ``Z`` then appears in view ``(u, v)`` displaced by
``-(u - u0) * d`` in y and ``-(v - v0) * d`` in x with ``d = focal_px * pitch_mm / Z - d0``, the
disparity of ``docs/conventions.md``.

``pitch_mm`` is what the light field records: for a capture rectified with a stage calibration
(``lfrig rectify --stage stage.json``) the stage's true step, for other captures the commanded
pitch, for a benchmark scene its baseline. For a rectified capture the rectification is recorded
too, with ``M_pose_rect``: the rectification's ``K`` absorbs the stage's residual axis skew and the
difference of its two pitch errors, so the pose frame is the metric rectified frame times this
near-identity matrix (``x_pose = M_pose_rect @ x_rect``; ``x_cam = R_rect_cam.T @ x_rect`` is the raw
camera's frame).

Files (:func:`export_poses`):

Both formats put the centre of the top-left pixel at ``(0.5, 0.5)`` (lfrig at ``(0, 0)``), so their
principal points are lfrig's plus 0.5 px.

- ``cameras.txt``, ``images.txt``, ``points3D.txt``: COLMAP's text model. Cameras are ``PINHOLE
  fx fy cx cy`` (one, or one per view when ``d0 != 0``); images carry the world-to-camera pose as
  the quaternion ``qw qx qy qz`` (the identity) and ``t = -C`` in mm, and an empty line of 2D points;
  points are the back-projected trusted pixels of the disparity map (a seeded sample), without
  tracks.
- ``transforms.json``: ``camera_angle_x``, ``camera_angle_y``, ``fl_x``, ``fl_y``, ``cx``, ``cy``,
  ``w``, ``h``, zero distortion, and ``frames`` with ``file_path`` (relative to the file) and a
  4x4 camera-to-world ``transform_matrix`` in the OpenGL camera convention NeRF uses (camera x
  right, y up, looking along -z): ``[[1, 0, 0, Cx], [0, -1, 0, Cy], [0, 0, -1, Cz], [0, 0, 0, 1]]``
  in the world frame above (mm). Per-frame ``cx``/``cy`` when ``d0 != 0``. An ``lfrig`` key
  records units, frame, grid, pitch and the rectification.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from recon.camera import Camera
from recon.errors import ExportError

#: Points written to ``points3D.txt`` at most (a seeded sample of the trusted pixels).
MAX_POINTS = 50_000
COLMAP_FILES = ("cameras.txt", "images.txt", "points3D.txt")
TRANSFORMS_JSON = "transforms.json"
#: COLMAP and NeRF tools put the centre of the top-left pixel at (0.5, 0.5), lfrig at (0, 0): their
#: principal point is lfrig's plus this.
PIXEL_ORIGIN_SHIFT_PX = 0.5
#: NeRF's camera axes (x right, y up, z backwards) in lfrig's camera frame (x right, y down, z forward).
OPENGL_FROM_LFRIG = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class ViewPose:
    """One view's camera.

    Attributes
    ----------
    u, v
        Grid row and column.
    number
        Row-major view number ``u * V + v`` (the benchmark's ``input_CamNNN``).
    name
        The view's file, relative to the light-field folder.
    centre_mm
        ``(3,)`` optical centre in the centre camera frame, mm.
    principal_point_px
        ``(cx, cy)`` of this view, pixels.
    """

    u: int
    v: int
    number: int
    name: str
    centre_mm: np.ndarray
    principal_point_px: tuple[float, float]

    @property
    def image_id(self) -> int:
        """COLMAP's image id: the row-major view number plus one (COLMAP ids start at 1)."""
        return self.number + 1


def view_poses(*, grid: tuple[int, int], camera: Camera, image_size: tuple[int, int],
               names: list[str] | None = None) -> list[ViewPose]:
    """The cameras of a ``grid = (U, V)`` light field of ``image_size = (W, H)`` views, row-major.

    ``names[u * V + v]`` is view ``(u, v)``'s file (default lfrig's capture layout, ``views/uUU_vVV.png``).
    """
    from recon.lf.capture import view_name

    rows, cols = (int(n) for n in grid)
    if rows < 1 or cols < 1:
        raise ValueError(f"grid must be (rows, cols) >= 1; got {grid!r}")
    width, height = (int(n) for n in image_size)
    if names is not None and len(names) != rows * cols:
        raise ValueError(f"{len(names)} names for a {rows}x{cols} grid")
    cx, cy = camera.principal_point((height, width))
    u0, v0 = rows // 2, cols // 2
    d0, pitch = camera.disparity_offset, camera.pitch_mm
    poses = []
    for u in range(rows):
        for v in range(cols):
            number = u * cols + v
            name = names[number] if names is not None else view_name(u, v)
            poses.append(ViewPose(u=u, v=v, number=number, name=name,
                                  centre_mm=np.array([(v - v0) * pitch, (u - u0) * pitch, 0.0]),
                                  principal_point_px=(cx + (v - v0) * d0, cy + (u - u0) * d0)))
    return poses


def camera_to_world_opengl(pose: ViewPose) -> np.ndarray:
    """``(4, 4)`` camera-to-world matrix of ``pose`` with NeRF's (OpenGL's) camera axes."""
    matrix = np.eye(4)
    matrix[:3, :3] = OPENGL_FROM_LFRIG  # the views are not rotated against the centre camera
    matrix[:3, 3] = pose.centre_mm
    return matrix


# --------------------------------------------------------------------------------------------------
# the files
# --------------------------------------------------------------------------------------------------


def colmap_text(poses: list[ViewPose], *, focal_px: float, image_size: tuple[int, int],
                points_mm: np.ndarray | None = None, colours: np.ndarray | None = None) -> dict[str, str]:
    """COLMAP's ``cameras.txt``, ``images.txt`` and ``points3D.txt`` as text.

    ``points_mm`` ``(N, 3)`` and ``colours`` ``(N, 3)`` uint8 go to ``points3D.txt`` (no tracks).
    """
    width, height = (int(n) for n in image_size)
    shared = len({p.principal_point_px for p in poses}) == 1
    cameras = ["# Camera list with one line of data per camera:",
               "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]  (PINHOLE: fx, fy, cx, cy; pixels)",
               f"# Number of cameras: {1 if shared else len(poses)}"]
    images = ["# Image list with two lines of data per image:",
              "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME  (world to camera; mm)",
              "#   POINTS2D[] as (X, Y, POINT3D_ID)",
              f"# Number of images: {len(poses)}, mean observations per image: 0"]
    for pose in poses:
        camera_id = 1 if shared else pose.image_id
        if not shared or pose is poses[0]:
            cx, cy = (c + PIXEL_ORIGIN_SHIFT_PX for c in pose.principal_point_px)
            cameras.append(f"{camera_id} PINHOLE {width} {height} {focal_px:.10g} {focal_px:.10g} {cx:.10g} {cy:.10g}")
        tx, ty, tz = (-c + 0.0 for c in pose.centre_mm)  # t = -R C with R the identity
        images.append(f"{pose.image_id} 1 0 0 0 {tx:.10g} {ty:.10g} {tz:.10g} {camera_id} {pose.name}")
        images.append("")
    points = ["# 3D point list with one line of data per point:",
              "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)  (mm)"]
    count = 0 if points_mm is None else len(points_mm)
    points.append(f"# Number of points: {count}, mean track length: 0")
    if count:
        rgb = np.full((count, 3), 200, np.uint8) if colours is None else np.asarray(colours, np.uint8)
        points += [f"{k + 1} {x:.6f} {y:.6f} {z:.6f} {r} {g} {b} 0"
                   for k, ((x, y, z), (r, g, b)) in enumerate(zip(np.asarray(points_mm, np.float64).tolist(), rgb.tolist()))]
    return {"cameras.txt": "\n".join(cameras) + "\n", "images.txt": "\n".join(images) + "\n",
            "points3D.txt": "\n".join(points) + "\n"}


def transforms(poses: list[ViewPose], *, focal_px: float, image_size: tuple[int, int], paths: list[str],
               extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The NeRF-style ``transforms.json`` object; ``paths[k]`` is frame ``k``'s ``file_path``."""
    width, height = (int(n) for n in image_size)
    rows, cols = max(p.u for p in poses) + 1, max(p.v for p in poses) + 1
    centre = poses[(rows // 2) * cols + cols // 2]  # its principal point is the light field's
    cx, cy = (c + PIXEL_ORIGIN_SHIFT_PX for c in centre.principal_point_px)
    shared = len({p.principal_point_px for p in poses}) == 1
    frames = []
    for pose, path in zip(poses, paths):
        frame: dict[str, Any] = {"file_path": path, "transform_matrix": camera_to_world_opengl(pose).tolist(),
                                 "colmap_im_id": pose.image_id, "lfrig_uv": [pose.u, pose.v]}
        if not shared:
            frame["cx"], frame["cy"] = (c + PIXEL_ORIGIN_SHIFT_PX for c in pose.principal_point_px)
        frames.append(frame)
    return {
        "camera_model": "OPENCV",
        "camera_angle_x": 2.0 * math.atan(width / (2.0 * focal_px)),
        "camera_angle_y": 2.0 * math.atan(height / (2.0 * focal_px)),
        "fl_x": focal_px, "fl_y": focal_px, "cx": cx, "cy": cy, "w": width, "h": height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
        "lfrig": extra or {},
    }


@dataclass
class PosesSummary:
    """What :func:`export_poses` wrote."""

    folder: Path
    views: int
    points: int
    source_found: bool
    rectified: bool

    def __str__(self) -> str:
        text = (f"{self.folder}: COLMAP text model ({', '.join(COLMAP_FILES)}) and {TRANSFORMS_JSON}, "
                f"{self.views} views, {self.points} points")
        if self.rectified:
            text += "; pitch from the stage calibration the capture was rectified with"
        if not self.source_found:
            text += "; the light-field folder was not found, image names follow lfrig's capture layout"
        return text


def _source_layout(source: Path | None, grid: tuple[int, int]) -> tuple[list[str] | None, dict[str, Any]]:
    """The views' file names in the light-field folder and its capture header (``{}`` for none)."""
    rows, cols = grid
    if source is None or not source.is_dir():
        return None, {}
    from recon.lf.benchmark import BENCHMARK_VIEW
    from recon.lf.capture import MANIFEST, view_name

    if (source / MANIFEST).is_file():
        header: dict[str, Any] = {}
        try:
            with open(source / MANIFEST, encoding="utf-8") as f:
                first = json.loads(f.readline())
            header = first if isinstance(first, dict) else {}
        except (OSError, ValueError):
            header = {}
        return [view_name(u, v) for u in range(rows) for v in range(cols)], header
    numbered = {int(m[1]): m[0] for m in (BENCHMARK_VIEW.match(p.name) for p in source.iterdir()) if m}
    if len(numbered) >= rows * cols:
        return [numbered.get(k, f"input_Cam{k:03d}.png") for k in range(rows * cols)], {}
    return None, {}


def result_grid(result) -> tuple[int, int]:
    """``(rows, cols)`` of the light field a reconstruction folder came from (``result.json`` → ``grid``).

    Raises
    ------
    ExportError
        When ``result.json`` does not record it as two positive integers.
    """
    from recon.result import RESULT_JSON

    grid = result.record.grid
    if not (isinstance(grid, list) and len(grid) == 2
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in grid)):
        what = "records no grid" if grid is None else f"has grid = {grid!r}, not [rows, cols]"
        raise ExportError(f"{result.path / RESULT_JSON} {what}; the poses need the light field's grid "
                          "(run lfrig reconstruct again to record it)")
    return int(grid[0]), int(grid[1])


def export_poses(result, out_dir, *, camera: Camera, max_points: int = MAX_POINTS, seed: int = 0) -> PosesSummary:
    """Write the views' cameras of a reconstruction folder (:func:`recon.result.read_result`) into
    ``out_dir`` (created if missing): COLMAP's text model and ``transforms.json``.

    ``camera`` is the folder's (with any overrides); the grid and image size come from
    ``result.json``, the file names from the light-field folder ``source`` (when it is found).
    ``points3D.txt`` holds at most ``max_points`` trusted pixels (:func:`recon.export.trusted_pixels`),
    back-projected, with the centre view's colours.

    Raises
    ------
    ExportError
        When ``result.json`` records no grid, or ``out_dir`` cannot be written.
    """
    from recon.cloud import depth_to_points, valid_depth
    from recon.export import trusted_pixels
    from recon.lf.imageio import write_bytes_atomic
    from recon.result import source_folder

    record = result.record
    grid = result_grid(result)
    height, width = result.disparity_px.shape
    source = source_folder(result.path, record)
    names, header = _source_layout(source, (grid[0], grid[1]))
    poses = view_poses(grid=(grid[0], grid[1]), camera=camera, image_size=(width, height), names=names)

    keep = trusted_pixels(result.disparity_px, confidence=result.confidence, search_range=result.search_range)
    if result.mask is not None:
        keep &= result.mask
    depth = camera.depth_mm(result.disparity_px.astype(np.float64))
    chosen = np.flatnonzero(valid_depth(depth, mask=keep))
    if len(chosen) > max_points:
        chosen = np.sort(np.random.default_rng(seed).choice(chosen, max_points, replace=False))
    points = depth_to_points(depth, focal_px=camera.focal_px, principal_point_px=camera.principal_point_px)
    points = points.reshape(-1, 3)[chosen]
    colours = None
    if result.image is not None:
        from recon.report.figures import as_rgb8

        colours = as_rgb8(result.image).reshape(-1, 3)[chosen]

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ExportError(f"{out}: cannot create the poses folder ({error.strerror})") from None
    rectification = header.get("rectification") if isinstance(header.get("rectification"), dict) else None
    extra: dict[str, Any] = {
        "units": "mm",
        "world_frame": "the centre view's camera frame: x right, y down, z forward (lfrig's PLY files)",
        "camera_convention": "transform_matrix is camera-to-world with OpenGL camera axes: x right, y up, "
                             "looking along -z",
        "grid": [grid[0], grid[1]], "pitch_mm": camera.pitch_mm, "focal_px": camera.focal_px,
        "disparity_offset": camera.disparity_offset,
        "source": None if source is None else str(source),
        "pitch_from": "stage calibration (rectified capture)" if rectification else "the light field's pitch",
    }
    if rectification:
        extra["rectification"] = rectification
        try:
            k_rect = np.asarray(rectification.get("K_rect", []), dtype=float)
        except (TypeError, ValueError):  # a damaged header: the poses do not need it
            k_rect = np.zeros(0)
        if k_rect.shape == (3, 3) and np.isfinite(k_rect).all():
            cx, cy = camera.principal_point((height, width))
            k_pose = np.array([[camera.focal_px, 0.0, cx], [0.0, camera.focal_px, cy], [0.0, 0.0, 1.0]])
            extra["M_pose_rect"] = (np.linalg.inv(k_pose) @ k_rect).tolist()
    if source is not None and names is not None:
        paths = [Path(os.path.relpath(source.resolve() / name, out.resolve())).as_posix() for name in names]
    else:
        paths = [pose.name for pose in poses]
    texts = colmap_text(poses, focal_px=camera.focal_px, image_size=(width, height), points_mm=points,
                        colours=colours)
    texts[TRANSFORMS_JSON] = json.dumps(transforms(poses, focal_px=camera.focal_px, image_size=(width, height),
                                                   paths=paths, extra=extra), indent=1) + "\n"
    for name, text in texts.items():
        target = out / name
        if target.is_symlink():
            raise ExportError(f"{target}: is a symbolic link; lfrig does not write through links, remove it first")
        write_bytes_atomic(target, text.encode("utf-8"))
    return PosesSummary(folder=out, views=len(poses), points=len(points), source_found=names is not None,
                        rectified=rectification is not None)
