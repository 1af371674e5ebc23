"""The light field as data: views on a regular grid and what is known about the camera.

Axes (``docs/conventions.md``): ``views[u, v, y, x(, c)]``. ``u`` is the grid row (the camera moves
down the image, +y, as ``u`` grows), ``v`` the grid column (the camera moves right, +x, as ``v``
grows); the centre view is ``views[U // 2, V // 2]``. A scene point seen at pixel ``(y, x)`` of the
centre view with disparity ``d`` (pixels per view step) appears in view ``(u, v)`` at::

    (y - (u - u0) * d,  x - (v - v0) * d)

so that ``d > 0`` for points in front of the plane of zero disparity (the benchmark's sign).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class LightField:
    """A 4D light field with its metadata.

    Attributes
    ----------
    views
        ``(U, V, H, W)`` or ``(U, V, H, W, 3)`` array in the stored dtype (``uint8``, ``uint16`` or
        ``float32`` in ``[0, 1]``), colour in RGB order; or, read with ``grey=True``
        (:func:`recon.lf.read_lightfield`), the ``(U, V, H, W)`` ``float32`` luminance that
        :func:`to_gray` makes of the stored views.
    pitch_mm
        Distance between neighbouring grid positions in mm (the benchmark's ``baseline_mm``), or
        ``None`` when unknown.
    focal_px
        Focal length in pixels of the (rectified) views, or ``None`` when unknown.
    disparity_range
        ``(disp_min, disp_max)`` in pixels per view step that the scene is known to span, or ``None``.
    disparity_offset
        ``d0`` in pixels per view step: the views were shifted (refocused) so that a point at depth
        ``Z`` has disparity ``focal_px * pitch_mm / Z - d0``. 0 for an unshifted capture.
    principal_point_px
        ``(cx, cy)`` of the (rectified) views, x first as in a camera matrix; ``None`` means the image
        centre ``((W - 1) / 2, (H - 1) / 2)``.
    metadata
        Everything else the source recorded (``parameters.cfg`` sections, capture manifest header).
    source
        Folder the light field was read from, if any.
    stored_centre
        The centre view as stored, ``(H, W[, 3])`` in the stored dtype, when :attr:`views` holds the
        views converted to grey (read with ``grey=True``); ``None``: the centre of :attr:`views`.
    views_once
        ``True`` when the views are read for one estimate and nothing reads them after it (set by
        :func:`recon.pipeline.reconstruct_to_folder` on the light field it read itself): the
        estimator lets them go after the last step that reads them
        (:func:`recon.entropy.steps.boundary_step`, :meth:`release_views`).
    """

    views: np.ndarray
    pitch_mm: float | None = None
    focal_px: float | None = None
    disparity_range: tuple[float, float] | None = None
    disparity_offset: float = 0.0
    principal_point_px: tuple[float, float] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    source: Path | None = None
    stored_centre: np.ndarray | None = None
    views_once: bool = False
    #: :attr:`views`' shape, kept when they are let go (:meth:`release_views`).
    shape: tuple[int, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.views.ndim not in (4, 5) or (self.views.ndim == 5 and self.views.shape[-1] != 3):
            raise ValueError(
                f"views must be (U, V, H, W) or (U, V, H, W, 3); got shape {self.views.shape}"
            )
        self.shape = tuple(int(n) for n in self.views.shape)

    def release_views(self) -> None:
        """Let go of :attr:`views` (``None`` from now on) when :attr:`views_once` says nothing reads
        them again and the centre view is kept (:attr:`stored_centre`); the shapes, the centre view
        and the metadata stay. Otherwise nothing changes."""
        if self.views_once and self.stored_centre is not None:
            self.views = None

    @property
    def grid_shape(self) -> tuple[int, int]:
        """``(U, V)``: number of grid rows and columns."""
        return self.shape[0], self.shape[1]

    @property
    def image_shape(self) -> tuple[int, int]:
        """``(H, W)`` of every view in pixels."""
        return self.shape[2], self.shape[3]

    @property
    def centre_index(self) -> tuple[int, int]:
        """``(u0, v0) = (U // 2, V // 2)``."""
        return self.grid_shape[0] // 2, self.grid_shape[1] // 2

    @property
    def is_colour(self) -> bool:
        return len(self.shape) == 5

    def centre_view(self) -> np.ndarray:
        """The centre view in the stored dtype, ``(H, W[, 3])`` (:attr:`stored_centre` when set)."""
        if self.stored_centre is not None:
            return self.stored_centre
        u0, v0 = self.centre_index
        return self.views[u0, v0]

    def float_views(self) -> np.ndarray:
        """All views as ``float32`` in ``[0, 1]``, same shape as :attr:`views`."""
        return to_float(self.views)

    def gray(self) -> np.ndarray:
        """All views as ``(U, V, H, W)`` ``float32`` luminance in ``[0, 1]`` (Rec. 601 weights)."""
        return to_gray(self.views)


def to_float(images: np.ndarray) -> np.ndarray:
    """Scale integer images to ``float32`` in ``[0, 1]``; float input is returned as ``float32``."""
    if images.dtype == np.uint8:
        return images.astype(np.float32) * np.float32(1 / 255)
    if images.dtype == np.uint16:
        return images.astype(np.float32) * np.float32(1 / 65535)
    return images.astype(np.float32, copy=False)


def to_gray(images: np.ndarray) -> np.ndarray:
    """Luminance of RGB images (last axis of length 3) as ``float32`` in ``[0, 1]``.

    Rec. 601 weights (OpenCV's ``RGB2GRAY``) in floating point, so no precision is lost to rounding.
    Images without a colour axis are only scaled (see :func:`to_float`). Works on any leading shape,
    e.g. ``(U, V, H, W, 3) -> (U, V, H, W)``; each image is converted whole by :func:`gray_image`
    (OpenCV computes the last ``W % 8`` pixels of a row in another order than the rest, so a crop's
    grey may differ from the grey's crop in its last columns).
    """
    if not (images.ndim >= 3 and images.shape[-1] == 3):
        return to_float(images)
    flat = images.reshape((-1,) + images.shape[-3:])
    out = np.empty(flat.shape[:3], dtype=np.float32)

    def convert(i: int) -> None:  # per image keeps the float32 temporary small
        gray_image(flat[i], out=out[i])

    workers = min(len(flat), os.cpu_count() or 1)
    if workers > 1:  # numpy's cast and OpenCV release the interpreter lock: one image per thread
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for _ in pool.map(convert, range(len(flat))):
                pass
    else:
        for i in range(len(flat)):
            convert(i)
    return out.reshape(images.shape[:-1])


def gray_image(image: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
    """One ``(H, W, 3)`` RGB or ``(H, W)`` grey image in its stored dtype as ``(H, W)`` ``float32``
    luminance in ``[0, 1]``, into ``out`` when given: what :func:`to_gray` makes of it, bit for bit
    (``recon.lf.imageio.read_images`` converts each view with it as it is decoded)."""
    if out is None:
        out = np.empty(image.shape[:2], dtype=np.float32)
    if image.ndim == 2:
        out[...] = to_float(image)
        return out
    scale = {np.dtype(np.uint8): 1 / 255, np.dtype(np.uint16): 1 / 65535}.get(image.dtype, 1.0)
    import cv2

    return np.multiply(cv2.cvtColor(image.astype(np.float32), cv2.COLOR_RGB2GRAY), np.float32(scale), out=out)


def max_view_offset(grid_shape: tuple[int, int]) -> int:
    """``max |u - u0|, |v - v0|`` over the grid: how many view steps the farthest view is away."""
    rows, cols = grid_shape
    return max(rows // 2, rows - 1 - rows // 2, cols // 2, cols - 1 - cols // 2)


def view_shift_px(disparity_range: tuple[float, float], grid_shape: tuple[int, int]) -> int:
    """``ceil(max|d| * max view offset)``: the farthest (pixels) any view is sampled from a pixel
    of the centre view for a disparity in ``disparity_range`` (px/view)."""
    return math.ceil(max(abs(disparity_range[0]), abs(disparity_range[1])) * max_view_offset(grid_shape) - 1e-9)
