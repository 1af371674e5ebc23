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

Rendering
---------
Each pixel is supersampled on an ``s x s`` grid; every sample's ray is the mrcal unprojection of the
sample position (computed once per camera and cached), rotated into the world frame, and intersected
with every rectangle of the scene; the nearest hit wins. Textures are band-limited and filtered
analytically with a box the size of the sample's footprint on the surface (sums of cosines, each
attenuated by ``sinc(f * footprint)``; the chessboard's edges are linear ramps of that width), so the
images are free of aliasing and corners and edges are unbiased. Samples are averaged per pixel, then
optional seeded Gaussian noise is added and the image is quantised.

Two engines do the ray casting and shading: ``"numpy"`` (the readable reference) and ``"numba"``
(the default, the same arithmetic in a compiled loop); ``tests/test_fakecam.py`` checks they agree.

Default geometry: the paper's rig, a 1280x980 detector with 4.8 um pixels (a common machine-vision
pixel pitch; the paper does not state it) behind a 35 mm lens, so ``focal_px = 35 / 0.0048 =
7291.7``; a 0.5 mm pitch; objects between 0.9 and 1.0 m, where one view step is a disparity of
3.6-4.1 px (half that with ``binning=2``).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from rig.errors import RigError

# ----------------------------------------------------------------------------------------------
# The rig: camera and stage, as they really are
# ----------------------------------------------------------------------------------------------

#: OPENCV8 coefficients ``(k1, k2, p1, p2, k3, k4, k5, k6)`` of the default lens: about 3 px of
#: barrel distortion in the corners of the full 1280x980 detector, plus a little decentring.
DEFAULT_DISTORTION = (-0.35, 0.9, 2.0e-4, -1.5e-4, 0.0, 0.0, 0.0, 0.0)


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


def rotation_from_vector(r: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rotation matrix of the rotation vector ``r`` (axis times angle in radians)."""
    r = np.asarray(r, dtype=float)
    angle = float(np.linalg.norm(r))
    if angle < 1e-15:
        return np.eye(3)
    k = r / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


# ----------------------------------------------------------------------------------------------
# The scene: textured rectangles
# ----------------------------------------------------------------------------------------------

TEXTURE_FLAT, TEXTURE_NOISE, TEXTURE_CHECKER = 0, 1, 2


@dataclass(frozen=True)
class NoiseTexture:
    """A band-limited random texture: ``0.5 + sum_k a_k cos(2 pi f_k . (a, b) + phi_k)``, clipped to
    ``[0, 1]``, mapped linearly from ``colour0`` (value 0) to ``colour1`` (value 1).

    ``band_cycles_per_mm`` bounds the spatial frequencies (log-uniform), amplitudes fall as ``f^-0.5``
    and are scaled to a standard deviation of ``contrast``.
    """

    seed: int = 0
    colour0: tuple[float, float, float] = (0.1, 0.1, 0.1)
    colour1: tuple[float, float, float] = (0.9, 0.9, 0.9)
    band_cycles_per_mm: tuple[float, float] = (0.02, 1.0)
    waves: int = 24
    contrast: float = 0.2

    def wave_table(self) -> np.ndarray:
        """``(waves, 5)``: ``(fa, fb, phase, amplitude, |f|)`` per cosine, frequencies in cycles/mm."""
        rng = np.random.default_rng(self.seed)
        lo, hi = self.band_cycles_per_mm
        freq = np.exp(rng.uniform(math.log(lo), math.log(hi), self.waves))
        angle = rng.uniform(0, math.pi, self.waves)
        phase = rng.uniform(0, 2 * math.pi, self.waves)
        amp = freq**-0.5
        amp *= self.contrast / math.sqrt(0.5 * float(np.sum(amp**2)))
        return np.stack([freq * np.cos(angle), freq * np.sin(angle), phase, amp, freq], axis=1)


@dataclass(frozen=True)
class CheckerTexture:
    """A chessboard with ``inner = (cols, rows)`` inner corners and ``square_mm`` squares, centred on
    the rectangle, dark (``dark``) in the corner squares, on a light (``light``) margin.

    Board coordinates: the rectangle's ``a`` axis runs along the columns, ``b`` along the rows; inner
    corner ``(i, j)`` (column ``i``, row ``j``) sits at ``a = (i + 1 - (cols + 1) / 2) * square_mm``,
    ``b = (j + 1 - (rows + 1) / 2) * square_mm``.
    """

    inner: tuple[int, int] = (10, 7)
    square_mm: float = 10.0
    dark: float = 0.08
    light: float = 0.92


@dataclass(frozen=True)
class FlatTexture:
    colour: tuple[float, float, float] = (0.5, 0.5, 0.5)


@dataclass(frozen=True)
class Rect:
    """A textured rectangle ``{centre + a * axis_a + b * axis_b : |a| <= half_a, |b| <= half_b}``.

    ``axis_a`` and ``axis_b`` are orthonormal (world frame); texture coordinates are ``(a, b)`` in mm.
    """

    name: str
    centre_mm: tuple[float, float, float]
    axis_a: tuple[float, float, float]
    axis_b: tuple[float, float, float]
    half_size_mm: tuple[float, float]
    texture: NoiseTexture | CheckerTexture | FlatTexture = field(default_factory=NoiseTexture)

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.axis_a, self.axis_b)

    def world_from_local(self, ab_mm: np.ndarray) -> np.ndarray:
        """World points (N, 3) of texture coordinates ``ab_mm`` (N, 2) on this rectangle."""
        ab = np.asarray(ab_mm, dtype=float)
        return (
            np.asarray(self.centre_mm)
            + ab[..., :1] * np.asarray(self.axis_a)
            + ab[..., 1:2] * np.asarray(self.axis_b)
        )


@dataclass(frozen=True)
class Scene:
    """Rectangles in world coordinates (mm), a background colour for rays that hit nothing, and a
    directional light (world frame) for Lambertian shading ``ambient + (1 - ambient) |n . l|``."""

    rects: tuple[Rect, ...]
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    light: tuple[float, float, float] = (-0.3, -0.5, -1.0)
    ambient: float = 0.65

    def find(self, name: str) -> Rect:
        for rect in self.rects:
            if rect.name == name:
                return rect
        raise KeyError(name)


def _unit(v: Sequence[float]) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float)
    a = a / np.linalg.norm(a)
    return (float(a[0]), float(a[1]), float(a[2]))


def box(name: str, *, centre_xy_mm: tuple[float, float], front_z_mm: float,
        size_mm: tuple[float, float, float], texture: Any) -> tuple[Rect, ...]:
    """Six faces of an axis-aligned box: front face at ``z = front_z_mm`` of ``size (w, h)`` around
    ``centre_xy_mm``, ``size[2]`` deep. The faces share the texture (texture coordinates per face)."""
    cx, cy = centre_xy_mm
    w, h, d = size_mm
    zc = front_z_mm + d / 2
    ex, ey, ez = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    return (
        Rect(f"{name}.front", (cx, cy, front_z_mm), ex, ey, (w / 2, h / 2), texture),
        Rect(f"{name}.back", (cx, cy, front_z_mm + d), ex, ey, (w / 2, h / 2), texture),
        Rect(f"{name}.left", (cx - w / 2, cy, zc), ez, ey, (d / 2, h / 2), texture),
        Rect(f"{name}.right", (cx + w / 2, cy, zc), ez, ey, (d / 2, h / 2), texture),
        Rect(f"{name}.top", (cx, cy - h / 2, zc), ex, ez, (w / 2, d / 2), texture),
        Rect(f"{name}.bottom", (cx, cy + h / 2, zc), ex, ez, (w / 2, d / 2), texture),
    )


def default_scene(*, seed: int = 0) -> Scene:
    """The standard test scene, all between 0.9 and 1.0 m in front of the reference position.

    - ``backdrop``: a textured wall at z = 1000 mm, larger than the field of view;
    - ``slant``: a plane turned 35 deg about the vertical, its depth running from about 945 to 985 mm;
    - ``boxA``: a 50 x 40 x 30 mm box with its front face at 930 mm, right of centre;
    - ``boxB``: a 26 x 22 x 20 mm box at 905 mm that partly covers the slanted plane;
    - ``rod``: a 2 mm wide vertical strip at 900 mm crossing box A (a thin structure).
    """
    s = seed * 101
    slant_angle = math.radians(35.0)
    slant_a = (math.cos(slant_angle), 0.0, math.sin(slant_angle))
    rects: list[Rect] = [
        Rect("backdrop", (0.0, 0.0, 1000.0), (1, 0, 0), (0, 1, 0), (200.0, 150.0),
             NoiseTexture(seed=s + 1, colour0=(0.15, 0.2, 0.35), colour1=(0.85, 0.85, 0.8))),
        Rect("slant", (-42.0, 12.0, 965.0), slant_a, (0, 1, 0), (30.0, 40.0),
             NoiseTexture(seed=s + 2, colour0=(0.35, 0.12, 0.05), colour1=(0.95, 0.8, 0.4),
                          band_cycles_per_mm=(0.05, 1.2))),
    ]
    rects += box("boxA", centre_xy_mm=(38.0, -18.0), front_z_mm=930.0, size_mm=(50.0, 40.0, 30.0),
                 texture=NoiseTexture(seed=s + 3, colour0=(0.05, 0.3, 0.1), colour1=(0.75, 0.95, 0.6)))
    rects += box("boxB", centre_xy_mm=(-22.0, 30.0), front_z_mm=905.0, size_mm=(26.0, 22.0, 20.0),
                 texture=NoiseTexture(seed=s + 4, colour0=(0.4, 0.05, 0.3), colour1=(1.0, 0.75, 0.9),
                                      band_cycles_per_mm=(0.1, 1.5)))
    rects.append(Rect("rod", (22.0, 0.0, 900.0), (1, 0, 0), (0, 1, 0), (1.0, 60.0),
                      FlatTexture((0.95, 0.95, 0.9))))
    return Scene(tuple(rects), background=(0.0, 0.0, 0.0))


def chessboard_scene(*, inner: tuple[int, int] = (10, 7), square_mm: float = 10.0,
                     centre_mm: Sequence[float] = (0.0, 0.0, 1000.0),
                     rotation_deg: Sequence[float] = (0.0, 0.0, 0.0), margin_mm: float | None = None,
                     background: tuple[float, float, float] = (0.3, 0.3, 0.3)) -> Scene:
    """A chessboard calibration target alone in front of a uniform background.

    The board's ``a`` axis (columns) and ``b`` axis (rows) are the world x and y axes rotated by the
    rotation vector ``rotation_deg`` (degrees); its centre is at ``centre_mm`` (world frame). The
    white margin defaults to one square. See :func:`board_corners_world` for the corner positions.
    """
    if margin_mm is None:
        margin_mm = square_mm
    R = rotation_from_vector(np.deg2rad(np.asarray(rotation_deg, dtype=float)))
    half = ((inner[0] + 1) * square_mm / 2 + margin_mm, (inner[1] + 1) * square_mm / 2 + margin_mm)
    rect = Rect("board", tuple(float(c) for c in centre_mm), _unit(R[:, 0]), _unit(R[:, 1]), half,
                CheckerTexture(inner=tuple(inner), square_mm=square_mm))
    return Scene((rect,), background=background, ambient=1.0)


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


def board_corners_world(scene: Scene, *, name: str = "board") -> np.ndarray:
    """``(rows, cols, 3)`` world positions (mm) of the inner corners of a chessboard rectangle,
    ordered row by row from the corner at negative ``a`` and ``b`` (mrcal's board layout)."""
    rect = scene.find(name)
    tex = rect.texture
    if not isinstance(tex, CheckerTexture):
        raise ValueError(f"rectangle {name!r} is not a chessboard")
    cols, rows = tex.inner
    a = (np.arange(cols) + 1 - (cols + 1) / 2) * tex.square_mm
    b = (np.arange(rows) + 1 - (rows + 1) / 2) * tex.square_mm
    ab = np.stack(np.meshgrid(a, b), axis=-1)
    return rect.world_from_local(ab)


# ----------------------------------------------------------------------------------------------
# Packing a scene into arrays for the kernels
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Packed:
    geom: np.ndarray     # (R, 14): centre(3) axis_a(3) axis_b(3) normal(3) half_a half_b
    kind: np.ndarray     # (R,) int64 texture kind
    colours: np.ndarray  # (R, 2, 3)
    waves: np.ndarray    # (R, Wmax, 5) fa fb phase amp |f| (amp 0 for unused)
    checker: np.ndarray  # (R, 5): square, cols, rows, dark, light
    shade: np.ndarray    # (R,) Lambertian factor
    background: np.ndarray  # (3,)


def _pack(scene: Scene) -> _Packed:
    n = len(scene.rects)
    wmax = max([r.texture.waves for r in scene.rects if isinstance(r.texture, NoiseTexture)] + [1])
    geom = np.zeros((n, 14))
    kind = np.zeros(n, dtype=np.int64)
    colours = np.zeros((n, 2, 3))
    waves = np.zeros((n, wmax, 5))
    checker = np.zeros((n, 5))
    shade = np.zeros(n)
    light = np.asarray(scene.light, dtype=float)
    light = light / np.linalg.norm(light)
    for i, r in enumerate(scene.rects):
        a = np.asarray(r.axis_a, dtype=float)
        b = np.asarray(r.axis_b, dtype=float)
        if abs(np.linalg.norm(a) - 1) > 1e-9 or abs(np.linalg.norm(b) - 1) > 1e-9 or abs(a @ b) > 1e-9:
            raise ValueError(f"rectangle {r.name!r}: axis_a and axis_b must be orthonormal")
        nrm = np.cross(a, b)
        geom[i] = np.concatenate([r.centre_mm, a, b, nrm, r.half_size_mm])
        shade[i] = scene.ambient + (1 - scene.ambient) * abs(float(nrm @ light))
        t = r.texture
        if isinstance(t, NoiseTexture):
            kind[i] = TEXTURE_NOISE
            colours[i] = [t.colour0, t.colour1]
            table = t.wave_table()
            waves[i, : len(table)] = table
        elif isinstance(t, CheckerTexture):
            kind[i] = TEXTURE_CHECKER
            checker[i] = [t.square_mm, t.inner[0], t.inner[1], t.dark, t.light]
            colours[i] = [(t.dark,) * 3, (t.light,) * 3]
        elif isinstance(t, FlatTexture):
            kind[i] = TEXTURE_FLAT
            colours[i] = [t.colour, t.colour]
        else:
            raise TypeError(f"unknown texture {t!r}")
    return _Packed(geom, kind, colours, waves, checker, shade, np.asarray(scene.background, dtype=float))


# ----------------------------------------------------------------------------------------------
# Kernels: reference (numpy) and fast (numba) twins
# ----------------------------------------------------------------------------------------------

def cast_rays_numpy(origin: np.ndarray, dirs: np.ndarray, packed: _Packed) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of rays ``origin + t * dirs`` with the scene's rectangles (reference engine).

    Parameters
    ----------
    origin
        ``(3,)`` world position in mm shared by all rays.
    dirs
        ``(N, 3)`` unit directions in the world frame.

    Returns
    -------
    t, index, a, b
        ``(N,)`` each: distance in mm (``inf`` if no hit), index of the hit rectangle (-1 if none),
        texture coordinates in mm on it.
    """
    n = dirs.shape[0]
    best_t = np.full(n, np.inf)
    best_i = np.full(n, -1, dtype=np.int64)
    best_a = np.zeros(n)
    best_b = np.zeros(n)
    for i, g in enumerate(packed.geom):
        c, ax, bx, nrm = g[0:3], g[3:6], g[6:9], g[9:12]
        denom = dirs @ nrm
        p_rel = origin - c  # hit - c = (origin - c) + t * d
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(p_rel @ nrm) / denom
        a = p_rel @ ax + t * (dirs @ ax)
        b = p_rel @ bx + t * (dirs @ bx)
        hit = (np.abs(denom) > 1e-12) & (t > 0) & (t < best_t) & (np.abs(a) <= g[12]) & (np.abs(b) <= g[13])
        best_t[hit] = t[hit]
        best_i[hit] = i
        best_a[hit] = a[hit]
        best_b[hit] = b[hit]
    return best_t, best_i, best_a, best_b


def _sinc(x: np.ndarray) -> np.ndarray:
    """``sin(pi x) / (pi x)``; a Taylor polynomial below 0.3 (error < 2e-6), as in the fast kernel."""
    y = (np.pi * x) ** 2
    poly = 1.0 - y / 6.0 + y * y / 120.0 - y * y * y / 5040.0
    with np.errstate(divide="ignore", invalid="ignore"):
        exact = np.sin(np.pi * x) / (np.pi * x)
    return np.where(np.abs(x) < 0.3, poly, exact)


def _square_wave_filtered(x: np.ndarray, square: float, width: np.ndarray) -> np.ndarray:
    """Box-filtered (width ``width``) square wave that is +1 on ``[2k s, (2k+1) s)`` and -1 elsewhere."""
    k = np.floor(x / square + 0.5)
    e = x - k * square
    sign = 1.0 - 2.0 * (np.abs(k) % 2)
    return sign * np.clip(e / (0.5 * width), -1.0, 1.0)


def _edge_filtered(x: np.ndarray, square: float, width: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """The square wave of :func:`_square_wave_filtered` seen through a box of ``width`` and a
    Gaussian of ``sigma`` (both mm): each edge an ``erf`` of the combined standard deviation
    ``sqrt(sigma^2 + width^2 / 12)``; the plain box-filter ramp where ``sigma == 0``."""
    from scipy.special import erf

    k = np.floor(x / square + 0.5)
    e = x - k * square
    sign = 1.0 - 2.0 * (np.abs(k) % 2)
    total = np.sqrt(sigma**2 + width**2 / 12.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        smooth = erf(e / (math.sqrt(2.0) * total))
    return sign * np.where(sigma > 0, smooth, np.clip(e / (0.5 * width), -1.0, 1.0))


def shade_numpy(index: np.ndarray, a: np.ndarray, b: np.ndarray, footprint: np.ndarray, packed: _Packed,
                sigma: np.ndarray | None = None) -> np.ndarray:
    """Colour ``(N, 3)`` in ``[0, 1]`` of hits (reference engine). ``footprint`` is the box-filter
    width and ``sigma`` the standard deviation of the Gaussian blur (lens PSF), both in mm on the
    surface per ray."""
    if sigma is None:
        sigma = np.zeros_like(footprint)
    out = np.empty((index.size, 3))
    out[:] = packed.background
    for i in range(packed.geom.shape[0]):
        sel = index == i
        if not np.any(sel):
            continue
        ai, bi, wi, si = a[sel], b[sel], footprint[sel], sigma[sel]
        kind = packed.kind[i]
        if kind == TEXTURE_NOISE:
            value = np.full(ai.shape, 0.5)
            for fa, fb, phase, amp, f in packed.waves[i]:
                if amp == 0.0:
                    continue
                value += (amp * _sinc(f * wi) * np.exp(-2.0 * (math.pi * f * si) ** 2)
                          * np.cos(2 * math.pi * (fa * ai + fb * bi) + phase))
            value = np.clip(value, 0.0, 1.0)
        elif kind == TEXTURE_CHECKER:
            square, cols, rows, dark, light = packed.checker[i]
            xa = ai + (cols + 1) * square / 2
            xb = bi + (rows + 1) * square / 2
            inside = (xa >= 0) & (xa <= (cols + 1) * square) & (xb >= 0) & (xb <= (rows + 1) * square)
            prod = _edge_filtered(xa, square, wi, si) * _edge_filtered(xb, square, wi, si)
            value = np.where(inside, 0.5 - 0.5 * prod, 1.0)
        else:
            value = np.zeros(ai.shape)
        c0, c1 = packed.colours[i]
        out[sel] = packed.shade[i] * (c0 + value[:, None] * (c1 - c0))
    return out


def render_rays_numpy(origin: np.ndarray, dirs: np.ndarray, pixel_angle: float, packed: _Packed,
                      blur_angle: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shade unit rays ``(N, 3)`` (world frame) from ``origin`` (reference engine).

    ``pixel_angle`` (radians) is the angular size of one sample and ``blur_angle`` the standard
    deviation of the lens's Gaussian PSF (radians); textures are filtered by their footprints on the
    hit surface, ``t * angle / sqrt(|cos incidence|)``.

    Returns colour ``(N, 3)`` in ``[0, 1]``, hit distance ``(N,)`` in mm (``inf`` for none) and the
    index ``(N,)`` of the rectangle hit (-1 for none).
    """
    t, index, a, b = cast_rays_numpy(origin, dirs, packed)
    footprint = np.zeros_like(t)
    hit = index >= 0
    cos_i = np.abs(np.einsum("ij,ij->i", dirs[hit], packed.geom[index[hit], 9:12]))
    footprint[hit] = t[hit] * pixel_angle / np.sqrt(np.maximum(cos_i, 1e-3))
    sigma = footprint * (blur_angle / pixel_angle)
    return shade_numpy(index, a, b, footprint, packed, sigma), t, index


try:  # numba is a dependency, but keep the module importable without its compiler
    import numba
except ImportError:  # pragma: no cover
    numba = None


def _make_numba_kernel():
    @numba.njit(cache=True)
    def kernel(origin, dirs, pixel_angle, blur_angle, geom, kind, colours, waves, checker, shade, background,
               out, out_t, out_i):
        n = dirs.shape[0]
        nr = geom.shape[0]
        two_pi = 2.0 * math.pi
        for r in range(n):
            dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
            best_t = np.inf
            best_i = -1
            best_a = 0.0
            best_b = 0.0
            for i in range(nr):
                nx, ny, nz = geom[i, 9], geom[i, 10], geom[i, 11]
                denom = dx * nx + dy * ny + dz * nz
                if abs(denom) <= 1e-12:
                    continue
                px = origin[0] - geom[i, 0]
                py = origin[1] - geom[i, 1]
                pz = origin[2] - geom[i, 2]
                t = -(px * nx + py * ny + pz * nz) / denom
                if not (t > 0.0) or not (t < best_t):
                    continue
                a = px * geom[i, 3] + py * geom[i, 4] + pz * geom[i, 5] + t * (dx * geom[i, 3] + dy * geom[i, 4] + dz * geom[i, 5])
                if abs(a) > geom[i, 12]:
                    continue
                b = px * geom[i, 6] + py * geom[i, 7] + pz * geom[i, 8] + t * (dx * geom[i, 6] + dy * geom[i, 7] + dz * geom[i, 8])
                if abs(b) > geom[i, 13]:
                    continue
                best_t, best_i, best_a, best_b = t, i, a, b
            out_t[r] = best_t
            out_i[r] = best_i
            if best_i < 0:
                out[r, 0] = background[0]
                out[r, 1] = background[1]
                out[r, 2] = background[2]
                continue
            i = best_i
            cos_i = abs(dx * geom[i, 9] + dy * geom[i, 10] + dz * geom[i, 11])
            w = best_t * pixel_angle / math.sqrt(max(cos_i, 1e-3))
            sig = w * (blur_angle / pixel_angle)
            total = math.sqrt(sig * sig + w * w / 12.0)
            k = kind[i]
            if k == 1:
                value = 0.5
                for j in range(waves.shape[1]):
                    amp = waves[i, j, 3]
                    if amp == 0.0:
                        continue
                    x = waves[i, j, 4] * w
                    if abs(x) < 0.3:
                        y = (math.pi * x) ** 2
                        s = 1.0 - y / 6.0 + y * y / 120.0 - y * y * y / 5040.0
                    else:
                        s = math.sin(math.pi * x) / (math.pi * x)
                    g = math.exp(-2.0 * (math.pi * waves[i, j, 4] * sig) ** 2)
                    value += amp * s * g * math.cos(two_pi * (waves[i, j, 0] * best_a + waves[i, j, 1] * best_b) + waves[i, j, 2])
                value = min(max(value, 0.0), 1.0)
            elif k == 2:
                square = checker[i, 0]
                cols = checker[i, 1]
                rows = checker[i, 2]
                xa = best_a + (cols + 1) * square / 2
                xb = best_b + (rows + 1) * square / 2
                if xa >= 0 and xa <= (cols + 1) * square and xb >= 0 and xb <= (rows + 1) * square:
                    ka = math.floor(xa / square + 0.5)
                    kb = math.floor(xb / square + 0.5)
                    ea = xa - ka * square
                    eb = xb - kb * square
                    if sig > 0:
                        sa = math.erf(ea / (math.sqrt(2.0) * total))
                        sb = math.erf(eb / (math.sqrt(2.0) * total))
                    else:
                        sa = min(max(ea / (0.5 * w), -1.0), 1.0)
                        sb = min(max(eb / (0.5 * w), -1.0), 1.0)
                    sa *= 1.0 - 2.0 * (abs(ka) % 2)
                    sb *= 1.0 - 2.0 * (abs(kb) % 2)
                    value = 0.5 - 0.5 * sa * sb
                else:
                    value = 1.0
            else:
                value = 0.0
            for c in range(3):
                c0 = colours[i, 0, c]
                out[r, c] = shade[i] * (c0 + value * (colours[i, 1, c] - c0))

    return kernel


_numba_kernel = None


def render_rays_numba(origin: np.ndarray, dirs: np.ndarray, pixel_angle: float, packed: _Packed,
                      blur_angle: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fast twin of :func:`render_rays_numpy` (same inputs and outputs)."""
    global _numba_kernel
    if numba is None:  # pragma: no cover
        return render_rays_numpy(origin, dirs, pixel_angle, packed, blur_angle)
    if _numba_kernel is None:
        _numba_kernel = _make_numba_kernel()
    n = dirs.shape[0]
    out = np.empty((n, 3))
    out_t = np.empty(n)
    out_i = np.empty(n, dtype=np.int64)
    _numba_kernel(np.ascontiguousarray(origin, dtype=float), np.ascontiguousarray(dirs, dtype=float),
                  float(pixel_angle), float(blur_angle), packed.geom, packed.kind, packed.colours, packed.waves,
                  packed.checker, packed.shade, packed.background, out, out_t, out_i)
    return out, out_t, out_i


_ENGINES = {"numpy": render_rays_numpy, "numba": render_rays_numba}


def _edge_pixels(index: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixels whose 8-neighbourhood sees more than one surface (or background)."""
    pad = np.pad(index, 1, mode="edge")
    h, w = index.shape
    edge = np.zeros(index.shape, dtype=bool)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            edge |= pad[dy:dy + h, dx:dx + w] != index
    return edge


def render_image(origin: np.ndarray, centre_dirs: np.ndarray, sub_dirs: Callable[[np.ndarray, np.ndarray], np.ndarray],
                 *, pixel_angle: float, supersample: int, packed: _Packed, blur_px: float = 0.0,
                 engine: str = "numba") -> tuple[np.ndarray, np.ndarray]:
    """Render an image with adaptive supersampling.

    Every pixel is first shaded from its centre ray with the texture filtered over the whole pixel
    footprint (exact for a surface that covers the pixel: ``s x s`` samples of ``1/s`` footprints
    average to the same box filter). Pixels next to a change of surface are then re-rendered from
    ``supersample**2`` sub-pixel rays and averaged, which anti-aliases occlusion and object edges.

    Parameters
    ----------
    origin
        ``(3,)`` ray origin, world frame, mm.
    centre_dirs
        ``(H, W, 3)`` unit world directions through the pixel centres.
    sub_dirs
        ``sub_dirs(ys, xs) -> (M, s, s, 3)`` unit world directions of the sub-pixel samples of the
        pixels ``(ys[m], xs[m])``.
    pixel_angle
        Angular size of a pixel in radians (``1 / focal_px``).
    blur_px
        Standard deviation of the lens's Gaussian point spread in pixels, applied to the textures
        analytically (band-limits them so that corner and edge positions are unbiased).

    Returns
    -------
    rgb, depth_t
        ``(H, W, 3)`` colour in ``[0, 1]`` and ``(H, W)`` distance (mm) along the centre rays.
    """
    render = _ENGINES[engine]
    h, w = centre_dirs.shape[:2]
    blur_angle = blur_px * pixel_angle
    rgb, t, index = render(origin, centre_dirs.reshape(-1, 3), pixel_angle, packed, blur_angle)
    rgb = rgb.reshape(h, w, 3)
    s = supersample
    if s > 1:
        ys, xs = np.nonzero(_edge_pixels(index.reshape(h, w)))
        if ys.size:
            dirs = sub_dirs(ys, xs).reshape(-1, 3)
            sub_rgb, _, _ = render(origin, dirs, pixel_angle / s, packed, blur_angle)
            rgb[ys, xs] = sub_rgb.reshape(ys.size, s * s, 3).mean(axis=1)
    return rgb, t.reshape(h, w)


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
        if engine not in _ENGINES:
            raise ValueError(f"engine must be one of {sorted(_ENGINES)}; got {engine!r}")
        if int(supersample) != supersample or supersample < 1:
            raise ValueError(f"supersample must be a positive integer; got {supersample!r}")
        full_w = self.rig.sensor_size_px[0] // binning
        full_h = self.rig.sensor_size_px[1] // binning
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
        self._packed_cache: dict[int, tuple[Scene, _Packed]] = {}
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
        _, t, _ = _ENGINES[self.engine](self.rig.camera_centre(position_mm), d_world.reshape(-1, 3),
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
        _, t, _ = _ENGINES[self.engine](self.rig.camera_centre(position_mm), dirs_world.reshape(-1, 3),
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

    def _packed(self, scene: Scene) -> _Packed:
        key = id(scene)
        cached = self._packed_cache.get(key)
        if cached is None or cached[0] is not scene:
            cached = (scene, _pack(scene))
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


__all__ = [
    "FakeCamera", "FakeRig", "Scene", "Rect", "NoiseTexture", "CheckerTexture", "FlatTexture",
    "default_scene", "chessboard_scene", "calibration_poses", "board_corners_world", "box", "rectified_geometry",
    "RectifiedGeometry", "cast_rays_numpy", "render_rays_numpy", "render_rays_numba", "render_image",
]
