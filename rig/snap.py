"""One frame at the bench: ``lfrig camera snap`` and the readouts ``lfrig camera preview`` shows.

A frame is judged against the range its camera can deliver (:func:`full_scale`): a pixel is clipped
when it sits at the bottom (0) or the top of that range. The focus measure is the variance of the
Laplacian (Pech-Pacheco et al., "Diatom autofocusing in brightfield microscopy", ICPR 2000) of the
grey image scaled to 0..1, so its value does not depend on the bit depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rig.errors import RigError


def full_scale(image: np.ndarray, settings: dict[str, Any] | None = None) -> int:
    """The largest value the camera can deliver in ``image``'s dtype.

    ``uint8``: 255. ``uint16``: from the camera's settings when they name the significant bits
    (Aravis: ``significant_bits`` and ``bit_shift``, a 12-bit format MSB-aligned tops at 0xFFF0;
    the fake camera: ``bit_depth``), else 65535.
    """
    if image.dtype == np.uint8:
        return 255
    if image.dtype != np.uint16:
        raise RigError(f"the camera delivered {image.dtype} pixels; expected uint8 or uint16")
    settings = settings or {}
    bits = settings.get("significant_bits")
    if bits:
        shift = int(settings.get("bit_shift") or 0)
        return ((1 << min(int(bits), 16)) - 1) << shift if int(bits) < 16 else 65535
    return 65535


def grey(image: np.ndarray) -> np.ndarray:
    """``(H, W)`` or ``(H, W, 3)`` RGB -> ``(H, W)`` float64 luminance (Rec. 601 weights), in the image's units."""
    if image.ndim == 2:
        return image.astype(np.float64)
    return image[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def focus_measure(image: np.ndarray, *, top: int, roi: tuple[int, int, int, int] | None = None) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image scaled to 0..1 over ``roi``.

    ``roi`` is ``(x0, y0, width, height)`` in pixels, clipped to the image; ``None`` is the whole
    frame. Larger is sharper; compare values of the same scene only. Regions under 3 x 3 pixels give 0.
    """
    g = grey(image) / float(top)
    if roi is not None:
        x0, y0, w, h = roi
        g = g[max(0, y0):max(0, y0 + h), max(0, x0):max(0, x0 + w)]
    if g.shape[0] < 3 or g.shape[1] < 3:
        return 0.0
    lap = g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


@dataclass(frozen=True)
class FrameStats:
    """What a frame holds: size, range and clipping, with ``top`` the camera's full scale."""

    width: int
    height: int
    channels: int
    dtype: str
    top: int
    min: int
    max: int
    clipped_low: float  # fraction of pixel values at 0
    clipped_high: float  # fraction of pixel values at ``top`` or above

    def line(self) -> str:
        colour = "grey" if self.channels == 1 else f"{self.channels} channels"
        return (f"{self.width} x {self.height} px, {colour}, {self.dtype} (full scale {self.top}); "
                f"min {self.min}, max {self.max}; clipped {100 * self.clipped_low:.2f} % at 0, "
                f"{100 * self.clipped_high:.2f} % at the top")


def frame_stats(image: np.ndarray, *, top: int) -> FrameStats:
    """Size, min/max and the fractions of pixel values at 0 and at ``top`` (all channels counted)."""
    return FrameStats(
        width=int(image.shape[1]), height=int(image.shape[0]), channels=1 if image.ndim == 2 else int(image.shape[2]),
        dtype=str(image.dtype), top=int(top), min=int(image.min()), max=int(image.max()),
        clipped_low=float(np.mean(image == 0)), clipped_high=float(np.mean(image >= top)),
    )


def check_snap_path(path: Path) -> Path:
    """The file ``camera snap`` may write: a ``.png`` in an existing folder, not a folder or a link."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise RigError(f"-o {path}: give a .png file name (snap writes PNG, 16-bit when the camera gives more than 8 bits)")
    if path.is_symlink():
        raise RigError(f"-o {path}: is a symbolic link; give the path of a regular file")
    if path.is_dir():
        raise RigError(f"-o {path}: is a folder; give a file name such as {path / 'snap.png'}")
    if not path.parent.is_dir():
        raise RigError(f"-o {path}: the folder {path.parent} does not exist; create it first")
    return path


def snap(camera: Any, path: Path) -> FrameStats:
    """Take one frame with ``camera`` (a :class:`rig.protocols.Camera`) and write it to ``path`` as PNG,
    atomically (8-bit for ``uint8`` frames, 16-bit for ``uint16``). Returns its statistics."""
    from recon.lf.imageio import write_png

    image = camera.trigger()
    stats = frame_stats(image, top=full_scale(image, camera.settings()))
    write_png(path, image)
    return stats
