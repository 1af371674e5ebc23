"""The simulated camera's world: scenes of textured rectangles and an exact, alias-free renderer.

:mod:`rig.fakecam` puts a :class:`Scene` in front of its simulated camera; this module knows nothing
of cameras or stages: it intersects rays (in the world frame, mm) with the scene's rectangles and
shades them.

Each pixel is supersampled on an ``s x s`` grid; every sample's ray is the mrcal unprojection of the
sample position (computed once per camera and cached), rotated into the world frame, and intersected
with every rectangle of the scene; the nearest hit wins. Textures are band-limited and filtered
analytically with a box the size of the sample's footprint on the surface (sums of cosines, each
attenuated by ``sinc(f * footprint)``; the chessboard's edges are linear ramps of that width), so the
images are free of aliasing and corners and edges are unbiased. Samples are averaged per pixel, then
optional seeded Gaussian noise is added and the image is quantised.

Two engines do the ray casting and shading: ``"numpy"`` (the readable reference) and ``"numba"``
(the default, the same arithmetic in a compiled loop); ``tests/test_fakecam.py`` checks they agree.

Frames and units are those of :mod:`rig.fakecam` (``docs/conventions.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

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
class Packed:
    geom: np.ndarray     # (R, 14): centre(3) axis_a(3) axis_b(3) normal(3) half_a half_b
    kind: np.ndarray     # (R,) int64 texture kind
    colours: np.ndarray  # (R, 2, 3)
    waves: np.ndarray    # (R, Wmax, 5) fa fb phase amp |f| (amp 0 for unused)
    checker: np.ndarray  # (R, 5): square, cols, rows, dark, light
    shade: np.ndarray    # (R,) Lambertian factor
    background: np.ndarray  # (3,)


def pack_scene(scene: Scene) -> Packed:
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
    return Packed(geom, kind, colours, waves, checker, shade, np.asarray(scene.background, dtype=float))


# ----------------------------------------------------------------------------------------------
# Kernels: reference (numpy) and fast (numba) twins
# ----------------------------------------------------------------------------------------------

def cast_rays_numpy(origin: np.ndarray, dirs: np.ndarray, packed: Packed) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def shade_numpy(index: np.ndarray, a: np.ndarray, b: np.ndarray, footprint: np.ndarray, packed: Packed,
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


def render_rays_numpy(origin: np.ndarray, dirs: np.ndarray, pixel_angle: float, packed: Packed,
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


def render_rays_numba(origin: np.ndarray, dirs: np.ndarray, pixel_angle: float, packed: Packed,
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


ENGINES = {"numpy": render_rays_numpy, "numba": render_rays_numba}


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
                 *, pixel_angle: float, supersample: int, packed: Packed, blur_px: float = 0.0,
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
    render = ENGINES[engine]
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
