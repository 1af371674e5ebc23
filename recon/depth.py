"""Depth scores, the benchmark's camera, and depth maps on disk.

The conversion itself, ``Z = focal_px * pitch_mm / (d + d0)``, is :mod:`recon.camera`'s
(:class:`recon.camera.Camera`, :func:`recon.camera.disparity_to_depth`).

The 4D Light Field Benchmark (Honauer et al., ACCV 2016) records its camera in ``parameters.cfg``;
its toolkit converts with::

    depth_m = 1 / (disp * 1000 * sensor_size_mm / (baseline_mm * focal_length_mm * max(W, H))
                   + 1 / focus_distance_m)

which is the formula above with ``focal_px = focal_length_mm * max(W, H) / sensor_size_mm``,
``pitch_mm = baseline_mm`` and ``d0 = focal_px * baseline_mm / (1000 * focus_distance_m)``
(:func:`benchmark_camera`, :func:`recon.lf.params.benchmark_focal_px`,
:func:`recon.lf.params.focus_disparity_px`). Depth here is always in millimetres.
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.camera import Camera
from recon.errors import ReconError
from recon.lf.params import benchmark_focal_px, focus_disparity_px, read_parameters


class DepthFormatError(ReconError):
    """A depth map or camera-parameter file is missing, malformed, or cannot be written."""


def depth_error_scores(
    depth_mm, truth_mm, *, mask=None, border_px: int = 0, tolerance: float = 0.005
) -> dict[str, float]:
    """Relative depth error of an estimate against the truth.

    Parameters
    ----------
    depth_mm, truth_mm
        ``(H, W)`` depth in mm; pixels where either is not finite and positive are skipped.
    mask
        Optional ``(H, W)`` bool: score only where ``True`` (e.g. textured pixels).
    border_px
        Pixels left out on every side (the benchmark leaves out 15).
    tolerance
        Relative error counted as good for ``within_pct``, default 0.5 % of the distance.

    Returns
    -------
    ``{"median_abs_rel_pct", "mean_abs_rel_pct", "p90_abs_rel_pct", "within_pct", "tolerance_pct",
    "pixels"}``: percentages of the true distance (``|Z - Z_true| / Z_true``), the share of pixels
    within ``tolerance`` in percent, and how many pixels were scored. NaN scores when none is left.
    """
    depth = np.asarray(depth_mm, dtype=np.float64)
    truth = np.asarray(truth_mm, dtype=np.float64)
    if depth.shape != truth.shape or depth.ndim != 2:
        raise ValueError(f"depth_mm {depth.shape} and truth_mm {truth.shape} must be (H, W) maps of one shape")
    keep = np.zeros(depth.shape, dtype=bool)
    height, width = depth.shape
    keep[border_px : height - border_px, border_px : width - border_px] = True
    with np.errstate(invalid="ignore"):
        keep &= np.isfinite(depth) & np.isfinite(truth) & (depth > 0) & (truth > 0)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    relative = np.abs(depth[keep] - truth[keep]) / truth[keep]
    scores = {"tolerance_pct": 100.0 * tolerance, "pixels": int(keep.sum())}
    if relative.size == 0:
        nan = float("nan")
        return {"median_abs_rel_pct": nan, "mean_abs_rel_pct": nan, "p90_abs_rel_pct": nan, "within_pct": nan, **scores}
    return {
        "median_abs_rel_pct": float(100.0 * np.median(relative)),
        "mean_abs_rel_pct": float(100.0 * np.mean(relative)),
        "p90_abs_rel_pct": float(100.0 * np.percentile(relative, 90)),
        "within_pct": float(100.0 * np.mean(relative <= tolerance)),
        **scores,
    }


# --------------------------------------------------------------------------------------------------
# the benchmark's camera
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BenchmarkCamera:
    """The camera of a 4D Light Field Benchmark scene as ``parameters.cfg`` records it.

    Attributes are in the file's own units; :meth:`camera` gives lfrig's :class:`recon.camera.Camera`.
    """

    focal_length_mm: float
    sensor_size_mm: float
    width_px: int
    height_px: int
    baseline_mm: float
    focus_distance_m: float

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (:func:`recon.lf.params.benchmark_focal_px`)."""
        return benchmark_focal_px(focal_length_mm=self.focal_length_mm, sensor_size_mm=self.sensor_size_mm,
                                  width_px=self.width_px, height_px=self.height_px)

    @property
    def pitch_mm(self) -> float:
        """Grid pitch in mm (the benchmark's ``baseline_mm``)."""
        return self.baseline_mm

    @property
    def disparity_offset(self) -> float:
        """``d0`` (:func:`recon.lf.params.focus_disparity_px`)."""
        return focus_disparity_px(focal_px=self.focal_px, pitch_mm=self.baseline_mm,
                                  focus_distance_m=self.focus_distance_m)

    def camera(self) -> Camera:
        """lfrig's camera for this scene (:class:`recon.camera.Camera`)."""
        return Camera(focal_px=self.focal_px, pitch_mm=self.pitch_mm, disparity_offset=self.disparity_offset)


def benchmark_camera(parameters) -> BenchmarkCamera:
    """Read the camera of a benchmark scene.

    Parameters
    ----------
    parameters
        Path of a ``parameters.cfg`` (or of the scene folder holding one), or a mapping of sections
        such as ``LightField.metadata["parameters"]`` (``{"intrinsics": {...}, "extrinsics": {...}}``).
    """
    if isinstance(parameters, (str, Path)):
        path = Path(parameters)
        if path.is_dir():
            path = path / "parameters.cfg"
        if not path.is_file():
            raise DepthFormatError(
                f"{path}: no parameters.cfg; benchmark depth needs the scene's parameters.cfg "
                "(focal_length_mm, sensor_size_mm, image resolution, baseline_mm, focus_distance_m). "
                "Copy it next to the views or pass focal_px/pitch_mm/disparity_offset yourself."
            )
        sections = read_parameters(path)
        where = str(path)
    else:
        sections = {str(k): dict(v) for k, v in dict(parameters).items() if isinstance(v, dict)}
        where = "parameters"

    def get(section: str, key: str) -> float:
        try:
            return float(sections[section][key])
        except KeyError:
            raise DepthFormatError(
                f"{where}: [{section}] {key} is missing; it is needed for the benchmark's "
                "disparity-to-depth conversion"
            ) from None
        except ValueError:
            raise DepthFormatError(
                f"{where}: [{section}] {key} = {sections[section][key]!r} is not a number"
            ) from None

    return BenchmarkCamera(
        focal_length_mm=get("intrinsics", "focal_length_mm"),
        sensor_size_mm=get("intrinsics", "sensor_size_mm"),
        width_px=int(get("intrinsics", "image_resolution_x_px")),
        height_px=int(get("intrinsics", "image_resolution_y_px")),
        baseline_mm=get("extrinsics", "baseline_mm"),
        focus_distance_m=get("extrinsics", "focus_distance_m"),
    )


def benchmark_disparity_to_depth(disparity_px, *, camera: BenchmarkCamera) -> np.ndarray:
    """The benchmark toolkit's conversion, written out as it states it, in mm.

    ``depth_mm = 1000 / (disparity_px * 1000 * sensor_size_mm / (baseline_mm * focal_length_mm *
    max(W, H)) + 1 / focus_distance_m)``. Agrees with :meth:`recon.camera.Camera.depth_mm` of
    ``camera.camera()`` (a test checks it); non-positive effective disparity gives ``NaN``.

    Parameters
    ----------
    disparity_px
        Array of any shape, pixels per view step.
    camera
        From :func:`benchmark_camera`.

    Returns
    -------
    depth_mm
        Same shape, ``float64``, mm.
    """
    disparity = np.asarray(disparity_px, dtype=np.float64)
    q = camera.baseline_mm * camera.focal_length_mm * max(camera.width_px, camera.height_px)
    inverse_depth_per_m = disparity * 1000.0 * camera.sensor_size_mm / q + 1.0 / camera.focus_distance_m
    with np.errstate(divide="ignore", invalid="ignore"):
        depth_mm = 1000.0 / inverse_depth_per_m
    return np.where(inverse_depth_per_m > 0, depth_mm, np.nan)


# --------------------------------------------------------------------------------------------------
# depth maps on disk
# --------------------------------------------------------------------------------------------------

#: The key of the PNG text chunk (and the sidecar JSON) that records a 16-bit depth PNG's scale.
PNG_SCALE_KEY = "lfrig-depth"


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _insert_text_chunk(png: bytes, key: str, text: str) -> bytes:
    # The IHDR chunk is always first: 8-byte signature + 4 length + 4 type + 13 data + 4 CRC.
    end_of_ihdr = 8 + 25
    chunk = _png_chunk(b"tEXt", key.encode("latin-1") + b"\0" + text.encode("latin-1"))
    return png[:end_of_ihdr] + chunk + png[end_of_ihdr:]


def _read_text_chunks(png: bytes) -> dict[str, str]:
    texts: dict[str, str] = {}
    position = 8
    while position + 8 <= len(png):
        (length,) = struct.unpack(">I", png[position : position + 4])
        kind = png[position + 4 : position + 8]
        data = png[position + 8 : position + 8 + length]
        if kind == b"tEXt" and b"\0" in data:
            key, _, value = data.partition(b"\0")
            texts[key.decode("latin-1")] = value.decode("latin-1")
        if kind == b"IEND":
            break
        position += 12 + length
    return texts


def png_sidecar_path(path) -> Path:
    """Where the scale of a 16-bit depth PNG is also written: ``depth.png`` -> ``depth.png.json``."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def encode_depth_png(depth_mm: np.ndarray, *, scale_mm: float | None = None, offset_mm: float | None = None):
    """Quantise depth to 16 bit: ``stored = 1 + round((depth_mm - offset_mm) / scale_mm)``, 0 = no value.

    Parameters
    ----------
    depth_mm
        ``(H, W)`` mm; ``NaN``/``inf``/non-positive pixels are stored as 0.
    scale_mm, offset_mm
        mm per count and the depth of count 1. By default the finite range is spread over
        1..65535 (``offset_mm`` = minimum depth, ``scale_mm = (max - min) / 65534``), so the
        quantisation error is at most ``scale_mm / 2``. Give ``scale_mm=0.1, offset_mm=0`` for a
        fixed 0.1 mm step.

    Returns
    -------
    (stored, metadata)
        ``(H, W)`` ``uint16`` and the dict written next to it (``unit``, ``scale_mm``,
        ``offset_mm``, ``invalid``, ``formula``).
    """
    depth = np.asarray(depth_mm, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth_mm must be (H, W); got shape {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    low = float(depth[valid].min()) if valid.any() else 0.0
    high = float(depth[valid].max()) if valid.any() else 0.0
    if offset_mm is None:
        offset_mm = low
    if scale_mm is None:
        scale_mm = (high - offset_mm) / 65534.0 if high > offset_mm else 1.0
    if not (np.isfinite(scale_mm) and scale_mm > 0):
        raise ValueError(f"scale_mm must be a positive number of mm per count; got {scale_mm!r}")
    counts = np.zeros(depth.shape, dtype=np.float64)
    counts[valid] = 1.0 + np.round((depth[valid] - offset_mm) / scale_mm)
    if valid.any() and (counts[valid].min() < 1 or counts[valid].max() > 65535):
        raise ValueError(
            f"depth {low:.6g}..{high:.6g} mm does not fit 16 bit with scale_mm={scale_mm} and "
            f"offset_mm={offset_mm}; pass a larger scale_mm or leave it to be chosen"
        )
    metadata = {
        "unit": "mm",
        "scale_mm": float(scale_mm),
        "offset_mm": float(offset_mm),
        "invalid": 0,
        "formula": "depth_mm = offset_mm + (stored - 1) * scale_mm; stored == 0 means no depth",
    }
    return counts.astype(np.uint16), metadata


def decode_depth_png(stored: np.ndarray, metadata: dict) -> np.ndarray:
    """Inverse of :func:`encode_depth_png`: ``(H, W)`` ``uint16`` -> ``(H, W)`` ``float64`` mm, ``NaN`` for 0."""
    counts = np.asarray(stored).astype(np.float64)
    depth = float(metadata["offset_mm"]) + (counts - 1.0) * float(metadata["scale_mm"])
    return np.where(counts == 0, np.nan, depth)


def write_depth(path, depth_mm: np.ndarray, *, scale_mm: float | None = None, offset_mm: float | None = None) -> Path:
    """Write an ``(H, W)`` depth map in mm; the format follows the suffix.

    - ``.pfm``: ``float32``, ``NaN`` where there is no depth (``recon.lf.pfm``; rows top-down in memory).
    - ``.npy``: ``float32`` as given (``NaN`` kept).
    - ``.png``: 16-bit grey, quantised by :func:`encode_depth_png`; the scale is stored in a PNG
      ``tEXt`` chunk under :data:`PNG_SCALE_KEY` and in the sidecar ``<name>.png.json``.

    Returns the path written.
    """
    path = Path(path)
    depth = np.asarray(depth_mm)
    if depth.ndim != 2:
        raise ValueError(f"depth_mm must be (H, W); got shape {depth.shape}")
    if not path.parent.is_dir():
        raise DepthFormatError(f"{path}: folder {path.parent} does not exist; create it first")
    suffix = path.suffix.lower()
    from recon.errors import FileWriteError
    from recon.lf.imageio import write_bytes_atomic

    try:
        if suffix == ".pfm":
            from recon.lf.pfm import write_pfm

            write_pfm(path, depth.astype(np.float32))
        elif suffix == ".npy":
            buffer = io.BytesIO()
            np.save(buffer, depth.astype(np.float32))
            write_bytes_atomic(path, buffer.getvalue())
        elif suffix == ".png":
            import cv2

            stored, metadata = encode_depth_png(depth, scale_mm=scale_mm, offset_mm=offset_mm)
            ok, encoded = cv2.imencode(".png", stored)
            if not ok:
                raise DepthFormatError(f"{path}: OpenCV could not encode the depth PNG")
            text = json.dumps(metadata, sort_keys=True)
            # The PNG carries its own scale; the sidecar is a copy for tools that cannot read tEXt.
            # PNG first: a write that fails there (a full disk) leaves nothing new at all, and a crash
            # between the two leaves the new PNG with the old sidecar, which the reader ignores when
            # the PNG has its chunk (lfrig's always has).
            write_bytes_atomic(path, _insert_text_chunk(encoded.tobytes(), PNG_SCALE_KEY, text))
            write_bytes_atomic(png_sidecar_path(path), (json.dumps(metadata, indent=2, sort_keys=True) + "\n").encode())
        else:
            raise DepthFormatError(f"{path}: unknown depth-map suffix {path.suffix!r}; use .pfm, .png or .npy")
    except FileWriteError as error:
        raise DepthFormatError(str(error)) from None
    return path


def read_depth(path) -> np.ndarray:
    """Read a depth map written by :func:`write_depth`: ``(H, W)`` float mm, ``NaN`` where none.

    For ``.png`` the scale comes from the PNG text chunk, else from the sidecar JSON.
    """
    path = Path(path)
    if not path.is_file():
        raise DepthFormatError(f"{path}: no such depth map")
    suffix = path.suffix.lower()
    if suffix == ".pfm":
        from recon.lf.pfm import read_pfm

        return read_pfm(path)
    if suffix == ".npy":
        from recon.lf.imageio import read_npy

        depth = read_npy(path, error=DepthFormatError)
        if not (isinstance(depth, np.ndarray) and depth.ndim == 2 and depth.dtype.kind in "fiu"):
            raise DepthFormatError(f"{path}: a depth map is a 2-D array of numbers; this one is "
                                   f"{getattr(depth, 'shape', '?')} {getattr(depth, 'dtype', type(depth).__name__)}")
        return depth
    if suffix == ".png":
        from recon.lf.imageio import MAX_IMAGE_BYTES, checked_png_header, decode_quietly, read_bytes
        from recon.lf.params import is_finite

        data = read_bytes(path, error=DepthFormatError, max_bytes=MAX_IMAGE_BYTES)
        checked_png_header(path, data, error=DepthFormatError)
        texts = _read_text_chunks(data)
        try:
            if PNG_SCALE_KEY in texts:
                metadata = json.loads(texts[PNG_SCALE_KEY])
            elif png_sidecar_path(path).is_file():
                metadata = json.loads(read_bytes(png_sidecar_path(path), error=DepthFormatError).decode("utf-8"))
            else:
                metadata = None
        except (ValueError, UnicodeDecodeError) as error:
            raise DepthFormatError(f"{path}: the depth scale is not valid JSON ({error})") from None
        if metadata is not None and not (
                isinstance(metadata, dict) and all(
                    isinstance(metadata.get(k), (int, float)) and not isinstance(metadata.get(k), bool)
                    and is_finite(metadata[k]) for k in ("offset_mm", "scale_mm"))
                and metadata["scale_mm"] > 0):
            raise DepthFormatError(f"{path}: the depth scale must give finite offset_mm and positive scale_mm; "
                                   f"got {metadata!r}"[:300])
        if metadata is None:
            raise DepthFormatError(
                f"{path}: a 16-bit depth PNG needs its scale, but there is no '{PNG_SCALE_KEY}' text "
                f"chunk and no {png_sidecar_path(path).name}; write it with lfrig or supply the sidecar"
            )
        stored = decode_quietly(np.frombuffer(data, dtype=np.uint8))
        if stored is None or stored.dtype != np.uint16 or stored.ndim != 2:
            raise DepthFormatError(f"{path}: not a single-channel 16-bit PNG")
        return decode_depth_png(stored, metadata)
    raise DepthFormatError(f"{path}: unknown depth-map suffix {path.suffix!r}; use .pfm, .png or .npy")
