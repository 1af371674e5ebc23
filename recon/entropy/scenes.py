"""Rendered light fields with exact ground truth that imitate the HCI benchmark scenes' difficulties.

The scenes of the 4D Light Field Benchmark other than backgammon are not in ``../shared``; these
stand in for them so that the estimator's defaults can be checked on more than one scene
(``bench/scenes.py`` prints the table, ``docs/entropy-method.md`` records it). Each scene is a few
textured *surfaces* with an arbitrary disparity function (not only planes), rendered by following
``docs/conventions.md`` exactly (the point of a surface at centre pixel ``q`` appears in view
``(u, v)`` at ``q - (u - u0, v - v0) d(q)``), with a z-buffer (the largest disparity, i.e. the
closest surface, wins), optional Gaussian camera noise per view (a scalar or an ``(H, W)`` map of
sigma, e.g. growing down the image as in *stratified/dots*) and 8-bit quantisation as in the PNGs.

=============  ==========================================================================
scene          imitates
=============  ==========================================================================
dots           stratified/dots: small disks of many sizes, camera noise growing downwards
pyramids       stratified/pyramids: convex and concave pyramids, a dome, a slanted plane
stripes        stratified/stripes: low-contrast stripes, a nearly textureless patch
boxes          training/boxes: natural texture, a fine mesh occluder, large flat areas
cotton         training/cotton: a smooth round object with weak texture before a wall
bars           6-px bars with 12-px gaps: background hidden from both grid halves
slants         training/sideboard: steep slanted planes, a box in front
noisy          boxes-like layout with strong noise (sigma 8 grey levels) everywhere
thin           rods (4 px, diagonal), wires (2 px) and a dense mesh (2-px wires every 8 px)
               in front of a textured wall: the issue's held-out "thin" kind
=============  ==========================================================================

:func:`region_masks` splits the centre view by the ground truth into ``edge`` (within 2 px of a
disparity jump), ``flat`` (no texture in the clean centre view), ``slant`` and ``plane`` so that
scores can be reported per kind of difficulty.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from recon.lf.lightfield import LightField
from recon.synthetic import noise_texture

Field = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Surface:
    """A textured surface over the centre view.

    ``texture`` ``(H, W)`` in ``[0, 1]`` (centre-view coordinates); ``disparity(y, x)`` its disparity
    in pixels per view step at centre-view coordinates (arrays, may be fractional), or a constant;
    ``mask(y, x)`` bool where the surface exists (``None``: everywhere).
    """

    texture: np.ndarray
    disparity: float | Field
    mask: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None

    def disparity_at(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        if callable(self.disparity):
            return np.asarray(self.disparity(y, x), np.float32)
        return np.full(np.shape(y), self.disparity, np.float32)


@dataclass
class Scene:
    """A rendered scene: the light field, its true centre-view disparity and the clean centre view."""

    name: str
    lf: LightField
    truth: np.ndarray
    clean_centre: np.ndarray


def render_surfaces(surfaces: list[Surface], *, grid: tuple[int, int] = (9, 9), iterations: int = 10,
                    noise: float | np.ndarray = 0.0, seed: int = 0, quantise: bool = True,
                    margin: float = 0.3) -> tuple[LightField, np.ndarray, np.ndarray]:
    """Render ``(U, V, H, W)`` grey views; returns ``(lf, truth, clean_centre)``.

    The centre-view position ``q`` a view pixel ``p`` shows is found by fixed-point iteration of
    ``q = p + (du, dv) d(q)`` (converges when ``|delta| |grad d| < 1``). ``noise`` is the sigma of
    additive Gaussian noise (``[0, 1]`` units), a scalar or an ``(H, W)`` map; ``quantise`` rounds
    to 8-bit levels. ``lf.disparity_range`` is the truth's range widened by ``margin``.
    """
    h, w = surfaces[0].texture.shape
    rows, cols = grid
    u0, v0 = rows // 2, cols // 2
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    views = np.zeros((rows, cols, h, w), np.float32)
    truth = np.full((h, w), np.nan, np.float32)
    rng = np.random.default_rng(seed)
    sigma = np.broadcast_to(np.asarray(noise, np.float32), (h, w))
    clean_centre = None
    for u in range(rows):
        for v in range(cols):
            du, dv = u - u0, v - v0
            image = np.zeros((h, w), np.float32)
            zbuf = np.full((h, w), -np.inf, np.float32)
            for s in surfaces:
                qy, qx = yy.copy(), xx.copy()
                n_iter = 1 if not callable(s.disparity) else iterations
                for _ in range(n_iter):
                    d = s.disparity_at(qy, qx)
                    qy, qx = yy + du * d, xx + dv * d
                d = s.disparity_at(qy, qx)
                inside = np.ones((h, w), bool) if s.mask is None else np.asarray(s.mask(qy, qx), bool)
                win = inside & (d > zbuf)
                sample = cv2.remap(s.texture, qx, qy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
                image[win] = sample[win]
                zbuf[win] = d[win]
            if du == 0 and dv == 0:
                truth = np.where(np.isfinite(zbuf), zbuf, np.nan).astype(np.float32)
                clean_centre = image.copy()
            if np.any(sigma > 0):
                image = image + sigma * rng.standard_normal((h, w)).astype(np.float32)
            image = np.clip(image, 0.0, 1.0)
            if quantise:
                image = np.round(image * 255.0) / 255.0
            views[u, v] = image
    rng_d = (float(np.nanmin(truth)) - margin, float(np.nanmax(truth)) + margin)
    return LightField(views=views, disparity_range=rng_d), truth, clean_centre


def natural_texture(shape: tuple[int, int], *, seed: int, contrast: float = 0.35) -> np.ndarray:
    """Multi-scale band-limited noise (scales 1, 3, 8 px) in ``[0, 1]``: a stand-in for natural texture."""
    parts = [noise_texture(shape, seed=seed + k, scale=s, contrast=1.0) - 0.5
             for k, s in enumerate((1.0, 3.0, 8.0))]
    t = parts[0] * 0.3 + parts[1] * 0.5 + parts[2] * 0.8
    t /= t.std() + 1e-12
    return np.clip(0.5 + contrast * 0.5 * t, 0, 1).astype(np.float32)


def _rect(y0, y1, x0, x1):
    return lambda y, x: (y >= y0) & (y < y1) & (x >= x0) & (x < x1)


def _dots(n: int, seed: int) -> Scene:
    back = Surface(natural_texture((n, n), seed=seed, contrast=0.3), -0.4)
    radii = (1.0, 1.5, 2.5, 4.0, 6.0)
    centres = []
    for i, r in enumerate(radii):  # columns of dots of one radius, several rows
        cx = n * (i + 0.5) / len(radii)
        for j in range(6):
            centres.append(((j + 0.5) * n / 6, cx, r))
    cen = np.array(centres, np.float32)

    def mask(y, x):
        inside = np.zeros(np.shape(y), bool)
        for cy, cx, r in cen:
            inside |= (y - cy) ** 2 + (x - cx) ** 2 <= r * r
        return inside

    front = Surface(np.clip(noise_texture((n, n), seed=seed + 9, scale=1.0, contrast=0.5) + 0.25, 0, 1),
                    0.9, mask)
    sigma = np.repeat(np.array([0.0, 0.01, 0.02, 0.04], np.float32), -(-n // 4))[:n]
    lf, truth, clean = render_surfaces([back, front], noise=sigma[:, None] * np.ones((1, n), np.float32),
                                       seed=seed)
    return Scene("dots", lf, truth, clean)


def _pyramids(n: int, seed: int) -> Scene:
    c = n / 4

    def disp(y, x):
        d = -0.3 + 0.0 * y
        for (cy, cx, sign) in ((c, c, 1.0), (c, 3 * c, -1.0)):  # convex and concave pyramids
            d = d + sign * np.maximum(0.0, 1.0 - np.maximum(np.abs(y - cy), np.abs(x - cx)) / (0.8 * c)) * 0.9
        r2 = ((y - 3 * c) ** 2 + (x - c) ** 2) / (0.8 * c) ** 2  # dome
        d = d + 0.9 * np.sqrt(np.maximum(0.0, 1.0 - r2))
        # a plane slanted in x, in the lower right quadrant, blended continuously
        ramp = np.clip((x - 2.2 * c) / (1.6 * c), 0, 1) * np.clip((y - 2.2 * c) / (0.2 * c), 0, 1)
        return d + 0.8 * ramp

    surf = Surface(natural_texture((n, n), seed=seed, contrast=0.3), disp)
    lf, truth, clean = render_surfaces([surf], seed=seed)
    return Scene("pyramids", lf, truth, clean)


def _stripes(n: int, seed: int) -> Scene:
    y, x = np.mgrid[0:n, 0:n].astype(np.float32)
    rng = np.random.default_rng(seed)
    back_tex = 0.5 + 0.04 * np.sign(np.sin(2 * np.pi * x / 9.0)) + 0.01 * rng.standard_normal((n, n))
    back_tex = cv2.GaussianBlur(back_tex.astype(np.float32), (0, 0), 0.7)
    front_tex = 0.45 + 0.06 * np.sin(2 * np.pi * (x + y) / 7.0) + 0.005 * rng.standard_normal((n, n))
    front_tex[:, int(0.55 * n):] = 0.45 + 0.008 * noise_texture((n, n - int(0.55 * n)), seed=seed + 3,
                                                                  scale=1.5, contrast=1.0)[:, :]
    back = Surface(back_tex.astype(np.float32), 0.5)
    front = Surface(front_tex.astype(np.float32), 1.3, _rect(0.25 * n, 0.75 * n, 0.2 * n, 0.8 * n))
    lf, truth, clean = render_surfaces([back, front], noise=0.004, seed=seed)
    return Scene("stripes", lf, truth, clean)


def _boxes(n: int, seed: int, *, noise: float = 0.0, name: str = "boxes") -> Scene:
    wall_tex = natural_texture((n, n), seed=seed, contrast=0.35)
    wall_tex[int(0.1 * n):int(0.4 * n), int(0.55 * n):int(0.9 * n)] = 0.62  # large flat area on the wall
    wall = Surface(wall_tex, lambda y, x: -0.8 + 0.003 * (x - n / 2))
    box_tex = natural_texture((n, n), seed=seed + 5, contrast=0.4)
    box_tex[int(0.6 * n):int(0.8 * n), int(0.1 * n):int(0.35 * n)] = 0.35  # flat face on the box
    box = Surface(box_tex, 0.4, _rect(0.5 * n, 0.9 * n, 0.05 * n, 0.45 * n))
    period, width = 10.0, 2.0

    def mesh(y, x):  # a fine grid (thin wires) in front of the right half
        on = (np.mod(x, period) < width) | (np.mod(y, period) < width)
        return on & (x >= 0.5 * n) & (y >= 0.45 * n)

    mesh_tex = np.clip(natural_texture((n, n), seed=seed + 7, contrast=0.3) - 0.15, 0, 1)
    wires = Surface(mesh_tex, 1.2, mesh)
    lf, truth, clean = render_surfaces([wall, box, wires], noise=noise, seed=seed)
    return Scene(name, lf, truth, clean)


def _cotton(n: int, seed: int) -> Scene:
    cy, cx, r = 0.55 * n, 0.5 * n, 0.32 * n

    def disp(y, x):
        rr = np.minimum(((y - cy) ** 2 + (x - cx) ** 2) / r ** 2, 1.0)
        return 0.3 + 0.9 * np.sqrt(1.0 - rr)

    wall = Surface(natural_texture((n, n), seed=seed, contrast=0.3), -0.6)
    ball = Surface(noise_texture((n, n), seed=seed + 1, scale=3.0, contrast=0.12), disp,
                   lambda y, x: (y - cy) ** 2 + (x - cx) ** 2 <= r * r)
    lf, truth, clean = render_surfaces([wall, ball], noise=0.003, seed=seed)
    return Scene("cotton", lf, truth, clean)


def _bars(n: int, seed: int) -> Scene:
    back = Surface(noise_texture((n, n), seed=seed, contrast=0.35), -0.6)
    front = Surface(noise_texture((n, n), seed=seed + 1, contrast=0.35), 1.2,
                    lambda y, x: np.mod(y, 18.0) < 6.0)
    lf, truth, clean = render_surfaces([back, front], seed=seed)
    return Scene("bars", lf, truth, clean)


def _slants(n: int, seed: int) -> Scene:
    left = Surface(natural_texture((n, n), seed=seed, contrast=0.35),
                   lambda y, x: -1.0 + 0.012 * x, _rect(-1e9, 1e9, -1e9, 0.5 * n))
    right = Surface(natural_texture((n, n), seed=seed + 2, contrast=0.35),
                    lambda y, x: 0.6 - 0.008 * (x - 0.5 * n) + 0.006 * (y - 0.5 * n),
                    _rect(-1e9, 1e9, 0.5 * n, 1e9))
    box = Surface(natural_texture((n, n), seed=seed + 4, contrast=0.35), 1.4,
                  _rect(0.6 * n, 0.85 * n, 0.3 * n, 0.7 * n))
    lf, truth, clean = render_surfaces([left, right, box], seed=seed)
    return Scene("slants", lf, truth, clean)


def _thin(n: int, seed: int) -> Scene:
    """Rods, wires and a mesh far in front of a wall: structures narrower than every window but the
    strips, and background seen through gaps that every half of the grid loses somewhere."""
    wall = Surface(natural_texture((n, n), seed=seed, contrast=0.35), lambda y, x: -0.7 + 0.002 * (y - n / 2))

    def rods(y, x):  # 4 px wide across x, leaning 31 degrees, every 40 px, in the left half
        return (np.mod(x + 0.6 * y, 40.0) < 4.0) & (x < 0.5 * n)

    def wires(y, x):  # vertical, 1.5 px wide (1 or 2 px in each view), upper right
        return (np.mod(x, 14.0) < 1.5) & (x >= 0.5 * n) & (y < 0.5 * n)

    def mesh(y, x):  # 2-px wires every 8 px, lower right: 6-px holes
        return ((np.mod(x, 8.0) < 2.0) | (np.mod(y, 8.0) < 2.0)) & (x >= 0.5 * n) & (y >= 0.5 * n)

    def texture(offset: int, shift: float) -> np.ndarray:
        return np.clip(natural_texture((n, n), seed=seed + offset, contrast=0.35) + shift, 0, 1)

    surfaces = [wall, Surface(texture(3, 0.1), 0.9, rods), Surface(texture(5, -0.2), 1.4, wires),
                Surface(texture(7, 0.15), 1.1, mesh)]
    lf, truth, clean = render_surfaces(surfaces, seed=seed)
    return Scene("thin", lf, truth, clean)


SCENES: dict[str, Callable[[int, int], Scene]] = {
    "dots": _dots,
    "pyramids": _pyramids,
    "stripes": _stripes,
    "boxes": _boxes,
    "cotton": _cotton,
    "bars": _bars,
    "slants": _slants,
    "noisy": lambda n, seed: _boxes(n, seed, noise=8 / 255, name="noisy"),
    "thin": _thin,
}


def make_scene(name: str, *, size: int = 192, seed: int = 0) -> Scene:
    """Render scene ``name`` (a key of :data:`SCENES`) at ``size x size`` pixels, 9x9 views."""
    try:
        return SCENES[name](size, seed)
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}") from None


REGION_KINDS = ("edge", "flat", "slant", "plane")


def region_masks(truth: np.ndarray, clean_centre: np.ndarray, *, jump: float = 0.15,
                 edge_radius: int = 2, flat_std: float = 2.0 / 255) -> dict[str, np.ndarray]:
    """``(H, W)`` bool masks of :data:`REGION_KINDS` from the ground truth (disjoint, cover all).

    ``edge``: within ``edge_radius`` px of a neighbour pair whose true disparity differs by more than
    ``jump``; ``flat``: not edge, and the clean centre view's 5x5 standard deviation is below
    ``flat_std``; ``slant``: the rest where the truth's gradient exceeds 0.002 px per pixel;
    ``plane``: the rest.
    """
    t = np.nan_to_num(truth.astype(np.float64))
    jumps = np.zeros(t.shape, bool)
    jy = np.abs(np.diff(t, axis=0)) > jump
    jx = np.abs(np.diff(t, axis=1)) > jump
    jumps[:-1] |= jy
    jumps[1:] |= jy
    jumps[:, :-1] |= jx
    jumps[:, 1:] |= jx
    edge = ndimage.binary_dilation(jumps, iterations=edge_radius)
    img = clean_centre.astype(np.float64)
    mean = ndimage.uniform_filter(img, 5)
    std = np.sqrt(np.maximum(ndimage.uniform_filter(img * img, 5) - mean * mean, 0))
    flat = ~edge & (std < flat_std)
    gy, gx = np.gradient(t)
    slant = ~edge & ~flat & (np.hypot(gy, gx) > 0.002)
    plane = ~edge & ~flat & ~slant
    return {"edge": edge, "flat": flat, "slant": slant, "plane": plane}
