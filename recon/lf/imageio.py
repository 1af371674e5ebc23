"""Reading and writing view images (PNG, 8 or 16 bit), with errors that name the file."""

from __future__ import annotations

import hashlib
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from recon.errors import LightFieldFormatError


def read_image(path: Path) -> np.ndarray:
    """Read one image as ``(H, W)`` or ``(H, W, 3)`` RGB in its stored dtype (alpha is dropped)."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise LightFieldFormatError(f"{path}: no such file") from None
    except OSError as error:
        raise LightFieldFormatError(f"{path}: cannot read ({error.strerror})") from None
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
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
