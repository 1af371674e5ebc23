"""A simulated camera on a simulated stage that renders a known 3D scene exactly.

:class:`FakeCamera` implements :class:`rig.protocols.Camera`. Each :meth:`FakeCamera.trigger` asks
the stage (a callable returning the read-back position in mm) where the camera is and ray-casts the
scene from there, through a distorted pinhole camera whose truth *is* an mrcal camera model. Every
quantity a later step estimates is exposed as truth: the camera model, ``R_cam_stage``, the stage's
real motion per commanded mm, depth maps, and the disparity of the ideal rectified light field.

Frames (``docs/conventions.md``)
--------------------------------
- **Stage frame**: orthonormal, x along the stage's real x motion, y in the plane of the real x and
  y motions, z completing a right-handed frame. The **world frame** is the stage frame translated so
  that the camera's centre of projection is at the origin when the stage is at ``rig.ref_mm``.
  Scenes are given in world coordinates in mm; the camera looks roughly along +z.
- Commanding a stage move by ``delta_mm`` (x, y, z) moves the camera by ``stage_matrix @ delta_mm``
  in the world frame (columns: the real displacement per commanded mm of each axis, which carries
  the pitch error and the skew between the x and y axes).
- ``R_cam_stage`` maps world (stage-frame) vectors into the camera frame (x right, y down, z along the
  optical axis). The camera never rotates: a stage translation only moves its centre.
- Pixels: ``(x, y)`` for mrcal, row 0 at the top, pixel centres at integer coordinates.

With ``R_cam_stage = I`` stage +x moves the camera to the image's right and stage +y moves it down,
so a capture grid that follows the conventions maps view column ``v`` to stage x and view row ``u``
to stage y: ``position = centre + ((v - v0) * pitch, (u - u0) * pitch, 0)``.

The scene and its renderer are :mod:`rig.render`.

Default geometry: the paper's rig, a 1280x980 detector with 4.8 um pixels (a common machine-vision
pixel pitch; the paper does not state it) behind a 35 mm lens, so ``focal_px = 35 / 0.0048 =
7291.7``; a 0.5 mm pitch; objects between 0.9 and 1.0 m, where one view step is a disparity of
3.6-4.1 px (half that with ``binning=2``).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from rig.errors import RigError
from rig.render import (ENGINES, Packed, Scene, chessboard_scene, default_scene, pack_scene, render_image,
                        rotation_from_vector)

# ----------------------------------------------------------------------------------------------
# The rig: camera and stage, as they really are
# ----------------------------------------------------------------------------------------------

#: OPENCV8 coefficients ``(k1, k2, p1, p2, k3, k4, k5, k6)`` of the default lens: about 3 px of
#: barrel distortion in the corners of the full 1280x980 detector, plus a little decentring.
DEFAULT_DISTORTION = (-0.35, 0.9, 2.0e-4, -1.5e-4, 0.0, 0.0, 0.0, 0.0)

#: The smallest image side the fake camera renders (pixels), whatever the binning.
MIN_IMAGE_PX = 8


@dataclass(frozen=True)
class FakeRig:
    """The true geometry of the simulated camera and stage.

    Attributes
    ----------
    sensor_size_px
        ``(width, height)`` of the full detector in pixels.
    pixel_size_um
        Pixel pitch of the detector in micrometres (unbinned).
    focal_mm
        Focal length of the lens in mm; ``focal_px = focal_mm / pixel_size``.
    aspect
        ``fy / fx`` (1 for square pixels).
    principal_offset_px
        Offset ``(dx, dy)`` of the principal point from the detector's centre in unbinned pixels.
    lensmodel
        An mrcal lens model name: ``LENSMODEL_PINHOLE`` or ``LENSMODEL_OPENCV4/5/8``.
    distortion
        The model's distortion coefficients (truncated or zero-padded to the model's count).
    rotation_deg
        ``R_cam_stage`` as a rotation vector in degrees, ``(rx, ry, rz)``: ``rz`` is the in-plane
        rotation of the image against the stage axes, ``rx`` and ``ry`` tilt the optical axis away
        from the stage's z axis (i.e. the stage's xy plane is not perpendicular to the optical axis).
    scale_error
        Real over commanded displacement minus one for stage axes x, y, z (``+0.004`` is a pitch 0.4 %
        too long).
    skew_deg
        Angle by which the stage's real y motion departs from perpendicular to its x motion, towards +x.
    ref_mm
        Stage position (x, y, z in mm) at which the camera's centre sits at the world origin.
    """

    sensor_size_px: tuple[int, int] = (1280, 980)
    pixel_size_um: float = 4.8
    focal_mm: float = 35.0
    aspect: float = 1.0
    principal_offset_px: tuple[float, float] = (4.0, -3.0)
    lensmodel: str = "LENSMODEL_OPENCV8"
    distortion: tuple[float, ...] = DEFAULT_DISTORTION
    rotation_deg: tuple[float, float, float] = (0.2, -0.15, 0.5)
    scale_error: tuple[float, float, float] = (0.0, 0.0, 0.0)
    skew_deg: float = 0.0
    ref_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def ideal(cls, **overrides: Any) -> "FakeRig":
        """A perfect rig: no distortion, stage axes parallel to the image axes, exact pitch."""
        base = dict(
            principal_offset_px=(0.0, 0.0),
            lensmodel="LENSMODEL_PINHOLE",
            distortion=(),
            rotation_deg=(0.0, 0.0, 0.0),
            scale_error=(0.0, 0.0, 0.0),
            skew_deg=0.0,
        )
        base.update(overrides)
        return cls(**base)

    @classmethod
    def misaligned(cls, **overrides: Any) -> "FakeRig":
        """The calibration issue's test rig: 1.5 deg in-plane rotation, 0.3 deg skew, about 0.6 deg
        tilt, pitch errors of +0.4 % (x) and -0.3 % (y), and the default distortion."""
        base = dict(rotation_deg=(0.45, -0.6, 1.5), scale_error=(0.004, -0.003, 0.0), skew_deg=0.3)
        base.update(overrides)
        return cls(**base)

    @property
    def focal_px(self) -> float:
        """Focal length in unbinned pixels (x)."""
        return self.focal_mm / (self.pixel_size_um * 1e-3)

    @property
    def R_cam_stage(self) -> np.ndarray:
        """``(3, 3)`` rotation mapping stage (world) vectors into the camera frame."""
        return rotation_from_vector(np.deg2rad(np.asarray(self.rotation_deg, dtype=float)))

    @property
    def stage_matrix(self) -> np.ndarray:
        """``(3, 3)``: column ``j`` is the real world displacement (mm) per commanded mm of axis ``j``."""
        ex, ey, ez = self.scale_error
        skew = math.radians(self.skew_deg)
        return np.array(
            [
                [1.0 + ex, (1.0 + ey) * math.sin(skew), 0.0],
                [0.0, (1.0 + ey) * math.cos(skew), 0.0],
                [0.0, 0.0, 1.0 + ez],
            ]
        )

    def camera_centre(self, position_mm: Sequence[float]) -> np.ndarray:
        """World coordinates (mm) of the camera's centre when the stage reads ``position_mm``."""
        delta = np.asarray(position_mm, dtype=float) - np.asarray(self.ref_mm, dtype=float)
        return self.stage_matrix @ delta

    def intrinsics(self, *, binning: int = 1, roi: tuple[int, int, int, int] | None = None) -> tuple[str, np.ndarray]:
        """``(lensmodel, intrinsics)`` in mrcal's form for the binned (and cropped) image.

        Binning by ``b`` divides the focal lengths by ``b`` and maps a pixel centre ``c`` to
        ``(c + 0.5) / b - 0.5``; an ROI ``(x0, y0, w, h)`` in binned pixels shifts the centre.
        Distortion acts on normalised coordinates and is unchanged.
        """
        width, height = self.sensor_size_px
        fx = self.focal_px / binning
        fy = fx * self.aspect
        cx = ((width - 1) / 2 + self.principal_offset_px[0] + 0.5) / binning - 0.5
        cy = ((height - 1) / 2 + self.principal_offset_px[1] + 0.5) / binning - 0.5
        if roi is not None:
            cx -= roi[0]
            cy -= roi[1]
        n_dist = _num_distortions(self.lensmodel)
        dist = np.zeros(n_dist)
        given = np.asarray(self.distortion, dtype=float)[:n_dist]
        dist[: given.size] = given
        return self.lensmodel, np.concatenate([[fx, fy, cx, cy], dist])


def _num_distortions(lensmodel: str) -> int:
    counts = {"LENSMODEL_PINHOLE": 0, "LENSMODEL_OPENCV4": 4, "LENSMODEL_OPENCV5": 5, "LENSMODEL_OPENCV8": 8}
    if lensmodel not in counts:
        raise ValueError(f"lensmodel must be one of {sorted(counts)}; got {lensmodel!r}")
    return counts[lensmodel]


def calibration_poses(camera: "FakeCamera", *, count: int, inner: tuple[int, int] = (10, 7),
                      square_mm: float = 10.0, distance_mm: tuple[float, float] = (800.0, 1100.0),
                      tilt_deg: float = 30.0, seed: int = 0,
                      position_mm: Sequence[float] | None = None) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
    """Board poses ``(centre_mm, rotation_deg)`` for :func:`chessboard_scene` that a calibration
    would use: the board whole in the picture (2 % border), its centre visiting a 3x3 grid of image
    positions in turn (so the corners of the imager are covered), at random distances in
    ``distance_mm`` and tilted by up to ``tilt_deg`` about the board's axes (alternating sign), with
    a little in-plane rotation. Seeded and deterministic.
    """
    import mrcal

    rng = np.random.default_rng(seed)
    position = camera.rig.ref_mm if position_mm is None else position_mm
    w, h = camera.image_size
    targets = [(fx, fy) for fy in (0.3, 0.5, 0.7) for fx in (0.3, 0.5, 0.7)]
    targets = targets[4:5] + targets[:4] + targets[5:]  # centre first
    poses = []
    for k in range(count):
        fx, fy = targets[k % len(targets)]
        for attempt in range(200):
            shrink = min(attempt // 40, 4) * 0.05  # move towards the centre if it keeps not fitting
            q = np.array([(0.5 + (fx - 0.5) * (1 - 4 * shrink)) * (w - 1), (0.5 + (fy - 0.5) * (1 - 4 * shrink)) * (h - 1)])
            z = rng.uniform(*distance_mm)
            ray = mrcal.unproject(q, camera.lensmodel, camera.intrinsics, normalize=True)
            centre = camera.rig.camera_centre(position) + camera.R_cam_stage.T @ (ray * z / ray[2])
            sign = 1.0 if k % 2 == 0 else -1.0
            rot = (sign * rng.uniform(0.3, 1.0) * tilt_deg, -sign * rng.uniform(0.3, 1.0) * tilt_deg,
                   rng.uniform(-10.0, 10.0))
            scene = chessboard_scene(inner=inner, square_mm=square_mm, centre_mm=centre, rotation_deg=rot)
            rect = scene.rects[0]
            ha, hb = rect.half_size_mm
            outline = rect.world_from_local(np.array([[-ha, -hb], [ha, -hb], [ha, hb], [-ha, hb]]))
            p = camera.camera_points(outline, position)
            if np.any(p[:, 2] <= 0):
                continue
            qo = camera.project(outline, position)
            if np.all((qo[:, 0] > 0.02 * w) & (qo[:, 0] < 0.98 * w) & (qo[:, 1] > 0.02 * h) & (qo[:, 1] < 0.98 * h)):
                poses.append((tuple(float(c) for c in centre), tuple(float(r) for r in rot)))
                break
        else:
            raise ValueError(f"no board pose fits the {w}x{h} image at {distance_mm} mm; use a smaller board "
                             "or larger distances")
    return poses


# ----------------------------------------------------------------------------------------------
# Rectified ideal (the truth that calibration + rectification should reproduce)
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RectifiedGeometry:
    """The ideal rectified camera of a capture grid.

    ``R_rect_cam`` maps camera-frame vectors into the rectified frame, whose x axis is along the
    grid's column step (``v``) and whose z axis is perpendicular to both steps, on the camera's side.
    ``K_rect`` (``(3, 3)``, upper triangular) is chosen so that a point at rectified depth ``Z_mm``
    moves by exactly ``-(u - u0) * d`` in y and ``-(v - v0) * d`` in x, with
    ``d = focal_px * pitch_mm / Z_mm`` (``docs/conventions.md``).
    """

    R_rect_cam: np.ndarray
    K_rect: np.ndarray
    focal_px: float
    pitch_mm: float
    step_u_cam_mm: np.ndarray
    step_v_cam_mm: np.ndarray


def rectified_geometry(step_u_cam_mm: np.ndarray, step_v_cam_mm: np.ndarray, *, focal_px: float,
                       centre_px: tuple[float, float]) -> RectifiedGeometry:
    """Ideal rectification of a grid whose view steps are ``step_u_cam_mm``/``step_v_cam_mm``
    (``(3,)`` camera-frame displacement of the camera per grid row / column, mm).

    With ``tv = |step_v|`` and the ``u`` step ``(a, b, 0)`` in the rectified frame,
    ``pitch_mm = sqrt(tv * b)``, ``fx = focal_px * pitch_mm / tv``, ``fy = focal_px * pitch_mm / b`` and
    the skew ``-fx * a / b`` make both steps exact translations of ``d`` pixels.
    """
    su = np.asarray(step_u_cam_mm, dtype=float)
    sv = np.asarray(step_v_cam_mm, dtype=float)
    x = sv / np.linalg.norm(sv)
    z = np.cross(sv, su)
    z /= np.linalg.norm(z)
    if z[2] <= 0:
        raise ValueError("the grid's u and v steps are mirrored against the image axes (v x u points "
                         "backwards); swap the stage axes that the grid rows/columns map to")
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    su_r = R @ su
    tv = float(np.linalg.norm(sv))
    a, b = float(su_r[0]), float(su_r[1])
    pitch = math.sqrt(tv * b)
    fx = focal_px * pitch / tv
    fy = focal_px * pitch / b
    K = np.array([[fx, -fx * a / b, centre_px[0]], [0.0, fy, centre_px[1]], [0.0, 0.0, 1.0]])
    return RectifiedGeometry(R, K, float(focal_px), pitch, su, sv)


# ----------------------------------------------------------------------------------------------
# The camera
# ----------------------------------------------------------------------------------------------

class FakeCamera:
    """A simulated camera whose frame depends on the simulated stage's position.

    Parameters
    ----------
    position_mm
        Callable returning the stage's read-back position ``(x, y, z)`` in mm; it is called once per
        :meth:`trigger`. ``None`` keeps the camera at ``rig.ref_mm``.
    rig
        The true camera and stage geometry (:class:`FakeRig`); defaults to a lightly misaligned rig.
    scene
        What the camera sees (:func:`default_scene` by default).
    binning
        Integer binning of the detector (1, 2, 4, ...): ``binning=2`` gives 640x490 from 1280x980.
    roi
        ``(x0, y0, width, height)`` in binned pixels, or ``None`` for the full (binned) detector.
    supersample
        Samples per pixel along each axis at edges between surfaces (anti-aliasing of occlusions).
    blur_px
        Standard deviation (pixels) of the lens's Gaussian point spread function, applied to the
        textures analytically. Some blur is what real lenses have, and it band-limits the image so
        that sub-pixel corner detectors are unbiased (with 0, edges are one-pixel ramps and
        gradient-based corner refinement has phase errors of ~0.08 px).
    noise_sigma
        Standard deviation of additive Gaussian noise in units of full scale (0 = noise-free).
    seed
        Seeds the noise. The noise of a frame depends only on ``seed`` and the stage position, so a
        view taken again (a resumed capture) is bit-identical.
    bit_depth
        8 or 16: frames are ``uint8`` or ``uint16``.
    colour
        RGB ``(H, W, 3)`` frames if true, else luminance ``(H, W)``.
    exposure_us, gain
        Brightness scales linearly with ``exposure_us / 10000 * gain`` (reported by :meth:`settings`).
    is_moving
        Optional callable; if it returns true at :meth:`trigger`, :class:`rig.errors.RigError` is
        raised (a frame during motion is a bug of the capture loop).
    engine
        ``"numba"`` (default) or ``"numpy"`` (the reference).
    """

    def __init__(self, position_mm: Callable[[], Sequence[float]] | None = None, *,
                 rig: FakeRig | None = None, scene: Scene | None = None, binning: int = 1,
                 roi: tuple[int, int, int, int] | None = None, supersample: int = 2, blur_px: float = 0.5,
                 noise_sigma: float = 0.0, seed: int = 0, bit_depth: int = 8, colour: bool = True,
                 exposure_us: float = 10000.0, gain: float = 1.0,
                 is_moving: Callable[[], bool] | None = None, engine: str = "numba") -> None:
        self.rig = rig if rig is not None else FakeRig()
        self.scene = scene if scene is not None else default_scene()
        if int(binning) != binning or binning < 1:
            raise ValueError(f"binning must be a positive integer; got {binning!r}")
        if bit_depth not in (8, 16):
            raise ValueError(f"bit_depth must be 8 or 16; got {bit_depth!r}")
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {sorted(ENGINES)}; got {engine!r}")
        if int(supersample) != supersample or supersample < 1:
            raise ValueError(f"supersample must be a positive integer; got {supersample!r}")
        full_w = self.rig.sensor_size_px[0] // binning
        full_h = self.rig.sensor_size_px[1] // binning
        if full_w < MIN_IMAGE_PX or full_h < MIN_IMAGE_PX:
            raise ValueError(f"binning {binning} leaves a {full_w}x{full_h} image of the "
                             f"{self.rig.sensor_size_px[0]}x{self.rig.sensor_size_px[1]} detector; give a binning "
                             f"of at most {min(self.rig.sensor_size_px) // MIN_IMAGE_PX}")
        if not (math.isfinite(noise_sigma) and 0 <= noise_sigma <= 1):
            raise ValueError(f"noise_sigma must be from 0 to 1 of full scale; got {noise_sigma!r}")
        if roi is not None:
            x0, y0, w, h = (int(v) for v in roi)
            if x0 < 0 or y0 < 0 or w < 1 or h < 1 or x0 + w > full_w or y0 + h > full_h:
                raise ValueError(f"roi {roi!r} does not fit the {full_w}x{full_h} binned detector")
            roi = (x0, y0, w, h)
            self.image_size = (w, h)
        else:
            self.image_size = (full_w, full_h)
        self.binning = int(binning)
        self.roi = roi
        self.supersample = int(supersample)
        if not blur_px >= 0:
            raise ValueError(f"blur_px must be >= 0; got {blur_px!r}")
        self.blur_px = float(blur_px)
        self.noise_sigma = float(noise_sigma)
        self.seed = int(seed)
        self.bit_depth = int(bit_depth)
        self.colour = bool(colour)
        self.exposure_us = float(exposure_us)
        self.gain = float(gain)
        self.engine = engine
        self._position = position_mm
        self._is_moving = is_moving
        self._ray_cache: dict[str, np.ndarray] = {}
        self._packed_cache: dict[int, tuple[Scene, Packed]] = {}
        self.frames_taken = 0
        self._closed = False

    # -- truth ------------------------------------------------------------------------------

    @property
    def lensmodel(self) -> str:
        return self.rig.lensmodel

    @property
    def intrinsics(self) -> np.ndarray:
        """mrcal intrinsics vector ``(fx, fy, cx, cy, distortions...)`` of the frames (truth)."""
        return self.rig.intrinsics(binning=self.binning, roi=self.roi)[1]

    @property
    def model(self):
        """The true camera model as an ``mrcal.cameramodel`` (identity extrinsics)."""
        import mrcal

        return mrcal.cameramodel(intrinsics=(self.lensmodel, self.intrinsics),
                                 imagersize=np.array(self.image_size),
                                 rt_cam_ref=np.zeros(6))

    @property
    def focal_px(self) -> float:
        """Focal length in pixels of the frames (x)."""
        return float(self.intrinsics[0])

    @property
    def R_cam_stage(self) -> np.ndarray:
        return self.rig.R_cam_stage

    def project(self, points_mm: np.ndarray, position_mm: Sequence[float]) -> np.ndarray:
        """Pixel coordinates ``(..., 2)`` (x, y) of world points ``(..., 3)`` (mm) seen with the stage
        at ``position_mm`` (no occlusion test)."""
        import mrcal

        p_cam = self.camera_points(points_mm, position_mm)
        return mrcal.project(p_cam, self.lensmodel, self.intrinsics)

    def camera_points(self, points_mm: np.ndarray, position_mm: Sequence[float]) -> np.ndarray:
        """World points ``(..., 3)`` in the camera frame (mm) with the stage at ``position_mm``."""
        p = np.asarray(points_mm, dtype=float) - self.rig.camera_centre(position_mm)
        return p @ self.R_cam_stage.T

    def grid_steps_cam(self, *, pitch_mm: float, u_axis: Sequence[float] = (0, 1, 0),
                       v_axis: Sequence[float] = (1, 0, 0)) -> tuple[np.ndarray, np.ndarray]:
        """True camera displacement ``(3,)`` in the camera frame (mm) per grid row (``u``) and column
        (``v``) step, for a grid that commands ``pitch_mm`` along the stage axes ``u_axis``/``v_axis``."""
        A = self.rig.stage_matrix
        R = self.R_cam_stage
        su = R @ A @ (pitch_mm * np.asarray(u_axis, dtype=float))
        sv = R @ A @ (pitch_mm * np.asarray(v_axis, dtype=float))
        return su, sv

    def rectified_truth(self, *, pitch_mm: float = 0.5, centre_mm: Sequence[float] | None = None,
                        u_axis: Sequence[float] = (0, 1, 0), v_axis: Sequence[float] = (1, 0, 0),
                        focal_px: float | None = None, centre_px: tuple[float, float] | None = None,
                        image_size: tuple[int, int] | None = None) -> dict[str, Any]:
        """Ground truth of the ideal rectified light field's centre view.

        The grid is centred on stage position ``centre_mm`` (default ``rig.ref_mm``) and commands
        ``pitch_mm`` per view along the stage axes ``u_axis`` (rows) and ``v_axis`` (columns). The
        rectification is :func:`rectified_geometry` of the true grid steps, with ``focal_px``
        (default: this camera's, ``sqrt(fx fy)``) and principal point ``centre_px`` (default: the
        image centre) for an image of ``image_size`` (default: this camera's).

        Returns a dict with ``geometry`` (:class:`RectifiedGeometry`), ``depth_mm`` (``(H, W)``,
        rectified z of the nearest surface through each pixel centre, NaN where none),
        ``disparity_px`` (``focal_px * pitch_mm / depth_mm``, pixels per view step, NaN where none),
        ``focal_px`` and ``pitch_mm`` (the true geometric-mean step of :func:`rectified_geometry`).
        """
        w, h = image_size if image_size is not None else self.image_size
        if centre_px is None:
            centre_px = ((w - 1) / 2, (h - 1) / 2)
        if focal_px is None:
            focal_px = float(np.sqrt(self.intrinsics[0] * self.intrinsics[1]))
        su, sv = self.grid_steps_cam(pitch_mm=pitch_mm, u_axis=u_axis, v_axis=v_axis)
        geo = rectified_geometry(su, sv, focal_px=focal_px, centre_px=centre_px)
        centre = self.rig.ref_mm if centre_mm is None else centre_mm
        depth = self.depth_in_rectified(geo.K_rect, geo.R_rect_cam, (w, h), centre)
        return {"geometry": geo, "depth_mm": depth, "disparity_px": focal_px * geo.pitch_mm / depth,
                "focal_px": focal_px, "pitch_mm": geo.pitch_mm}

    def depth_in_rectified(self, K_rect: np.ndarray, R_rect_cam: np.ndarray, image_size: tuple[int, int],
                           position_mm: Sequence[float]) -> np.ndarray:
        """True depth seen through any rectified camera: ``(H, W)`` mm, NaN where no surface.

        The rectified camera has intrinsics ``K_rect`` ``(3, 3)`` and orientation ``R_rect_cam``
        (camera frame -> rectified frame), is ``image_size = (W, H)`` pixels, and sits where this
        camera is when the stage reads ``position_mm``. Depth is the rectified frame's z of the
        nearest surface through each pixel centre: the truth for a light field rectified with an
        *estimated* calibration (``calib.rectify.Rectification``), not only the ideal one.
        """
        w, h = image_size
        d_rect = self._pinhole_dirs(np.asarray(K_rect, float), np.arange(w, dtype=float)[None, :],
                                    np.arange(h, dtype=float)[:, None])
        d_world = d_rect @ np.asarray(R_rect_cam, float) @ self.R_cam_stage  # R_cam_stage^T R_rect_cam^T d
        _, t, _ = ENGINES[self.engine](self.rig.camera_centre(position_mm), d_world.reshape(-1, 3),
                                        1.0 / float(K_rect[0][0]), self._packed(self.scene))
        depth = t.reshape(h, w) * d_rect[..., 2]
        depth[~np.isfinite(depth)] = np.nan
        return depth

    @staticmethod
    def _pinhole_dirs(K: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Unit rays ``(..., 3)`` of pixels ``(x, y)`` (broadcast) of the pinhole camera ``K``."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        q = np.stack([x, y, np.ones_like(x)], axis=-1)
        d = q @ np.linalg.inv(K).T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def render_rectified_ideal(self, *, grid_shape: tuple[int, int] = (9, 9), pitch_mm: float = 0.5,
                               centre_mm: Sequence[float] | None = None,
                               u_axis: Sequence[float] = (0, 1, 0), v_axis: Sequence[float] = (1, 0, 0),
                               focal_px: float | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """The ideal rectified light field ``(U, V, H, W, 3)`` float32 in ``[0, 1]`` (noise-free) and its
        :meth:`rectified_truth`: every view a distortion-free pinhole image taken from the true lattice
        position, so that scene points follow the pure translation model exactly."""
        truth = self.rectified_truth(pitch_mm=pitch_mm, centre_mm=centre_mm, u_axis=u_axis,
                                     v_axis=v_axis, focal_px=focal_px)
        geo = truth["geometry"]
        R_world_rect = (geo.R_rect_cam @ self.R_cam_stage).T
        w, h = self.image_size
        s = self.supersample
        offs = (np.arange(s) + 0.5) / s - 0.5
        centre_dirs = self._pinhole_dirs(geo.K_rect, np.arange(w)[None, :], np.arange(h)[:, None]) @ R_world_rect.T

        def sub_dirs(ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
            y = ys[:, None, None] + offs[None, :, None]
            x = xs[:, None, None] + offs[None, None, :]
            return self._pinhole_dirs(geo.K_rect, x, y) @ R_world_rect.T

        centre = np.asarray(self.rig.ref_mm if centre_mm is None else centre_mm, dtype=float)
        U, V = grid_shape
        views = np.empty((U, V, h, w, 3), dtype=np.float32)
        for u in range(U):
            for v in range(V):
                pos = (centre + (u - U // 2) * pitch_mm * np.asarray(u_axis, dtype=float)
                       + (v - V // 2) * pitch_mm * np.asarray(v_axis, dtype=float))
                rgb, _ = render_image(self.rig.camera_centre(pos), centre_dirs, sub_dirs,
                                      pixel_angle=1.0 / truth["focal_px"], supersample=s, blur_px=self.blur_px,
                                      packed=self._packed(self.scene), engine=self.engine)
                views[u, v] = rgb
        return views, truth

    def depth_map(self, position_mm: Sequence[float]) -> np.ndarray:
        """``(H, W)`` depth (camera-frame z, mm) of the nearest surface along each pixel centre's ray
        with the stage at ``position_mm``; NaN where the ray hits nothing."""
        dirs_world = self._centre_dirs_world()
        _, t, _ = ENGINES[self.engine](self.rig.camera_centre(position_mm), dirs_world.reshape(-1, 3),
                                        1.0 / self.focal_px, self._packed(self.scene))
        depth = t.reshape(dirs_world.shape[:2]) * (dirs_world @ self.R_cam_stage.T)[..., 2]
        depth[~np.isfinite(depth)] = np.nan
        return depth

    # -- rendering --------------------------------------------------------------------------

    def _centre_dirs_world(self) -> np.ndarray:
        """``(H, W, 3)`` unit world-frame rays through the pixel centres (mrcal unprojection, cached)."""
        if "centre" not in self._ray_cache:
            import mrcal

            w, h = self.image_size
            gx, gy = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
            v = mrcal.unproject(np.stack([gx, gy], axis=-1), self.lensmodel, self.intrinsics, normalize=True)
            self._ray_cache["centre"] = np.ascontiguousarray(v @ self.R_cam_stage)
        return self._ray_cache["centre"]

    def _sub_dirs_world(self, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        """``(M, s, s, 3)`` unit world-frame rays of the sub-pixel samples of pixels ``(ys, xs)``.

        The unprojections of the whole ``(H s, W s)`` sample grid are computed on first use and kept
        as float32 (direction error below 1e-7 rad, i.e. < 0.001 px)."""
        s = self.supersample
        if "sub" not in self._ray_cache:
            import mrcal

            w, h = self.image_size
            offs = (np.arange(s) + 0.5) / s - 0.5
            gx, gy = np.meshgrid((np.arange(w)[:, None] + offs).ravel(), (np.arange(h)[:, None] + offs).ravel())
            v = mrcal.unproject(np.stack([gx, gy], axis=-1), self.lensmodel, self.intrinsics, normalize=True)
            self._ray_cache["sub"] = (v @ self.R_cam_stage).astype(np.float32).reshape(h, s, w, s, 3)
        return self._ray_cache["sub"][ys, :, xs, :].astype(float)

    def _packed(self, scene: Scene) -> Packed:
        key = id(scene)
        cached = self._packed_cache.get(key)
        if cached is None or cached[0] is not scene:
            cached = (scene, pack_scene(scene))
            self._packed_cache[key] = cached
        return cached[1]

    def render(self, position_mm: Sequence[float], *, scene: Scene | None = None) -> np.ndarray:
        """Noise-free linear image ``(H, W, 3)`` float64 in ``[0, 1]`` with the stage at ``position_mm``
        (before exposure scaling, noise and quantisation); see :func:`render_image`."""
        scene = self.scene if scene is None else scene
        rgb, _ = render_image(self.rig.camera_centre(position_mm), self._centre_dirs_world(),
                              self._sub_dirs_world, pixel_angle=1.0 / self.focal_px, blur_px=self.blur_px,
                              supersample=self.supersample, packed=self._packed(scene), engine=self.engine)
        return rgb

    def frame(self, position_mm: Sequence[float], *, scene: Scene | None = None) -> np.ndarray:
        """The frame :meth:`trigger` returns with the stage at ``position_mm``: exposure, seeded noise,
        quantisation to ``bit_depth``, RGB or luminance."""
        img = self.render(position_mm, scene=scene) * (self.exposure_us / 10000.0 * self.gain)
        if not self.colour:
            img = img @ np.array([0.299, 0.587, 0.114])
        if self.noise_sigma > 0:
            img = img + self.noise_sigma * self._noise_rng(position_mm).standard_normal(img.shape)
        full = 255 if self.bit_depth == 8 else 65535
        out = np.clip(np.rint(img * full), 0, full)
        return out.astype(np.uint8 if self.bit_depth == 8 else np.uint16)

    def _noise_rng(self, position_mm: Sequence[float]) -> np.random.Generator:
        micrometres = np.rint(np.asarray(position_mm, dtype=float) * 1000).astype(np.int64)
        digest = hashlib.sha256(np.concatenate([[self.seed], micrometres]).astype("<i8").tobytes()).digest()
        return np.random.default_rng(int.from_bytes(digest[:16], "little"))

    # -- the Camera protocol ----------------------------------------------------------------

    def trigger(self) -> np.ndarray:
        """A new frame from the stage's current position (see :meth:`frame`)."""
        if self._closed:
            raise RigError("the fake camera is closed; open a new FakeCamera")
        if self._is_moving is not None and self._is_moving():
            raise RigError("fake camera triggered while the stage is moving; wait until the stage is "
                           "idle before triggering")
        position = self.rig.ref_mm if self._position is None else tuple(self._position())
        self.frames_taken += 1
        return self.frame(position)

    def settings(self) -> dict[str, Any]:
        """Everything that determines a frame, JSON-serialisable."""
        w, h = self.image_size
        return {
            "device": "fake",
            "width": w,
            "height": h,
            "binning": self.binning,
            "roi": list(self.roi) if self.roi is not None else None,
            "pixel_size_um": self.rig.pixel_size_um * self.binning,
            "focal_mm": self.rig.focal_mm,
            "exposure_us": self.exposure_us,
            "gain": self.gain,
            "bit_depth": self.bit_depth,
            "colour": self.colour,
            "supersample": self.supersample,
            "blur_px": self.blur_px,
            "noise_sigma": self.noise_sigma,
            "seed": self.seed,
            "lensmodel": self.lensmodel,
            "intrinsics": [float(v) for v in self.intrinsics],
        }

    def close(self) -> None:
        self._closed = True

    def __enter__(self) -> "FakeCamera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def with_scene(self, scene: Scene) -> "FakeCamera":
        """A camera identical to this one (same rig, sensor and cached rays) that sees ``scene``."""
        twin = FakeCamera.__new__(FakeCamera)
        twin.__dict__.update(self.__dict__)
        twin.scene = scene
        twin._packed_cache = {}
        return twin


__all__ = ["FakeCamera", "FakeRig", "RectifiedGeometry", "calibration_poses", "rectified_geometry"]
