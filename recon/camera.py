"""The rectified camera of a light field, and the one formula between disparity and metric depth.

Frames and signs follow ``docs/conventions.md``. For a rectified light field whose views were taken
``pitch_mm`` apart by a camera with focal length ``focal_px`` (pixels), a point at depth ``Z`` (mm,
along the optical axis of the centre view, camera frame ``z``) has disparity::

    d = focal_px * pitch_mm / Z - d0

in pixels per view step, where ``d0`` (``disparity_offset``) is the shift applied when the views were
refocused (0 for an unshifted capture). Hence::

    Z = focal_px * pitch_mm / (d + d0)

``d + d0`` is the *effective* disparity. Where it is not positive (``<= 0``) the point would lie at
or behind infinity: no depth exists and the result is ``NaN``. ``NaN`` disparity gives ``NaN`` depth
and vice versa, so masks survive the conversion.

:class:`Camera` carries what the formula needs (and the principal point, for back-projection), so
that a reconstruction's camera travels as one value from rectification to the PLY.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from recon.lf.lightfield import LightField


#: Depths beyond this (1000 km) are "at infinity" for a light field taken on a lab stage: no depth.
MAX_DEPTH_MM = 1e9


@dataclass(frozen=True)
class Camera:
    """The rectified camera of a light field's centre view.

    Attributes
    ----------
    focal_px
        Focal length of the rectified views in pixels (> 0).
    pitch_mm
        Distance between neighbouring grid positions in mm (> 0).
    disparity_offset
        ``d0`` in pixels per view step: the refocusing shift (0 for an unshifted capture).
    principal_point_px
        ``(cx, cy)`` in pixels, x first; ``None`` means the image centre ``((W - 1) / 2, (H - 1) / 2)``.

    Raises
    ------
    ValueError
        For a focal length, pitch, offset or principal point that is not finite or lies outside
        lfrig's bounds (``recon.lf.params.camera_problem``: focal length 1 to 1e7 px, pitch 1e-6 to
        1e6 mm, ``|d0|`` up to 1e6, principal point within +-1e7 px).
    """

    focal_px: float
    pitch_mm: float
    disparity_offset: float = 0.0
    principal_point_px: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        _check_camera(self.focal_px, self.pitch_mm, self.disparity_offset)
        if self.principal_point_px is not None:
            cx, cy = self.principal_point_px
            from recon.lf.params import camera_problem

            problem = camera_problem(principal_point_px=(float(cx), float(cy)))
            if problem is not None:
                raise ValueError(problem)
            object.__setattr__(self, "principal_point_px", (float(cx), float(cy)))

    @classmethod
    def of(cls, lf: "LightField") -> "Camera | None":
        """The camera a light field records, or ``None`` when its focal length or pitch is unknown."""
        if lf.focal_px is None or lf.pitch_mm is None:
            return None
        return cls(focal_px=lf.focal_px, pitch_mm=lf.pitch_mm, disparity_offset=lf.disparity_offset,
                   principal_point_px=lf.principal_point_px)

    def depth_mm(self, disparity_px) -> np.ndarray:
        """:func:`disparity_to_depth` with this camera."""
        return disparity_to_depth(disparity_px, focal_px=self.focal_px, pitch_mm=self.pitch_mm,
                                  disparity_offset=self.disparity_offset)

    def disparity_px(self, depth_mm) -> np.ndarray:
        """:func:`depth_to_disparity` with this camera."""
        return depth_to_disparity(depth_mm, focal_px=self.focal_px, pitch_mm=self.pitch_mm,
                                  disparity_offset=self.disparity_offset)

    def principal_point(self, image_shape: tuple[int, int]) -> tuple[float, float]:
        """``(cx, cy)`` for an image of ``(H, W)`` pixels (the centre when none is recorded)."""
        if self.principal_point_px is not None:
            return self.principal_point_px
        height, width = image_shape
        return (width - 1) / 2.0, (height - 1) / 2.0

    def as_dict(self) -> dict[str, Any]:
        """The fields as ``result.json`` records them (``principal_point_px`` a list or ``None``)."""
        return {"focal_px": self.focal_px, "pitch_mm": self.pitch_mm, "disparity_offset": self.disparity_offset,
                "principal_point_px": list(self.principal_point_px) if self.principal_point_px else None}


def _check_camera(focal_px: float, pitch_mm: float, disparity_offset: float) -> None:
    from recon.lf.params import camera_problem

    for name, value in (("focal_px", focal_px), ("pitch_mm", pitch_mm), ("disparity_offset", disparity_offset)):
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name} must be a number; got {value!r}")
    problem = camera_problem(focal_px=float(focal_px), pitch_mm=float(pitch_mm), disparity_offset=float(disparity_offset))
    if problem is not None:
        raise ValueError(problem)


def _float_array(values, name: str) -> np.ndarray:
    array = np.asarray(values)
    if array.dtype.kind not in "fiu":
        raise ValueError(f"{name} must be a numeric array; got dtype {array.dtype}")
    if array.dtype.kind != "f":
        array = array.astype(np.float64)
    return array


def disparity_to_depth(
    disparity_px, *, focal_px: float, pitch_mm: float, disparity_offset: float = 0.0
) -> np.ndarray:
    """Depth along the optical axis from light-field disparity.

    ``Z_mm = focal_px * pitch_mm / (disparity_px + disparity_offset)``.

    Parameters
    ----------
    disparity_px
        Array of any shape, pixels per view step (sign as in ``docs/conventions.md``). ``NaN`` marks
        pixels without a value.
    focal_px
        Focal length of the rectified views in pixels.
    pitch_mm
        Distance between neighbouring grid positions in mm.
    disparity_offset
        ``d0`` in pixels per view step: the refocusing shift (0 for an unshifted capture).

    Returns
    -------
    depth_mm
        Same shape as ``disparity_px``, floating point (``float32`` stays ``float32``, anything else
        becomes ``float64``), mm. ``NaN`` where the effective disparity ``disparity_px +
        disparity_offset`` is not positive or not finite, or where the depth would lie beyond
        :data:`MAX_DEPTH_MM` (a disparity of 1e-40 is "at infinity", not a point 1e42 mm away).
    """
    _check_camera(focal_px, pitch_mm, disparity_offset)
    disparity = _float_array(disparity_px, "disparity_px")
    effective = disparity + disparity.dtype.type(disparity_offset)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = disparity.dtype.type(focal_px * pitch_mm) / effective
    keep = np.isfinite(effective) & (effective > 0) & (np.abs(depth) <= MAX_DEPTH_MM)
    return np.where(keep, depth, np.nan).astype(disparity.dtype)


def depth_to_disparity(
    depth_mm, *, focal_px: float, pitch_mm: float, disparity_offset: float = 0.0
) -> np.ndarray:
    """Light-field disparity from depth along the optical axis; the inverse of :func:`disparity_to_depth`.

    ``disparity_px = focal_px * pitch_mm / depth_mm - disparity_offset``.

    Parameters
    ----------
    depth_mm
        Array of any shape, mm along the camera ``z`` axis. ``NaN`` marks pixels without a value.
    focal_px, pitch_mm, disparity_offset
        As in :func:`disparity_to_depth`.

    Returns
    -------
    disparity_px
        Same shape and float dtype rule as :func:`disparity_to_depth`, pixels per view step. ``NaN``
        where ``depth_mm`` is not positive or not finite (``+inf`` is not a depth here either: store
        "at infinity" as disparity ``-disparity_offset`` yourself if you mean it).
    """
    _check_camera(focal_px, pitch_mm, disparity_offset)
    depth = _float_array(depth_mm, "depth_mm")
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = depth.dtype.type(focal_px * pitch_mm) / depth - depth.dtype.type(disparity_offset)
    return np.where(np.isfinite(depth) & (depth > 0), disparity, np.nan).astype(depth.dtype)
