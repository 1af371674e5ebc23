"""Camera intrinsics from images of a calibration board: corners by OpenCV, the solve by mrcal.

Pipeline (``calibrate_intrinsics_from_images``):

1. **Corners** (:func:`detect_corners`): ``cv2.findChessboardCornersSB`` for a chessboard (and
   ``cv2.findChessboardCorners`` where it fails), or the ChArUco detector of opencv-contrib (partial
   views allowed), then Förstner refinement (:func:`refine_corners`). Corners come back in mrcal's board
   layout, ``(rows, cols, 3)`` = ``(x, y, weight)`` with ``weight = -1`` for a corner not seen, the
   first corner the one nearer the image's top-left (the 180 deg ambiguity of a chessboard is
   resolved the same way in every image). Images without a board are listed and skipped.
2. **Solve** (:func:`calibrate_intrinsics`), in stages as mrcal's own tool does: a focal-length
   estimate from the boards' homographies (``cv2.initCameraMatrix2D``), mrcal's stereographic seed,
   a geometry-only solve, then the stereographic core, then the requested lens model (OPENCV8 by
   default) with all intrinsics, mrcal's outlier rejection and regularisation; then (not for splined
   models) again with every corner weighted by ``1 / sigma``, ``sigma`` the corners' noise measured
   by that solve (mrcal sizes its regularisation for residuals of about one weighted unit, see
   ``docs/calibration.md``).
3. **Report** (:class:`IntrinsicsResult`): RMS and worst reprojection error, the outliers, the
   projection uncertainty (``mrcal.projection_uncertainty``) at the working distance across the
   imager, and a residual picture (:func:`write_residual_picture`).

Units: pixels (``x`` right, ``y`` down, pixel centres at integers), board squares and distances in
mm. The mrcal model's reference frame is the camera (identity extrinsics).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from calib.errors import CalibError

DEFAULT_LENSMODEL = "LENSMODEL_OPENCV8"
#: Fewest images with a detected board that :func:`calibrate_intrinsics` accepts.
MIN_IMAGES = 4
#: Floor of the corner noise (px) from which :func:`calibrate_intrinsics` weights the corners:
#: weights stay below 1 / this even for corners that fit exactly (rendered, noise-free boards).
MIN_CORNER_SIGMA_PX = 1e-3
#: Re-solves with corner weights 1 / (measured noise) after the first full solve.
MAX_REWEIGHTINGS = 3


@dataclass(frozen=True)
class Board:
    """A calibration board.

    Attributes
    ----------
    cols, rows
        Inner corners per row and per column (a chessboard of ``(cols + 1) x (rows + 1)`` squares).
    square_mm
        Side of one square in mm.
    charuco_dictionary
        ``None`` for a plain chessboard, else an OpenCV ArUco dictionary name (``"DICT_5X5_100"``)
        for a ChArUco board of the same squares.
    marker_mm
        Side of the ArUco markers (ChArUco only); default 0.7 squares.
    """

    cols: int
    rows: int
    square_mm: float
    charuco_dictionary: str | None = None
    marker_mm: float | None = None

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2:
            raise CalibError(f"a board needs at least 2x2 inner corners; got {self.cols}x{self.rows}")
        if not self.square_mm > 0:
            raise CalibError(f"--square-mm must be positive; got {self.square_mm}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``: mrcal's ``(object_height_n, object_width_n)``."""
        return self.rows, self.cols

    def object_points(self) -> np.ndarray:
        """``(rows, cols, 3)`` corner positions in the board frame (mm, z = 0), mrcal's layout."""
        x, y = np.meshgrid(np.arange(self.cols) * self.square_mm, np.arange(self.rows) * self.square_mm)
        return np.stack([x, y, np.zeros_like(x)], axis=-1).astype(float)


def parse_board(text: str, *, square_mm: float, charuco: str | None = None, marker_mm: float | None = None) -> Board:
    """``"COLSxROWS"`` (inner corners, e.g. ``"10x7"``) as a :class:`Board`."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise CalibError(f"--board {text!r}: expected COLSxROWS of inner corners, e.g. 10x7")
    if not (2 <= int(m[1]) <= 200 and 2 <= int(m[2]) <= 200):
        raise CalibError(f"--board {text!r}: a board has 2 to 200 inner corners per row and per column")
    if not (math.isfinite(square_mm) and square_mm > 0):
        raise CalibError(f"--square-mm {square_mm}: give the side of one square, a positive number of mm")
    if marker_mm is not None and not (math.isfinite(marker_mm) and 0 < marker_mm < square_mm):
        raise CalibError(f"--marker-mm {marker_mm}: give a positive size smaller than the square ({square_mm} mm)")
    return Board(int(m[1]), int(m[2]), float(square_mm), charuco, marker_mm)


# ----------------------------------------------------------------------------------------------
# Corners
# ----------------------------------------------------------------------------------------------

def to_gray8(image: np.ndarray) -> np.ndarray:
    """An ``(H, W)`` ``uint8`` grey image from grey/RGB ``uint8``/``uint16``/float images."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    if img.dtype == np.uint8:
        return img
    if np.issubdtype(img.dtype, np.integer):
        img = img / 65535.0 * 255.0 if img.dtype == np.uint16 else img.astype(float)
    elif img.max() <= 1.0:
        img = img * 255.0
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _orient(corners: np.ndarray) -> np.ndarray:
    """Reverse a ``(rows, cols, 3)`` grid when its first corner is farther from the image's top-left
    than its last one (chessboards are symmetric under a half turn)."""
    first, last = corners[0, 0, :2], corners[-1, -1, :2]
    if first.sum() > last.sum():
        return corners[::-1, ::-1].copy()
    return corners


def refine_corners(gray: np.ndarray, corners_xy: np.ndarray, *, radius: int | np.ndarray = 5, blur_px: float = 1.0,
                   iterations: int = 5) -> np.ndarray:
    """Refine chessboard corners to the point where the image's edges meet (Förstner's operator).

    For a corner ``c`` every gradient ``g(q)`` near it is perpendicular to ``q - c`` (the edges are
    lines through ``c``), so ``c`` solves ``sum_q w(q) g g^T (q - c) = 0`` (Gaussian weights ``w`` of
    standard deviation ``radius / 2`` around the current estimate, gradients of the image smoothed
    by ``blur_px``). Unlike OpenCV's ``cornerSubPix`` this uses the gradients at whole pixels (no
    resampling) and the result is unbiased for any X-junction of straight edges, tilted boards
    included: on rendered boards with a realistic lens blur it is within ~0.005 px of the truth
    where ``findChessboardCornersSB`` alone is off by 0.02-0.04 px. Its noise falls as the window
    grows, so the window should be as large as the board allows (see :func:`refine_radii`).

    Parameters
    ----------
    gray
        ``(H, W)`` image.
    corners_xy
        ``(N, 2)`` starting positions ``(x, y)`` in pixels (within about a pixel of the corners).
    radius
        Window half-size in pixels: one for all corners, or ``(N,)`` one per corner.

    Returns
    -------
    ``(N, 2)`` refined positions. Near the image's edge the window shrinks to fit (2 px at least); a
    corner whose window still leaves the image, whose system is singular or that would move by more
    than ``radius / 2`` keeps its starting position.
    """
    import cv2

    f = gray.astype(np.float32)
    if blur_px > 0:
        f = cv2.GaussianBlur(f, (0, 0), blur_px)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    start = np.asarray(corners_xy, dtype=float).reshape(-1, 2)
    radii = np.broadcast_to(np.asarray(radius, dtype=int), (len(start),))
    # near the image's edge a smaller window still fits (the gradients need one pixel of margin)
    h, w = f.shape
    with np.errstate(invalid="ignore"):
        room = np.floor(np.min([start[:, 0], start[:, 1], w - 1 - start[:, 0], h - 1 - start[:, 1]], axis=0)) - 2
    radii = np.where(np.isfinite(room), np.clip(np.minimum(radii, np.nan_to_num(room)), 2, None), radii).astype(int)
    out = start.copy()
    for r in np.unique(radii):
        sel = radii == r
        out[sel] = _refine_forstner(gx, gy, start[sel], int(r), iterations)
    return out


def _refine_forstner(gx: np.ndarray, gy: np.ndarray, start: np.ndarray, radius: int, iterations: int) -> np.ndarray:
    """:func:`refine_corners` for one window radius, on precomputed gradients ``gx``, ``gy``."""
    h, w = gx.shape
    p = start.copy()
    dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    dx, dy = dx.ravel(), dy.ravel()
    ok = np.ones(len(p), dtype=bool)
    for _ in range(iterations):
        xi = np.rint(p[:, 0]).astype(int)
        yi = np.rint(p[:, 1]).astype(int)
        inside = (xi - radius >= 1) & (xi + radius < w - 1) & (yi - radius >= 1) & (yi + radius < h - 1)
        ok &= inside
        xi = np.clip(xi, radius + 1, w - radius - 2)
        yi = np.clip(yi, radius + 1, h - radius - 2)
        X = xi[:, None] + dx[None, :]
        Y = yi[:, None] + dy[None, :]
        Gx = gx[Y, X].astype(float)
        Gy = gy[Y, X].astype(float)
        wgt = np.exp(-((X - p[:, :1]) ** 2 + (Y - p[:, 1:]) ** 2) / (2 * (radius / 2.0) ** 2))
        a11 = np.sum(wgt * Gx * Gx, axis=1)
        a12 = np.sum(wgt * Gx * Gy, axis=1)
        a22 = np.sum(wgt * Gy * Gy, axis=1)
        b1 = np.sum(wgt * (Gx * Gx * X + Gx * Gy * Y), axis=1)
        b2 = np.sum(wgt * (Gx * Gy * X + Gy * Gy * Y), axis=1)
        det = a11 * a22 - a12 * a12
        good = det > 1e-9 * (a11 + a22) ** 2 + 1e-30
        ok &= good
        det = np.where(good, det, 1.0)
        new = np.stack([(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det], axis=1)
        p = np.where(good[:, None], new, p)
    moved = np.linalg.norm(p - start, axis=1)
    ok &= np.isfinite(moved) & (moved <= radius / 2.0)
    return np.where(ok[:, None], p, start)


def detect_corners(image: np.ndarray, board: Board, *, refine: bool = True) -> np.ndarray | None:
    """Find the board's inner corners in one image.

    Returns
    -------
    ``(rows, cols, 3)`` float array of ``(x, y, weight)`` (pixels; weight 1 for a detected corner,
    -1 for one not seen), or ``None`` when the board is not found (or, for ChArUco, fewer than
    a quarter of its corners are seen).
    """
    import cv2

    gray = to_gray8(image)
    if board.charuco_dictionary is None:
        # Fast first; the exhaustive search and histogram normalisation only when that fails
        # (normalisation helps in poor light but biases SB's corners by up to 0.2 px on clean
        # images; the Förstner refinement below removes what bias remains).
        found, corners = False, None
        for flags in (0, cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY,
                      cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE):
            found, corners = cv2.findChessboardCornersSB(gray, (board.cols, board.rows), flags=flags)
            if found and corners is not None:
                break
        if not found or corners is None:
            # The sector-based detector gives up on strongly foreshortened boards (squares seen as
            # thin rhombi) that OpenCV's quad-based detector still finds; its corners are only
            # pixel-accurate, which the refinement below takes care of.
            found, corners = cv2.findChessboardCorners(
                gray, (board.cols, board.rows),
                flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found or corners is None:
            return None
        xy = corners.reshape(-1, 2).astype(float)
    else:
        found_xy = _detect_charuco(gray, board)
        if found_xy is None:
            return None
        xy = found_xy[..., :2].reshape(-1, 2)
    seen = np.all(np.isfinite(xy), axis=1)
    if refine:
        fraction = 1.0 / 3.0
        if board.charuco_dictionary is not None:  # the white gap between a square's edge and its marker
            marker = board.marker_mm if board.marker_mm is not None else 0.7 * board.square_mm
            fraction = min(fraction, 0.5 * (1.0 - marker / board.square_mm))
        radii = refine_radii(xy.reshape(board.rows, board.cols, 2), fraction=fraction)
        xy[seen] = refine_corners(gray, xy[seen], radius=radii[seen])
    weight = np.where(seen, 1.0, -1.0).reshape(board.rows, board.cols, 1)
    out = np.concatenate([np.nan_to_num(xy).reshape(board.rows, board.cols, 2), weight], axis=-1)
    if board.charuco_dictionary is None:
        return _orient(out)
    return out  # ChArUco ids fix the orientation: no half-turn ambiguity


#: Largest Förstner window radius (px): 16 px windows average 4x less noise than 6 px ones.
MAX_REFINE_RADIUS_PX = 16


def refine_radii(grid_xy: np.ndarray, *, fraction: float = 1.0 / 3.0) -> np.ndarray:
    """Förstner window radius per corner of a ``(rows, cols, 2)`` grid (NaN for corners not seen):
    ``fraction`` (a third) of the smallest height of the squares around the corner (a square seen
    as a thin rhombus has edges closer to the corner than its sides are long), 2 to
    :data:`MAX_REFINE_RADIUS_PX`. A ChArUco board needs a smaller fraction: its markers' edges must
    stay outside the window.

    Returns ``(rows * cols,)`` ints.
    """
    g = np.asarray(grid_xy, dtype=float)
    rows, cols = g.shape[:2]
    a = g[:-1, 1:] - g[:-1, :-1]    # cell edge along the row
    b = g[1:, :-1] - g[:-1, :-1]    # cell edge along the column
    c = g[1:, 1:] - g[1:, :-1]      # the opposite edges (a cell is not quite a parallelogram)
    d = g[1:, 1:] - g[:-1, 1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        cross = np.abs(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])
        longest = np.max(np.stack([np.linalg.norm(v, axis=-1) for v in (a, b, c, d)]), axis=0)
        height = cross / longest
    height = np.where(np.isfinite(height) & (height > 0), height, np.inf)
    near = np.full((rows + 1, cols + 1), np.inf)
    near[1:-1, 1:-1] = height
    per_corner = np.minimum.reduce([near[:-1, :-1], near[:-1, 1:], near[1:, :-1], near[1:, 1:]])
    fallback = float(np.min(height)) if np.isfinite(height).any() else 45.0
    per_corner = np.where(np.isfinite(per_corner), per_corner, fallback)
    return np.clip(per_corner * fraction, 2, MAX_REFINE_RADIUS_PX).astype(int).ravel()


def charuco_board(board: Board):
    """The OpenCV ``CharucoBoard`` of a ChArUco :class:`Board`."""
    import cv2

    name = board.charuco_dictionary or ""
    if not hasattr(cv2.aruco, name):
        raise CalibError(f"--charuco {name!r} is not an OpenCV ArUco dictionary (try DICT_5X5_100, DICT_4X4_50, ...)")
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
    marker = board.marker_mm if board.marker_mm is not None else 0.7 * board.square_mm
    return cv2.aruco.CharucoBoard((board.cols + 1, board.rows + 1), board.square_mm, marker, dictionary)


def _detect_charuco(gray: np.ndarray, board: Board) -> np.ndarray | None:
    import cv2

    detector = cv2.aruco.CharucoDetector(charuco_board(board))
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < max(4, board.rows * board.cols // 4):
        return None
    out = np.full((board.rows, board.cols, 3), np.nan)
    out[..., 2] = -1.0
    for (x, y), i in zip(corners.reshape(-1, 2), ids.ravel()):
        out[int(i) // board.cols, int(i) % board.cols] = (x, y, 1.0)
    return out


# ----------------------------------------------------------------------------------------------
# Solve
# ----------------------------------------------------------------------------------------------

@dataclass
class IntrinsicsResult:
    """A calibrated camera and how good it is.

    Attributes
    ----------
    model
        ``mrcal.cameramodel`` with the optimisation inputs (so uncertainty can be recomputed).
    rms_px
        RMS reprojection error of the inlier corners, pixels (per corner, both coordinates).
    worst_px
        Largest inlier reprojection error (norm), pixels.
    outliers
        ``(K, 3)`` int array of ``(image index, row, col)`` of the corners rejected as outliers.
    n_corners
        Number of corners observed.
    per_image_rms_px
        ``(N,)`` RMS error of each used image's inlier corners.
    residuals_px
        ``(N, rows, cols, 2)`` reprojection residuals (observed minus predicted is mrcal's sign).
    observations
        ``(N, rows, cols, 3)`` the corners as solved: weight ``1 / sigma`` with ``sigma`` the corners'
        measured noise in pixels (at most 1 / :data:`MIN_CORNER_SIGMA_PX`, at least 1), or < 0 for an
        outlier or a corner not seen.
    uncertainty_px
        Worst-direction projection standard deviation at ``working_distance_mm``:
        ``{"centre": ..., "median": ..., "max": ...}`` over a grid on the imager.
    working_distance_mm
        Where the uncertainty is evaluated.
    used, skipped
        Names of the images used, and of those where no board was found.
    """

    model: Any
    rms_px: float
    worst_px: float
    outliers: np.ndarray
    n_corners: int
    per_image_rms_px: np.ndarray
    residuals_px: np.ndarray
    observations: np.ndarray
    uncertainty_px: dict[str, float]
    working_distance_mm: float
    used: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)

    def report(self) -> str:
        """A human-readable summary (what ``lfrig calibrate intrinsics`` prints)."""
        lensmodel, intr = self.model.intrinsics()
        w, h = self.model.imagersize()
        lines = [
            f"lens model        {lensmodel}",
            f"imager            {w} x {h} px",
            f"focal             fx {intr[0]:.2f} px, fy {intr[1]:.2f} px",
            f"principal point   ({intr[2]:.2f}, {intr[3]:.2f}) px",
            f"images            {len(self.used)} used, {len(self.skipped)} skipped (no board)",
            f"RMS reprojection  {self.rms_px:.3f} px (worst {self.worst_px:.3f} px)",
            f"outliers          {len(self.outliers)} of {self.n_corners} corners",
            "uncertainty       {centre:.3f} px at the centre, median {median:.3f}, max {max:.3f} px "
            "(worst direction, 1 sigma) at {d:.0f} mm".format(d=self.working_distance_mm, **self.uncertainty_px),
        ]
        for name in self.skipped:
            lines.append(f"skipped           {name}: board not found")
        worst = np.argsort(self.per_image_rms_px)[::-1][:3]
        for i in worst:
            name = self.used[i] if i < len(self.used) else f"image {i}"
            lines.append(f"worst images      {name}: {self.per_image_rms_px[i]:.3f} px RMS")
        return "\n".join(lines)


def _focal_estimate(observations: np.ndarray, board: Board, image_size: tuple[int, int]) -> float:
    """Pinhole focal length (px) from the boards' homographies (Zhang's method via OpenCV)."""
    import cv2

    obj = board.object_points().reshape(-1, 3).astype(np.float32)
    object_points, image_points = [], []
    for obs in observations:
        ok = obs[..., 2].ravel() > 0
        if ok.sum() < 6:
            continue
        object_points.append(obj[ok])
        image_points.append(obs[..., :2].reshape(-1, 2)[ok].astype(np.float32))
    K = cv2.initCameraMatrix2D(object_points, image_points, tuple(int(v) for v in image_size))
    f = float(np.sqrt(K[0, 0] * K[1, 1]))
    if not np.isfinite(f) or f <= 0:
        raise CalibError("could not estimate a focal length from the boards; use images with the board tilted "
                         "in different directions, or pass --focal-px")
    return f


def calibrate_intrinsics(observations: np.ndarray, *, board: Board, image_size: tuple[int, int],
                         lensmodel: str = DEFAULT_LENSMODEL, focal_estimate_px: float | None = None,
                         working_distance_mm: float = 1000.0, names: Sequence[str] | None = None) -> IntrinsicsResult:
    """Solve a monocular calibration with mrcal.

    Parameters
    ----------
    observations
        ``(N, rows, cols, 3)``: ``(x, y, weight)`` per corner, pixels; weight <= 0 excludes a corner.
    board
        The board (its ``square_mm`` sets the scale; ``(rows, cols)`` must match ``observations``).
    image_size
        ``(width, height)`` of the images in pixels.
    lensmodel
        mrcal lens model, e.g. ``LENSMODEL_OPENCV8`` (default), ``LENSMODEL_OPENCV4``,
        ``LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=15``.
    focal_estimate_px
        Seed for the focal length; estimated from the boards when omitted.
    working_distance_mm
        Distance at which the projection uncertainty is reported.

    Raises
    ------
    CalibError
        Fewer than :data:`MIN_IMAGES` observations, a lens model mrcal does not know, or a solve that
        does not converge to a sensible answer.
    """
    import mrcal

    obs = np.array(observations, dtype=float)
    if obs.ndim != 4 or obs.shape[1:] != (board.rows, board.cols, 3):
        raise ValueError(f"observations must be (N, {board.rows}, {board.cols}, 3); got {obs.shape}")
    n = obs.shape[0]
    if n < MIN_IMAGES:
        raise CalibError(f"only {n} usable board image(s); at least {MIN_IMAGES} are needed (mrcal's advice: "
                         "dozens, covering the whole imager, board tilted both ways)")
    try:
        mrcal.lensmodel_num_params(lensmodel)
    except Exception:
        raise CalibError(f"--lensmodel {lensmodel!r} is not an mrcal lens model (e.g. LENSMODEL_OPENCV8)") from None
    names = list(names) if names is not None else [f"image {i}" for i in range(n)]
    obs[..., 2] = np.where(obs[..., 2] > 0, 1.0, -1.0)
    if focal_estimate_px is None:
        focal_estimate_px = _focal_estimate(obs, board, image_size)

    imagersizes = np.array([image_size], dtype=np.int32)
    indices_frame_camera = np.stack([np.arange(n), np.zeros(n)], axis=1).astype(np.int32)
    # mrcal's seed (a PnP per image) ignores corners with weight < 0, like the optimiser.
    intrinsics, rt_cam_ref, rt_ref_frame = mrcal.seed_stereographic(
        imagersizes=imagersizes, focal_estimate=focal_estimate_px,
        indices_frame_camera=indices_frame_camera, observations=obs, object_spacing=board.square_mm)
    indices = np.concatenate([indices_frame_camera, indices_frame_camera[:, 1:] - 1], axis=1).astype(np.int32)
    common = dict(rt_cam_ref=rt_cam_ref, rt_ref_frame=rt_ref_frame, points=None, observations_board=obs,
                  indices_frame_camintrinsics_camextrinsics=indices, observations_point=None,
                  indices_point_camintrinsics_camextrinsics=None, imagersizes=imagersizes,
                  calibration_object_spacing=board.square_mm, verbose=False)
    # Stage 1-2: geometry only, then the stereographic core, no outlier rejection yet.
    for core in (False, True):
        mrcal.optimize(intrinsics=intrinsics, lensmodel="LENSMODEL_STEREOGRAPHIC",
                       do_optimize_intrinsics_core=core, do_optimize_intrinsics_distortions=False,
                       do_optimize_calobject_warp=False, do_optimize_extrinsics=False,
                       do_optimize_frames=True, do_apply_outlier_rejection=False,
                       do_apply_regularization=False, **common)
    # Stage 3: the requested model, distortions from zero (a narrow lens is nearly stereographic
    # and pinhole alike), everything free, outliers rejected, regularised.
    n_params = mrcal.lensmodel_num_params(lensmodel)
    meta = mrcal.lensmodel_metadata_and_config(lensmodel)
    full = np.zeros((1, n_params))
    if meta.get("has_core", 1):
        full[0, :4] = intrinsics[0, :4]
    else:  # pragma: no cover - models without a core are not used here
        raise CalibError(f"{lensmodel} has no intrinsics core; use an OPENCV or SPLINED model")
    if lensmodel.startswith("LENSMODEL_SPLINED"):
        # splined models carry a stereographic core; keep it fixed, as mrcal's tool does
        do_core = False
    else:
        do_core = True
    optimization_inputs = dict(intrinsics=full, lensmodel=lensmodel, do_optimize_intrinsics_core=do_core,
                               do_optimize_intrinsics_distortions=True, do_optimize_calobject_warp=False,
                               do_optimize_extrinsics=False, do_optimize_frames=True,
                               do_apply_outlier_rejection=True, do_apply_regularization=True, **common)
    stats = mrcal.optimize(**optimization_inputs)
    # Stage 4: weight the corners by their measured noise and solve again. mrcal's regularisation
    # (distortions towards 0, principal point towards the centre) is sized for residuals of about
    # one unit; corners good to 0.01-0.03 px with weight 1 let it dominate and bias the model
    # (docs/calibration.md, "Why lfrig was behind OpenCV"). Weights 1/sigma make the weighted
    # residuals about 1, as mrcal expects; every seen corner gets a new chance as an inlier.
    # Not for splined models: there the regularisation is what keeps the spline smooth where no
    # board was seen (weighting made a 16x12 spline on 25 boards far worse in the imager's corners).
    seen = np.array(observations, dtype=float)[..., 2] > 0
    weight = 1.0
    for _ in range(0 if lensmodel.startswith("LENSMODEL_SPLINED") else MAX_REWEIGHTINGS):
        sigma_px = _inlier_rms(stats["x"], obs, n, board) / weight
        new_weight = 1.0 / max(sigma_px, MIN_CORNER_SIGMA_PX)
        if new_weight <= 1.0 or abs(new_weight / weight - 1.0) < 0.25:
            break
        weight = new_weight
        obs[..., 2] = np.where(seen, weight, -1.0)
        stats = mrcal.optimize(**optimization_inputs)
    model = mrcal.cameramodel(optimization_inputs=optimization_inputs, icam_intrinsics=0)

    residuals = stats["x"][: obs.size // 3 * 2].reshape(n, board.rows, board.cols, 2) / weight
    inlier = obs[..., 2] > 0
    err = np.linalg.norm(residuals, axis=-1)
    if not inlier.any():
        raise CalibError("every corner was rejected as an outlier; check --board and --square-mm")
    rms = float(np.sqrt(np.mean(err[inlier] ** 2) / 2))
    per_image = np.array([float(np.sqrt(np.mean(e[m] ** 2) / 2)) if m.any() else math.nan
                          for e, m in zip(err, inlier)])
    outliers = np.argwhere(seen & ~inlier)
    if not np.isfinite(rms) or rms > 10.0:
        raise CalibError(f"the calibration did not converge (RMS {rms:.1f} px); check --board COLSxROWS "
                         "(inner corners) and --square-mm, and look at the residual picture")
    uncertainty = projection_uncertainty_summary(model, distance_mm=working_distance_mm)
    return IntrinsicsResult(model=model, rms_px=rms, worst_px=float(err[inlier].max()), outliers=outliers,
                            n_corners=int(seen.sum()), per_image_rms_px=per_image, residuals_px=residuals,
                            observations=obs, uncertainty_px=uncertainty,
                            working_distance_mm=float(working_distance_mm), used=names)


def _inlier_rms(x: np.ndarray, obs: np.ndarray, n: int, board: Board) -> float:
    """RMS per coordinate of the (weighted) residuals ``x`` of the inlier corners of ``obs``."""
    residuals = np.asarray(x)[: obs.size // 3 * 2].reshape(n, board.rows, board.cols, 2)
    inlier = obs[..., 2] > 0
    if not inlier.any():
        return math.inf
    return float(np.sqrt(np.mean(residuals[inlier] ** 2)))


def projection_uncertainty_summary(model: Any, *, distance_mm: float, grid: tuple[int, int] = (12, 9)) -> dict[str, float]:
    """Worst-direction 1-sigma projection uncertainty (px) of points at ``distance_mm`` seen across
    the imager on a ``grid`` of ``(nx, ny)`` pixels: ``{"centre", "median", "max"}``."""
    import mrcal

    w, h = model.imagersize()
    xs = np.linspace(0.05 * (w - 1), 0.95 * (w - 1), grid[0])
    ys = np.linspace(0.05 * (h - 1), 0.95 * (h - 1), grid[1])
    q = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    q = np.concatenate([q, [[(w - 1) / 2, (h - 1) / 2]]])
    p = distance_mm * mrcal.unproject(q, *model.intrinsics(), normalize=True)
    sigma = mrcal.projection_uncertainty(p, model=model, what="worstdirection-stdev")
    return {"centre": float(sigma[-1]), "median": float(np.median(sigma[:-1])), "max": float(np.max(sigma[:-1]))}


def projection_difference(model_a: Any, model_b: Any, *, distance_mm: float, gridn_width: int = 40,
                          restarts: int = 4) -> np.ndarray:
    """How far two camera models project the same points apart, up to the rotation between their
    frames (which no calibration can see): ``mrcal.projection_diff`` at ``distance_mm``.

    mrcal fits that implied rotation from a random starting point (``np.random``), and now and then
    lands in a poor local minimum (0.07 px instead of 0.01 px on the same pair). This runs the fit
    from ``restarts`` seeded starts, keeps the global random state as it was, and returns the
    difference of the best fit: ``(gridn_height, gridn_width)`` pixels.
    """
    import mrcal

    state = np.random.get_state()
    best = None
    try:
        for seed in range(restarts):
            np.random.seed(seed)
            diff = mrcal.projection_diff((model_a, model_b), gridn_width=gridn_width, distance=distance_mm,
                                         use_uncertainties=False, focus_radius=1e6)[0]
            if best is None or np.mean(diff**2) < np.mean(best**2):
                best = diff
    finally:
        np.random.set_state(state)
    return best


# ----------------------------------------------------------------------------------------------
# Images -> result, and the residual picture
# ----------------------------------------------------------------------------------------------

def _read_image(path: Path) -> np.ndarray:
    from recon.errors import LightFieldFormatError
    from recon.lf.imageio import read_image

    try:
        return read_image(Path(path))
    except LightFieldFormatError as error:
        raise CalibError(str(error)) from None


def calibrate_intrinsics_from_images(paths: Sequence[str | os.PathLike], *, board: Board,
                                     lensmodel: str = DEFAULT_LENSMODEL, focal_estimate_px: float | None = None,
                                     working_distance_mm: float = 1000.0,
                                     progress: Any = None) -> IntrinsicsResult:
    """Detect the board in every image and calibrate from those where it was found.

    Images must all have the same size. ``progress``, if given, is called as
    ``progress(fraction, file_name)`` (:mod:`recon.progress`) after each image.

    Raises
    ------
    CalibError
        Unreadable images, mixed sizes, or fewer than :data:`MIN_IMAGES` images with a board (the
        message lists the skipped images).
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise CalibError("no images given; pass the board images, e.g. boards/*.png")
    observations, used, skipped = [], [], []
    size = None
    for i, path in enumerate(paths):
        image = _read_image(path)
        this = (image.shape[1], image.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise CalibError(f"{path}: image is {this[0]}x{this[1]}, the first was {size[0]}x{size[1]}; "
                             "calibrate one camera setting (resolution, binning) at a time")
        corners = detect_corners(image, board)
        if corners is None:
            skipped.append(str(path))
        else:
            observations.append(corners)
            used.append(str(path))
        if progress is not None:
            progress((i + 1) / len(paths), path.name)
    if len(observations) < MIN_IMAGES:
        listed = ", ".join(Path(s).name for s in skipped[:8]) + (" ..." if len(skipped) > 8 else "")
        raise CalibError(
            f"the {board.cols}x{board.rows} board was found in only {len(observations)} of {len(paths)} images "
            f"(at least {MIN_IMAGES} needed); not found in: {listed or 'none'}. Check --board (inner corners, "
            "COLSxROWS) and that the whole board is in the picture")
    result = calibrate_intrinsics(np.stack(observations), board=board, image_size=size, lensmodel=lensmodel,
                                  focal_estimate_px=focal_estimate_px, working_distance_mm=working_distance_mm,
                                  names=used)
    result.skipped = skipped
    return result


def write_residual_picture(result: IntrinsicsResult, path: str | os.PathLike, *, scale: float | None = None) -> float:
    """Draw every corner's reprojection residual as an arrow over the imager and write a PNG.

    Arrows are magnified by ``scale`` (default: so that the 95th-percentile residual is 2 % of the
    image width) and coloured from green (small) to red (>= 3x RMS); outliers are purple crosses.
    Returns the magnification used.
    """
    import cv2

    w, h = (int(v) for v in result.model.imagersize())
    canvas = np.full((h, w, 3), 255, np.uint8)
    obs = result.observations
    res = result.residuals_px
    inlier = obs[..., 2] > 0
    err = np.linalg.norm(res, axis=-1)
    if scale is None:
        p95 = float(np.percentile(err[inlier], 95)) if inlier.any() else 1.0
        scale = 0.02 * w / max(p95, 1e-6)
    thickness = max(1, w // 800)
    for (x, y), (dx, dy), e, ok in zip(obs[..., :2].reshape(-1, 2), res.reshape(-1, 2), err.ravel(), inlier.ravel()):
        if not ok:
            continue
        t = min(e / max(3 * result.rms_px, 1e-9), 1.0)
        colour = (0, int(200 * (1 - t)), int(255 * t))  # BGR
        p0 = (int(round(x)), int(round(y)))
        p1 = (int(round(x + scale * dx)), int(round(y + scale * dy)))
        cv2.arrowedLine(canvas, p0, p1, colour, thickness, tipLength=0.3)
    for i, r, c in result.outliers:
        x, y = obs[i, r, c, :2]
        cv2.drawMarker(canvas, (int(round(x)), int(round(y))), (200, 0, 160), cv2.MARKER_TILTED_CROSS,
                       max(8, w // 100), thickness)
    text = f"residuals x{scale:.0f}   RMS {result.rms_px:.3f} px   outliers {len(result.outliers)}"
    cv2.putText(canvas, text, (10, max(20, h // 30)), cv2.FONT_HERSHEY_SIMPLEX, max(0.5, w / 1600), (0, 0, 0),
                thickness, cv2.LINE_AA)
    if not cv2.imwrite(str(path), canvas):
        raise CalibError(f"{path}: cannot write the residual picture here")
    return float(scale)
