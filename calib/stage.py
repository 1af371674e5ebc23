"""Stage geometry: the camera's real steps from a capture of a board seen in every view.

The camera only translates while the stage scans, so in the camera frame the board is seen in view
``(u, v)`` at::

    p = R_cam_board @ P + t_centre - (u - u0) * step_u - (v - v0) * step_v

with ONE rotation ``R_cam_board`` for all views, the board's position ``t_centre`` in the centre
view, and the two step vectors ``step_u`` (one grid row) and ``step_v`` (one grid column) in the
camera frame, mm. These 12 numbers are fitted jointly to every corner of every view by least squares
on the reprojection error (pixels, through the calibrated mrcal model), with outlier rejection.
A pose per view would be badly conditioned with a narrow lens (depth and tilt trade off); the shared
rotation and the lattice make the fit well determined.

The step lengths are the true pitch (the board's squares set the scale), the angle between them the
axis skew, and their direction against the image axes the in-plane rotation and tilt of the stage.
:mod:`calib.rectify` turns them into one rectifying map.

File: JSON (``{"format": "lfrig-stage", "version": 1, ...}``), see :meth:`StageCalibration.save`.
"""

from __future__ import annotations

import io
import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calib.errors import CalibError
from recon.lf.params import is_finite
from calib.intrinsics import Board, detect_corners

FORMAT = "lfrig-stage"
VERSION = 1
#: Fewest views with a detected board that :func:`calibrate_stage` accepts.
MIN_VIEWS = 4


def _rotation(r: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (radians), Rodrigues' formula."""
    angle = float(np.linalg.norm(r))
    if angle < 1e-15:
        return np.eye(3)
    k = np.asarray(r, dtype=float) / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


@dataclass
class StageCalibration:
    """The fitted stage geometry.

    Attributes
    ----------
    grid
        ``(rows, cols)`` of the calibration capture.
    pitch_mm
        Commanded (nominal) pitch of the calibration capture, mm.
    step_u_mm, step_v_mm
        ``(3,)`` camera displacement per grid row / column step in the camera frame, mm.
    r_cam_board, t_cam_board_mm
        The board's pose in the centre view (rotation vector, radians; translation of its first
        corner, mm).
    rms_px, max_px
        RMS (per coordinate) and largest reprojection error of the inlier corners, pixels.
    n_views, n_corners, n_outliers
        Views used, corners used, corners rejected.
    skipped
        Views ``"uUU_vVV"`` where the board was not found.
    per_view_rms_px
        ``{"uUU_vVV": rms}`` per view.
    lensmodel, intrinsics
        The camera model the fit used (for the record).
    """

    grid: tuple[int, int]
    pitch_mm: float
    step_u_mm: np.ndarray
    step_v_mm: np.ndarray
    r_cam_board: np.ndarray
    t_cam_board_mm: np.ndarray
    rms_px: float
    max_px: float
    n_views: int
    n_corners: int
    n_outliers: int
    skipped: list[str] = field(default_factory=list)
    per_view_rms_px: dict[str, float] = field(default_factory=dict)
    lensmodel: str = ""
    intrinsics: list[float] = field(default_factory=list)

    # -- derived numbers ---------------------------------------------------------------------

    @property
    def pitch_u_mm(self) -> float:
        """True length of one grid-row step, mm."""
        return float(np.linalg.norm(self.step_u_mm))

    @property
    def pitch_v_mm(self) -> float:
        """True length of one grid-column step, mm."""
        return float(np.linalg.norm(self.step_v_mm))

    @property
    def skew_deg(self) -> float:
        """90 deg minus the angle between the two steps."""
        c = float(self.step_u_mm @ self.step_v_mm) / (self.pitch_u_mm * self.pitch_v_mm)
        return 90.0 - math.degrees(math.acos(max(-1.0, min(1.0, c))))

    @property
    def rotation_deg(self) -> float:
        """In-plane angle of the column step against the image's x axis (positive: towards +y)."""
        return math.degrees(math.atan2(self.step_v_mm[1], self.step_v_mm[0]))

    @property
    def tilt_deg(self) -> float:
        """Angle between the optical axis and the normal of the plane the camera moves in."""
        n = np.cross(self.step_v_mm, self.step_u_mm)
        return math.degrees(math.acos(min(1.0, abs(n[2]) / np.linalg.norm(n))))

    def steps_for(self, pitch_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """``(step_u, step_v)`` (camera frame, mm) of a grid commanded at ``pitch_mm`` (the stage's
        errors scale with the commanded distance)."""
        scale = pitch_mm / self.pitch_mm
        return self.step_u_mm * scale, self.step_v_mm * scale

    def report(self) -> str:
        """Human-readable summary (what ``lfrig calibrate stage`` prints)."""
        p = self.pitch_mm
        return "\n".join([
            f"views             {self.n_views} used of {self.grid[0]}x{self.grid[1]}, {len(self.skipped)} without a board",
            f"corners           {self.n_corners} used, {self.n_outliers} rejected as outliers",
            f"residual          {self.rms_px:.3f} px RMS, worst {self.max_px:.3f} px",
            f"pitch (rows, u)   {self.pitch_u_mm:.5f} mm  ({(self.pitch_u_mm / p - 1) * 100:+.3f} % of {p:g} mm)",
            f"pitch (cols, v)   {self.pitch_v_mm:.5f} mm  ({(self.pitch_v_mm / p - 1) * 100:+.3f} % of {p:g} mm)",
            f"axis skew         {self.skew_deg:+.3f} deg",
            f"in-plane rotation {self.rotation_deg:+.3f} deg",
            f"tilt              {self.tilt_deg:.3f} deg",
            f"board distance    {float(np.linalg.norm(self.t_cam_board_mm)):.1f} mm",
        ])

    # -- file ---------------------------------------------------------------------------------

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        for key in ("step_u_mm", "step_v_mm", "r_cam_board", "t_cam_board_mm"):
            d[key] = [float(v) for v in np.asarray(getattr(self, key))]
        d["grid"] = list(self.grid)
        d["derived"] = {"pitch_u_mm": self.pitch_u_mm, "pitch_v_mm": self.pitch_v_mm, "skew_deg": self.skew_deg,
                        "rotation_deg": self.rotation_deg, "tilt_deg": self.tilt_deg}
        return {"format": FORMAT, "version": VERSION, **d}

    def save(self, path: str | os.PathLike) -> None:
        """Write as JSON (``derived`` holds the derived numbers, for people; it is not read back)."""
        from recon.lf.imageio import write_bytes_atomic

        write_bytes_atomic(Path(path), (json.dumps(self.to_json(), indent=2) + "\n").encode("utf-8"))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "StageCalibration":
        from recon.lf.imageio import read_bytes

        path = Path(path)
        data = read_bytes(path, error=CalibError, max_bytes=16 << 20,
                          missing="no such stage calibration; make one with `lfrig calibrate stage`")
        try:
            d = json.loads(data.decode("utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
            raise CalibError(f"{path}: not valid JSON ({e}); make it again with `lfrig calibrate stage`") from None
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise CalibError(f"{path}: not an lfrig stage calibration (format {FORMAT!r})")
        if d.get("version") != VERSION:
            raise CalibError(f"{path}: stage calibration version {d.get('version')!r}; this lfrig reads {VERSION}")
        d.pop("format")
        d.pop("version")
        d.pop("derived", None)
        try:
            stage = cls(
                grid=tuple(d.pop("grid")),
                step_u_mm=np.asarray(d.pop("step_u_mm"), dtype=float),
                step_v_mm=np.asarray(d.pop("step_v_mm"), dtype=float),
                r_cam_board=np.asarray(d.pop("r_cam_board"), dtype=float),
                t_cam_board_mm=np.asarray(d.pop("t_cam_board_mm"), dtype=float),
                **d,
            )
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            raise CalibError(f"{path}: incomplete or malformed stage calibration ({e}); make it again "
                             "with `lfrig calibrate stage`") from None
        problem = stage._problem()
        if problem:
            raise CalibError(f"{path}: {problem}; make it again with `lfrig calibrate stage`")
        return stage

    def _problem(self) -> str | None:
        """What makes a loaded calibration unusable, or ``None``."""
        def number(value: Any) -> bool:
            return isinstance(value, (int, float)) and not isinstance(value, bool) and is_finite(value)

        if not (len(self.grid) == 2 and all(isinstance(n, int) and not isinstance(n, bool) and n > 0
                                             for n in self.grid)):
            return f"grid = {list(self.grid)!r} must be [rows, cols], positive integers"
        if not (number(self.pitch_mm) and self.pitch_mm > 0):
            return f"pitch_mm = {self.pitch_mm!r} must be a positive number of mm"
        for name in ("step_u_mm", "step_v_mm", "r_cam_board", "t_cam_board_mm"):
            vector = getattr(self, name)
            if vector.shape != (3,) or not np.isfinite(vector).all():
                return f"{name} must be three finite numbers; got {vector.tolist()!r}"
        if not (self.pitch_u_mm > 0 and self.pitch_v_mm > 0):
            return "a step vector is zero"
        if not np.linalg.norm(np.cross(self.step_u_mm, self.step_v_mm)) > 1e-9 * self.pitch_u_mm * self.pitch_v_mm:
            return "the two step vectors are parallel"
        for name in ("rms_px", "max_px"):
            if not (number(getattr(self, name)) and getattr(self, name) >= 0):
                return f"{name} = {getattr(self, name)!r} must be a number >= 0"
        for name in ("n_views", "n_corners", "n_outliers"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
                return f"{name} = {value!r} must be an integer >= 0"
        if not (isinstance(self.skipped, list) and all(isinstance(v, str) for v in self.skipped)):
            return "skipped must be a list of view names"
        if not (isinstance(self.per_view_rms_px, dict) and all(number(v) for v in self.per_view_rms_px.values())):
            return "per_view_rms_px must map view names to numbers"
        if not isinstance(self.lensmodel, str):
            return "lensmodel must be a string"
        if not (isinstance(self.intrinsics, list) and all(number(v) for v in self.intrinsics)):
            return "intrinsics must be a list of numbers"
        return None


# ----------------------------------------------------------------------------------------------
# The fit
# ----------------------------------------------------------------------------------------------

def _seed(model: Any, obs: np.ndarray, board: Board, ku: np.ndarray, kv: np.ndarray) -> np.ndarray:
    """Initial ``[r, t_centre, step_u, step_v]``: a PnP of the view nearest the centre for the
    rotation, then per-view translations (linear, rotation fixed) regressed on the lattice."""
    import cv2
    import mrcal

    P = board.object_points().reshape(-1, 3)
    n_views = obs.shape[0]
    rays = []
    for k in range(n_views):
        v = mrcal.unproject(obs[k, ..., :2].reshape(-1, 2), *model.intrinsics())
        rays.append(v[:, :2] / v[:, 2:])
    centre = int(np.argmin(ku**2 + kv**2))
    ok = obs[centre, ..., 2].ravel() > 0
    found, rvec, tvec = cv2.solvePnP(P[ok], rays[centre][ok], np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if not found:
        raise CalibError("could not find the board's pose in the centre view; check --board and --square-mm")
    R = _rotation(rvec.ravel())
    RP = P @ R.T
    ts = np.zeros((n_views, 3))
    for k in range(n_views):
        ok = obs[k, ..., 2].ravel() > 0
        x, y = rays[k][ok, 0], rays[k][ok, 1]
        X, Y, Z = RP[ok].T
        zero, one = np.zeros_like(x), np.ones_like(x)
        A = np.concatenate([np.stack([one, zero, -x], axis=1), np.stack([zero, one, -y], axis=1)])
        b = np.concatenate([x * Z - X, y * Z - Y])
        ts[k] = np.linalg.lstsq(A, b, rcond=None)[0]
    # t_k = t_centre - ku step_u - kv step_v
    M = np.stack([np.ones(n_views), -ku, -kv], axis=1)
    coef = np.linalg.lstsq(M, ts, rcond=None)[0]
    return np.concatenate([rvec.ravel(), coef[0], coef[1], coef[2]])


def _predict(params: np.ndarray, model: Any, P: np.ndarray, ku: np.ndarray, kv: np.ndarray) -> np.ndarray:
    """Projected corners ``(n_views, n_corners, 2)`` of the lattice model."""
    import mrcal

    R = _rotation(params[0:3])
    t0, su, sv = params[3:6], params[6:9], params[9:12]
    p = (P @ R.T)[None, :, :] + (t0[None, :] - ku[:, None] * su[None, :] - kv[:, None] * sv[None, :])[:, None, :]
    return mrcal.project(p, *model.intrinsics())


def calibrate_stage(corners: np.ndarray, *, model: Any, board: Board, pitch_mm: float,
                    outlier_sigmas: float = 6.0) -> StageCalibration:
    """Fit the stage geometry to board corners seen from every grid position.

    Parameters
    ----------
    corners
        ``(U, V, rows, cols, 3)`` corners ``(x, y, weight)`` per view (weight <= 0: not seen; a view
        with no corner seen is skipped).
    model
        The calibrated ``mrcal.cameramodel`` of the camera (same image size as the views).
    board
        The board (its ``square_mm`` sets the scale of the steps).
    pitch_mm
        Commanded pitch of the capture, mm.
    outlier_sigmas
        Corners farther than this many robust standard deviations (per coordinate, and at least
        0.05 px) from the fit are rejected and the fit repeated (twice at most).

    Raises
    ------
    CalibError
        Fewer than :data:`MIN_VIEWS` views with a board, or views that do not span two grid rows and
        two grid columns.
    """
    from scipy.optimize import least_squares

    corners = np.asarray(corners, dtype=float)
    U, V = corners.shape[:2]
    u0, v0 = U // 2, V // 2
    seen_view = np.any(corners[..., 2] > 0, axis=(2, 3))
    skipped = [f"u{u:02d}_v{v:02d}" for u in range(U) for v in range(V) if not seen_view[u, v]]
    us, vs = np.nonzero(seen_view)
    if len(us) < MIN_VIEWS:
        raise CalibError(f"the board was found in only {len(us)} of {U * V} views (at least {MIN_VIEWS} needed); "
                         "the board must be whole in every view: move it farther or use a smaller one")
    if len(set(us)) < 2 or len(set(vs)) < 2:
        raise CalibError("the views with a board do not span two grid rows and two grid columns; both step "
                         "vectors need views along both axes")
    obs = corners[us, vs]  # (n, rows, cols, 3)
    ku = (us - u0).astype(float)
    kv = (vs - v0).astype(float)
    P = board.object_points().reshape(-1, 3)
    q = obs[..., :2].reshape(len(us), -1, 2)
    use = obs[..., 2].reshape(len(us), -1) > 0
    params = _seed(model, obs, board, ku, kv)
    n_outliers = 0
    for _ in range(3):
        mask = use.copy()

        def residuals(x: np.ndarray) -> np.ndarray:
            return (_predict(x, model, P, ku, kv) - q)[mask].ravel()

        fit = least_squares(residuals, params, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12)
        params = fit.x
        r = np.linalg.norm(_predict(params, model, P, ku, kv) - q, axis=-1)
        sigma = 1.4826 * float(np.median(np.abs((_predict(params, model, P, ku, kv) - q)[mask])))
        bad = mask & (r > max(outlier_sigmas * sigma, 0.05))
        if not bad.any():
            break
        use &= ~bad
        n_outliers += int(bad.sum())
    resid = (_predict(params, model, P, ku, kv) - q)
    err = np.linalg.norm(resid, axis=-1)
    per_view = {f"u{u:02d}_v{v:02d}": float(np.sqrt(np.mean(resid[k][use[k]] ** 2))) if use[k].any() else math.nan
                for k, (u, v) in enumerate(zip(us, vs))}
    lensmodel, intr = model.intrinsics()
    return StageCalibration(
        grid=(U, V), pitch_mm=float(pitch_mm), step_u_mm=params[6:9].copy(), step_v_mm=params[9:12].copy(),
        r_cam_board=params[0:3].copy(), t_cam_board_mm=params[3:6].copy(),
        rms_px=float(np.sqrt(np.mean(resid[use] ** 2))), max_px=float(err[use].max()),
        n_views=len(us), n_corners=int(use.sum()), n_outliers=n_outliers, skipped=skipped,
        per_view_rms_px=per_view, lensmodel=lensmodel, intrinsics=[float(v) for v in intr])


def detect_grid_corners(views: np.ndarray, board: Board, *, progress: Any = None) -> np.ndarray:
    """Board corners ``(U, V, rows, cols, 3)`` of every view of a light field ``(U, V, H, W[, 3])``
    (weight -1 everywhere in a view without a board). ``progress(fraction, view)`` is called per view (:mod:`recon.progress`)."""
    U, V = views.shape[:2]
    out = np.zeros((U, V, board.rows, board.cols, 3))
    out[..., 2] = -1.0
    for u in range(U):
        for v in range(V):
            c = detect_corners(views[u, v], board)
            if c is not None:
                out[u, v] = c
            if progress is not None:
                progress((u * V + v + 1) / (U * V), f"u{u:02d} v{v:02d}")
    return out


def calibrate_stage_from_capture(path: str | os.PathLike, *, model: Any, board: Board,
                                 progress: Any = None, verify: bool = True) -> tuple[StageCalibration, np.ndarray]:
    """Read a capture of a board (``recon.lf.capture`` / benchmark layout), find the corners in every view
    and fit. Returns the calibration and the corners ``(U, V, rows, cols, 3)``. ``verify``: check the
    views against the capture's journalled checksums.

    Raises
    ------
    CalibError
        When the views and the model differ in size, the capture has no pitch, or the fit fails.
    """
    from recon.lf import read_lightfield

    lf = read_lightfield(path, verify=verify)
    h, w = lf.image_shape
    mw, mh = (int(v) for v in model.imagersize())
    if (w, h) != (mw, mh):
        raise CalibError(f"{path}: views are {w}x{h} but the camera model is {mw}x{mh}; calibrate the camera "
                         "at the capture's resolution and binning")
    if not lf.pitch_mm:
        raise CalibError(f"{path}: the capture records no pitch_mm; it is needed to scale the step vectors")
    corners = detect_grid_corners(lf.views, board, progress=progress)
    return calibrate_stage(corners, model=model, board=board, pitch_mm=float(lf.pitch_mm)), corners


def load_model(path: str | os.PathLike):
    """Read an mrcal ``.cameramodel`` file, with an error that names the file."""
    import mrcal

    from recon.lf.imageio import read_bytes

    path = Path(path)
    data = read_bytes(path, error=CalibError, max_bytes=64 << 20,  # read once, bounded: mrcal reads it whole
                      missing="no such camera model; make one with `lfrig calibrate intrinsics`")
    try:
        model = mrcal.cameramodel(io.StringIO(data.decode("utf-8")))
    except Exception as e:  # mrcal raises plain exceptions for broken files
        raise CalibError(f"{path}: not a readable mrcal camera model ({e})") from None
    problem = _model_problem(model)
    if problem:
        raise CalibError(f"{path}: {problem}; calibrate the camera again with `lfrig calibrate intrinsics`")
    return model


def _model_problem(model: Any) -> str | None:
    """What makes a read camera model unusable (zero or negative focal length, non-finite numbers,
    an empty imager), or ``None``. Every mrcal lens model starts with ``fx, fy, cx, cy``."""
    try:
        _, intrinsics = model.intrinsics()
        width, height = (int(v) for v in model.imagersize())
        extrinsics = np.asarray(model.extrinsics_rt_fromref(), dtype=float)
    except Exception as e:  # noqa: BLE001 - mrcal raises plain exceptions
        return f"incomplete camera model ({e})"
    intrinsics = np.asarray(intrinsics, dtype=float)
    if intrinsics.size < 4 or not np.isfinite(intrinsics).all():
        return "the intrinsics are not all finite numbers"
    if not (intrinsics[0] > 0 and intrinsics[1] > 0):
        return f"focal lengths fx = {intrinsics[0]:g}, fy = {intrinsics[1]:g} px must be positive"
    if width < 1 or height < 1:
        return f"imager size {width}x{height} is empty"
    if not np.isfinite(extrinsics).all():
        return "the extrinsics are not all finite numbers"
    return None


__all__ = ["StageCalibration", "calibrate_stage", "calibrate_stage_from_capture", "detect_grid_corners",
           "load_model"]
