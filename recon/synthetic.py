"""Small synthetic light fields with known disparity, for tests, demos and benchmarks.

A scene is a stack of layers, back to front. Each layer is a textured surface with a disparity
plane ``d(y, x) = d0 + gy * (y - cy) + gx * (x - cx)`` (centre-view pixel coordinates) and a mask
that says where, in the centre view, the layer is. Views are rendered by following the sign
convention of ``docs/conventions.md`` exactly: the layer's point at centre pixel ``q`` appears in
view ``(u, v)`` at ``q - (u - u0, v - v0) * d(q)``; nearer layers (drawn later) hide farther ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from recon.lf.lightfield import LightField


def noise_texture(shape: tuple[int, int], *, seed: int, scale: float = 2.0, contrast: float = 0.35) -> np.ndarray:
    """Band-limited random texture in ``[0, 1]``, ``(H, W)`` float32: white noise blurred by ``scale`` px."""
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal(shape).astype(np.float32)
    if scale > 0:
        noise = cv2.GaussianBlur(noise, (0, 0), scale)
    noise /= noise.std() + 1e-12
    return np.clip(0.5 + contrast * 0.5 * noise, 0, 1).astype(np.float32)


@dataclass
class Layer:
    """A textured surface: ``texture`` ``(H, W)`` in centre-view coordinates, its disparity plane and extent.

    ``mask(y, x)`` (centre-view coordinates, may be fractional) says where the layer exists; ``None``
    means everywhere.
    """

    texture: np.ndarray
    disparity: float
    slope: tuple[float, float] = (0.0, 0.0)  # (d/dy, d/dx) of disparity per pixel
    mask: object = None  # callable (y, x) -> bool array, or None
    centre: tuple[float, float] | None = field(default=None)

    def disparity_at(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        h, w = self.texture.shape
        cy, cx = self.centre if self.centre is not None else ((h - 1) / 2, (w - 1) / 2)
        return self.disparity + self.slope[0] * (y - cy) + self.slope[1] * (x - cx)


def render(layers: list[Layer], *, grid: tuple[int, int] = (9, 9), iterations: int = 4) -> tuple[LightField, np.ndarray]:
    """Render a grey light field ``(U, V, H, W)`` float32 and the centre view's true disparity ``(H, W)``.

    Layers are given back to front. For slanted layers the centre-view position of a view pixel is
    found by fixed-point iteration of ``q = p + delta * d(q)``.
    """
    h, w = layers[0].texture.shape
    rows, cols = grid
    u0, v0 = rows // 2, cols // 2
    views = np.zeros((rows, cols, h, w), dtype=np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    truth = np.full((h, w), np.nan, dtype=np.float32)
    for u in range(rows):
        for v in range(cols):
            du, dv = u - u0, v - v0
            image = views[u, v]
            for layer in layers:
                qy, qx = yy.copy(), xx.copy()
                for _ in range(iterations if layer.slope != (0.0, 0.0) else 1):
                    d = layer.disparity_at(qy, qx)
                    qy, qx = yy + du * d, xx + dv * d
                sample = cv2.remap(layer.texture, qx, qy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
                inside = np.ones((h, w), bool) if layer.mask is None else layer.mask(qy, qx)
                image[inside] = sample[inside]
                if du == 0 and dv == 0:
                    truth[inside] = layer.disparity_at(yy, xx)[inside]
    lf = LightField(views=views, disparity_range=(float(np.nanmin(truth)) - 0.5, float(np.nanmax(truth)) + 0.5))
    return lf, truth


def occluding_square_scene(size: int = 64, *, seed: int = 0, back: float = -0.5, front: float = 1.0,
                           grid: tuple[int, int] = (9, 9)) -> tuple[LightField, np.ndarray]:
    """A textured background plane and a textured square in front of it: occlusion edges on four sides."""
    lo, hi = size * 0.3, size * 0.7

    def square(y: np.ndarray, x: np.ndarray) -> np.ndarray:
        return (y >= lo) & (y < hi) & (x >= lo) & (x < hi)

    layers = [
        Layer(noise_texture((size, size), seed=seed), back),
        Layer(noise_texture((size, size), seed=seed + 1), front, mask=square),
    ]
    return render(layers, grid=grid)
