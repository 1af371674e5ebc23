"""Reading and writing view images (PNG, 8 or 16 bit), with errors that name the file."""

from __future__ import annotations

import hashlib
import os
import threading
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from recon.errors import LightFieldFormatError


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_problem(data: bytes) -> str | None:
    """What is structurally wrong with PNG bytes (truncated, a chunk's CRC, no IHDR/IEND), or ``None``.

    Checked before decoding, so that a damaged file is reported by lfrig in one line and not first by
    libpng on stderr (libpng prints its own errors, which OpenCV does not catch). Cheap: one CRC-32
    pass over the bytes, no decompression.
    """
    if not data.startswith(PNG_SIGNATURE):
        return "not a PNG (no PNG signature)"
    pos, first, view = len(PNG_SIGNATURE), True, memoryview(data)
    while True:
        if pos + 12 > len(data):
            return f"truncated at byte {pos} of {len(data)} (no IEND chunk)"
        length = int.from_bytes(view[pos:pos + 4], "big")
        kind = bytes(view[pos + 4:pos + 8])
        end = pos + 12 + length
        if length > 0x7FFFFFFF or end > len(data):
            return f"truncated in the {kind.decode('latin-1')!r} chunk at byte {pos}"
        crc = int.from_bytes(view[end - 4:end], "big")
        if zlib.crc32(view[pos + 4:end - 4]) != crc:
            return f"damaged {kind.decode('latin-1')!r} chunk at byte {pos} (CRC mismatch)"
        if first and kind != b"IHDR":
            return "damaged (the first chunk is not IHDR)"
        first = False
        if kind == b"IEND":
            return None
        pos = end


def _decode_quietly(data: np.ndarray) -> np.ndarray | None:
    """``cv2.imdecode`` with OpenCV's own log silenced: a failure is reported by the caller."""
    with _QUIET_LOCK:
        global _quiet_depth
        if _quiet_depth == 0:
            _quiet_saved[0] = cv2.utils.logging.getLogLevel()
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        _quiet_depth += 1
    try:
        return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return None
    finally:
        with _QUIET_LOCK:
            _quiet_depth -= 1
            if _quiet_depth == 0:
                cv2.utils.logging.setLogLevel(_quiet_saved[0])


_QUIET_LOCK = threading.Lock()
_quiet_depth = 0
_quiet_saved = [0]


def read_image(path: Path) -> np.ndarray:
    """Read one image as ``(H, W)`` or ``(H, W, 3)`` RGB in its stored dtype (alpha is dropped).

    Raises
    ------
    LightFieldFormatError
        Naming the file: missing, unreadable, a damaged PNG (checked by :func:`png_problem` before
        decoding), or not an image OpenCV can decode.
    """
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise LightFieldFormatError(f"{path}: no such file") from None
    except OSError as error:
        raise LightFieldFormatError(f"{path}: cannot read ({error.strerror})") from None
    if data[:8].tobytes() == PNG_SIGNATURE:
        problem = png_problem(data.tobytes())
        if problem:
            raise LightFieldFormatError(f"{path}: {problem}; replace or re-capture it")
    image = _decode_quietly(data) if data.size else None
    if image is None:
        raise LightFieldFormatError(f"{path}: not a readable image (corrupt or not a PNG); replace or re-capture it")
    if image.ndim == 3:
        if image.shape[2] == 4:
            image = image[:, :, :3]
        image = image[:, :, ::-1]  # OpenCV decodes to BGR
    return np.ascontiguousarray(image)


def read_images(paths: Sequence[Path]) -> np.ndarray:
    """Read equally sized images into one ``(N, H, W[, 3])`` array; PNG decoding runs in threads.

    Raises
    ------
    LightFieldFormatError
        Naming the first unreadable file, or the first file whose size, colour or bit depth differs
        from the first image's.
    """
    if not paths:
        raise ValueError("read_images needs at least one path")
    first = read_image(paths[0])
    out = np.empty((len(paths),) + first.shape, dtype=first.dtype)
    out[0] = first

    def load(i: int) -> None:
        image = read_image(paths[i])
        if image.shape != first.shape or image.dtype != first.dtype:
            raise LightFieldFormatError(
                f"{paths[i]}: image is {_describe(image)} but {paths[0].name} is {_describe(first)}; "
                "all views must have the same size, colour and bit depth"
            )
        out[i] = image

    with ThreadPoolExecutor(max_workers=min(8, (os.cpu_count() or 1) * 2)) as pool:
        for _ in pool.map(load, range(1, len(paths))):
            pass
    return out


def _describe(image: np.ndarray) -> str:
    h, w = image.shape[:2]
    colour = "RGB" if image.ndim == 3 else "grey"
    return f"{w}x{h} {colour} {image.dtype.itemsize * 8}-bit"


def encode_png(image: np.ndarray) -> bytes:
    """Encode an RGB or grey ``uint8``/``uint16`` image as PNG bytes."""
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"PNG views must be uint8 or uint16; got {image.dtype}")
    bgr = image[:, :, ::-1] if image.ndim == 3 else image
    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(bgr), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError("OpenCV could not encode the image as PNG")
    return buffer.tobytes()


def write_bytes_atomic(path: Path, data: bytes) -> str:
    """Write ``data`` to ``path`` so that a reader sees either the old file or the whole new one.

    The bytes go to a temporary file in the same folder (named with the process id, so two processes
    writing the same file never share it), are flushed to disk, and the file is renamed into place;
    the folder is synced so the rename survives a power cut. Returns the SHA-256 hex digest.
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    return hashlib.sha256(data).hexdigest()


def write_png(path: Path, image: np.ndarray) -> str:
    """Write an image as PNG atomically; returns the file's SHA-256."""
    return write_bytes_atomic(path, encode_png(image))
