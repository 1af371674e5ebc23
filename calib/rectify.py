"""Rectification: one map that makes a real capture a light field of pure translations.

Given the calibrated lens (an mrcal model) and the stage's real steps in the camera frame
(:class:`calib.stage.StageCalibration`), every view is resampled by the SAME map into a virtual
pinhole camera whose frame is aligned with the stage motion:

- ``R_rect_cam``: x along the column step ``step_v``, z perpendicular to both steps (on the camera's
  side), y = z x x. The camera then moves in the rectified xy plane.
- ``K_rect``: with the row step ``(a, b, 0)`` in that frame and ``tv = |step_v|``, the true pitch is
  ``pitch_mm = sqrt(tv * b)`` and ``fx = focal_px * pitch_mm / tv``, ``fy = focal_px * pitch_mm / b``,
  skew ``-fx * a / b``. A point at rectified depth ``Z`` then moves by exactly ``-(u - u0) * d`` in y
  and ``-(v - v0) * d`` in x with ``d = focal_px * pitch_mm / Z`` (``docs/conventions.md``), whatever
  the in-plane rotation, tilt, skew and pitch errors of the stage.

``focal_px`` defaults to the camera's ``sqrt(fx * fy)`` (so resolution is kept) and the principal
point to the image centre. The output is then cropped to the largest rectangle whose pixels all come
from inside the camera image (``crop=False`` keeps the input's size), and the principal point moves
with the crop. The rectified light field records ``focal_px``, ``pitch_mm`` and the principal point,
so depth is ``focal_px * pitch_mm / disparity`` with no other input (:class:`recon.camera.Camera`).

The pixel maps come from mrcal: a rectified pixel's ray ``R_rect_cam^T K_rect^-1 (x, y, 1)`` is
projected with the distorted model (``mrcal.project``) and the view is sampled there (cubic
interpolation, ``cv2.remap``); pixels whose source is outside the view are 0.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.errors import CalibError
from calib.stage import StageCalibration, load_model


@dataclass
class Rectification:
    """A rectifying resampling of every view.

    Attributes
    ----------
    R_rect_cam
        ``(3, 3)`` rotation from the camera frame to the rectified frame.
    K_rect
        ``(3, 3)`` upper-triangular intrinsics of the rectified views.
    focal_px, pitch_mm
        ``d = focal_px * pitch_mm / Z`` in the rectified light field (pixels per view step).
    image_size
        ``(width, height)`` of the rectified views.
    map_x, map_y
        ``(H, W)`` float32: the source pixel (x, y) in a raw view of each rectified pixel.
    lensmodel, intrinsics
        The camera model the maps were made from.
    """

    R_rect_cam: np.ndarray
    K_rect: np.ndarray
    focal_px: float
    pitch_mm: float
    image_size: tuple[int, int]
    map_x: np.ndarray
    map_y: np.ndarray
    lensmodel: str
    intrinsics: np.ndarray

    def points_to_rectified(self, q_raw: np.ndarray) -> np.ndarray:
        """Rectified pixel coordinates ``(..., 2)`` of raw-view pixels ``q_raw`` ``(..., 2)``."""
        import mrcal

        v = mrcal.unproject(np.asarray(q_raw, dtype=float), self.lensmodel, self.intrinsics)
        r = v @ self.R_rect_cam.T @ self.K_rect.T
        return r[..., :2] / r[..., 2:]

    def metadata(self) -> dict[str, Any]:
        """What a rectified light field records about its rectification (JSON-serialisable)."""
        return {"focal_px": self.focal_px, "pitch_mm": self.pitch_mm,
                "R_rect_cam": self.R_rect_cam.tolist(), "K_rect": self.K_rect.tolist(),
                "lensmodel": self.lensmodel, "intrinsics": [float(v) for v in self.intrinsics]}


def rectifying_frame(step_u_mm: np.ndarray, step_v_mm: np.ndarray, *, focal_px: float,
                     centre_px: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R_rect_cam, K_rect, pitch_mm)`` that make grid steps ``step_u_mm``/``step_v_mm`` (``(3,)``,
    camera frame, mm) pure translations of ``d = focal_px * pitch_mm / Z`` px per view step.

    Raises
    ------
    CalibError
        When the steps are (nearly) parallel, or mirrored against the image axes (``v x u`` points
        away from the scene: the grid's rows or columns run the wrong way for ``docs/conventions.md``).
    """
    su = np.asarray(step_u_mm, dtype=float)
    sv = np.asarray(step_v_mm, dtype=float)
    n = np.cross(sv, su)
    if np.linalg.norm(n) < 1e-6 * np.linalg.norm(su) * np.linalg.norm(sv):
        raise CalibError("the stage's row and column steps are parallel; the stage calibration is broken")
    if n[2] <= 0:
        raise CalibError("the grid is mirrored against the image axes (the camera should move right in the "
                         "image as v grows and down as u grows); flip one of the capture's grid axes "
                         "(--col-axis/--row-axis) and capture again")
    x = sv / np.linalg.norm(sv)
    z = n / np.linalg.norm(n)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    a, b, _ = R @ su
    tv = float(np.linalg.norm(sv))
    pitch = math.sqrt(tv * b)
    fx = focal_px * pitch / tv
    fy = focal_px * pitch / b
    K = np.array([[fx, -fx * a / b, centre_px[0]], [0.0, fy, centre_px[1]], [0.0, 0.0, 1.0]])
    return R, K, pitch


def _maps(model: Any, R: np.ndarray, K: np.ndarray, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    import mrcal

    w, h = image_size
    x, y = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays = np.stack([x, y, np.ones_like(x)], axis=-1) @ np.linalg.inv(K).T @ R  # R^T K^-1 q
    q = mrcal.project(rays, *model.intrinsics())
    q = np.where(rays[..., 2:] > 0, q, -1.0)
    return q[..., 0].astype(np.float32), q[..., 1].astype(np.float32)


def valid_crop(map_x: np.ndarray, map_y: np.ndarray, source_size: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` (inclusive) of a large rectangle of the output whose every pixel samples
    inside the source image ``source_size = (W, H)``.

    Peels whichever border row or column has the most invalid pixels until none is left: the result
    is the rectangle a user expects (no black wedges from the rotation), close to the largest.
    """
    w, h = source_size
    valid = (map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)
    y0, x0, y1, x1 = 0, 0, valid.shape[0] - 1, valid.shape[1] - 1
    while y0 < y1 and x0 < x1:
        bad = {"top": int((~valid[y0, x0:x1 + 1]).sum()), "bottom": int((~valid[y1, x0:x1 + 1]).sum()),
               "left": int((~valid[y0:y1 + 1, x0]).sum()), "right": int((~valid[y0:y1 + 1, x1]).sum())}
        side = max(bad, key=bad.get)
        if bad[side] == 0:
            return x0, y0, x1, y1
        if side == "top":
            y0 += 1
        elif side == "bottom":
            y1 -= 1
        elif side == "left":
            x0 += 1
        else:
            x1 -= 1
    raise CalibError("no part of the rectified image lies inside the camera's image; the stage calibration "
                     "or the camera model is broken")


def _output_defaults(model: Any, image_size: tuple[int, int] | None, focal_px: float | None,
                     centre_px: tuple[float, float] | None) -> tuple[tuple[int, int], float, tuple[float, float]]:
    """The output image size (the model's imager), focal length (``sqrt(fx fy)``) and principal point
    (the image centre) where the caller gave none."""
    intr = model.intrinsics()[1]
    w, h = (int(v) for v in (image_size if image_size is not None else model.imagersize()))
    if focal_px is None:
        focal_px = float(math.sqrt(intr[0] * intr[1]))
    if centre_px is None:
        centre_px = ((w - 1) / 2.0, (h - 1) / 2.0)
    return (w, h), focal_px, centre_px


def rectification(model: Any, stage: StageCalibration, *, pitch_mm: float | None = None,
                  focal_px: float | None = None, image_size: tuple[int, int] | None = None,
                  centre_px: tuple[float, float] | None = None, crop: bool = True) -> Rectification:
    """The rectification of a capture commanded at ``pitch_mm`` (default: the stage calibration's).

    ``focal_px`` defaults to the model's ``sqrt(fx fy)``, ``image_size`` to the model's imager and
    ``centre_px`` to the centre of the output image. With ``crop`` (the default) the output is then
    cut to the rectangle whose pixels all come from inside the camera image (:func:`valid_crop`), so
    no view has black borders where matching would find nothing; the principal point moves with it.
    """
    lensmodel, intr = model.intrinsics()
    (w, h), focal_px, centre_px = _output_defaults(model, image_size, focal_px, centre_px)
    su, sv = stage.steps_for(stage.pitch_mm if pitch_mm is None else pitch_mm)
    R, K, pitch = rectifying_frame(su, sv, focal_px=focal_px, centre_px=centre_px)
    map_x, map_y = _maps(model, R, K, (w, h))
    if crop:
        x0, y0, x1, y1 = valid_crop(map_x, map_y, tuple(int(v) for v in model.imagersize()))
        K = K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        map_x = np.ascontiguousarray(map_x[y0:y1 + 1, x0:x1 + 1])
        map_y = np.ascontiguousarray(map_y[y0:y1 + 1, x0:x1 + 1])
        w, h = x1 - x0 + 1, y1 - y0 + 1
    return Rectification(R, K, float(focal_px), float(pitch), (w, h), map_x, map_y, lensmodel, np.asarray(intr))


def undistortion(model: Any, *, focal_px: float | None = None, image_size: tuple[int, int] | None = None,
                 centre_px: tuple[float, float] | None = None, pitch_mm: float = 0.0) -> Rectification:
    """Undistortion alone (no rotation, square pixels): the baseline that :func:`rectification`
    improves on. Same conventions as :func:`rectification`."""
    lensmodel, intr = model.intrinsics()
    (w, h), focal_px, centre_px = _output_defaults(model, image_size, focal_px, centre_px)
    K = np.array([[focal_px, 0.0, centre_px[0]], [0.0, focal_px, centre_px[1]], [0.0, 0.0, 1.0]])
    map_x, map_y = _maps(model, np.eye(3), K, (w, h))
    return Rectification(np.eye(3), K, float(focal_px), float(pitch_mm), (w, h), map_x, map_y, lensmodel,
                         np.asarray(intr))


def rectify_views(views: np.ndarray, rect: Rectification, *, progress: Any = None) -> np.ndarray:
    """Resample every view with the one map: ``(U, V, H, W[, C])`` -> ``(U, V, H', W'[, C])``, same dtype.

    Cubic interpolation (``cv2.INTER_CUBIC``); outside the source view the result is 0. ``progress``:
    a :class:`recon.progress.ProgressCallback`, told after each view.
    """
    from recon.progress import report

    import cv2

    views = np.asarray(views)
    U, V = views.shape[:2]
    out = np.empty((U, V, rect.image_size[1], rect.image_size[0]) + views.shape[4:], dtype=views.dtype)
    work = views if views.dtype in (np.uint8, np.uint16, np.float32) else views.astype(np.float32)
    for u in range(U):
        for v in range(V):
            r = cv2.remap(work[u, v], rect.map_x, rect.map_y, interpolation=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            out[u, v] = r.reshape(out.shape[2:])
            report(progress, (u * V + v + 1) / (U * V), f"u{u:02d} v{v:02d}")
    return out


def pure_translation_fit(tracks: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """How well points follow ``(y0 - (u - u0) d, x0 - (v - v0) d)`` across the views.

    Parameters
    ----------
    tracks
        ``(U, V, N, 2)`` pixel positions ``(x, y)`` of N points in every view (NaN: not seen).

    Returns
    -------
    rms_px, disparity_px, residuals_px
        RMS of the residuals (per coordinate, pixels) after fitting ``(x0, y0, d)`` per point by least
        squares; ``(N,)`` fitted disparities; ``(U, V, N, 2)`` residuals.
    """
    tracks = np.asarray(tracks, dtype=float)
    U, V, N = tracks.shape[:3]
    ku, kv = np.meshgrid(np.arange(U) - U // 2, np.arange(V) - V // 2, indexing="ij")
    d = np.full(N, np.nan)
    resid = np.full(tracks.shape, np.nan)
    for i in range(N):
        x = tracks[:, :, i, 0].ravel()
        y = tracks[:, :, i, 1].ravel()
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < 3:
            continue
        n = int(ok.sum())
        # unknowns x0, y0, d: x = x0 - kv d, y = y0 - ku d
        A = np.zeros((2 * n, 3))
        A[:n, 0] = 1.0
        A[:n, 2] = -kv.ravel()[ok]
        A[n:, 1] = 1.0
        A[n:, 2] = -ku.ravel()[ok]
        b = np.concatenate([x[ok], y[ok]])
        sol = np.linalg.lstsq(A, b, rcond=None)[0]
        d[i] = sol[2]
        r = np.full((U * V, 2), np.nan)
        pred = A @ sol
        r[ok, 0] = x[ok] - pred[:n]
        r[ok, 1] = y[ok] - pred[n:]
        resid[:, :, i] = r.reshape(U, V, 2)
    rms = float(np.sqrt(np.nanmean(resid**2)))
    return rms, d, resid


def rectify_lightfield(lf: Any, rect: Rectification, *, progress: Any = None) -> Any:
    """A rectified copy of a :class:`recon.lf.lightfield.LightField` whose ``focal_px`` and ``pitch_mm``
    are the rectification's (``metadata["rectification"]`` records the rest)."""
    from recon.lf.lightfield import LightField

    views = rectify_views(lf.views, rect, progress=progress)
    metadata = {"rectification": rect.metadata(), "source": str(lf.source) if lf.source else None}
    return LightField(views=views, pitch_mm=rect.pitch_mm, focal_px=rect.focal_px,
                      disparity_range=None, disparity_offset=0.0,
                      principal_point_px=(float(rect.K_rect[0, 2]), float(rect.K_rect[1, 2])),
                      metadata=metadata, source=lf.source)


def rectify_capture(capture: str | os.PathLike, out: str | os.PathLike, *, model_path: str | os.PathLike,
                    stage_path: str | os.PathLike, focal_px: float | None = None, crop: bool = True,
                    verify: bool = True, progress: Any = None) -> Rectification:
    """Read a capture, rectify every view and write the result as a capture folder at ``out``.

    ``verify``: check the views against the capture's journalled checksums (``read_capture``).
    ``progress``: told the fraction done while the views are resampled (0..0.9) and when written (1).

    Raises
    ------
    CalibError
        When the model and the views differ in size or the capture has no pitch.
    """
    from recon.lf import read_lightfield
    from recon.lf.capture import write_lightfield
    from recon.progress import part, report

    model = load_model(model_path)
    stage = StageCalibration.load(stage_path)
    lf = read_lightfield(capture, verify=verify)
    h, w = lf.image_shape
    mw, mh = (int(v) for v in model.imagersize())
    if (w, h) != (mw, mh):
        raise CalibError(f"{capture}: views are {w}x{h} but {model_path} is for {mw}x{mh}; use the model "
                         "calibrated at the capture's resolution and binning")
    if not lf.pitch_mm:
        raise CalibError(f"{capture}: the capture records no pitch_mm; cannot scale the stage steps")
    if lf.disparity_offset:
        raise CalibError(f"{capture}: this light field is already shifted (refocused); rectify the raw capture")
    rect = rectification(model, stage, pitch_mm=float(lf.pitch_mm), focal_px=focal_px, crop=crop)
    rectified = rectify_lightfield(lf, rect, progress=part(progress, 0.0, 0.9))
    rectified.metadata["rectification"].update(model=str(model_path), stage=str(stage_path),
                                                capture_pitch_mm=float(lf.pitch_mm))
    write_lightfield(out, rectified, header_extra={"rectification": rectified.metadata["rectification"],
                                                   "source": str(capture)})
    report(progress, 1.0, "written")
    return rect
