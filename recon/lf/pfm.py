"""Portable Float Map (PFM) read and write.

A PFM file is a three-line ASCII header (``Pf`` for one channel, ``PF`` for three; ``W H``; a scale
whose sign gives the byte order, negative = little-endian) followed by raw float32 rows stored
**bottom-up**. In memory lfrig keeps row 0 at the top (``docs/conventions.md``), so both functions
flip rows.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from recon.errors import LightFieldFormatError
from recon.lf.imageio import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE, read_head


def read_pfm(path: str | os.PathLike) -> np.ndarray:
    """Read a PFM file.

    Returns
    -------
    ``(H, W)`` or ``(H, W, 3)`` ``float32`` array, row 0 at the top, native byte order.

    Raises
    ------
    LightFieldFormatError
        When the file is missing or not a regular file, the header is not PFM, claims more pixels
        than a view may have (``recon.lf.imageio.MAX_IMAGE_PIXELS``), or the data is shorter than the
        header says. Only the header's bytes are read.
    """
    path = Path(path)
    data, size = read_head(path, 256)
    # The header is three whitespace-separated tokens lines; tolerate comments-free variants that put
    # width and height on separate lines by tokenising the first bytes.
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        if start == pos or pos - start > 32:
            raise LightFieldFormatError(f"{path}: not a PFM file (header is incomplete)")
        tokens.append(data[start:pos])
    pos += 1  # exactly one whitespace byte ends the header
    kind = tokens[0]
    if kind not in (b"Pf", b"PF"):
        raise LightFieldFormatError(f"{path}: not a PFM file (starts with {kind[:8]!r}, expected 'Pf' or 'PF')")
    try:
        width, height, scale = int(tokens[1]), int(tokens[2]), float(tokens[3])
    except ValueError:
        raise LightFieldFormatError(f"{path}: broken PFM header (size or scale is not a number)") from None
    if width <= 0 or height <= 0 or scale == 0 or not math.isfinite(scale):
        raise LightFieldFormatError(f"{path}: broken PFM header (size {width}x{height}, scale {scale})")
    channels = 3 if kind == b"PF" else 1
    count = width * height * channels
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
        raise LightFieldFormatError(f"{path}: PFM of {width}x{height} pixels is larger than lfrig reads "
                                    f"(at most {MAX_IMAGE_SIDE} a side and {MAX_IMAGE_PIXELS} pixels)")
    if size - pos < 4 * count:
        raise LightFieldFormatError(
            f"{path}: PFM data is truncated ({max(size - pos, 0)} bytes, header promises {4 * count})"
        )
    data, _ = read_head(path, pos + 4 * count)  # the header's bytes only, whatever follows them
    dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
    array = np.frombuffer(data, dtype=dtype, count=count, offset=pos).astype(np.float32)
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.ascontiguousarray(array.reshape(shape)[::-1])


def write_pfm(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write ``(H, W)`` or ``(H, W, 3)`` data as little-endian float32 PFM (row 0 at the top in memory).

    The file is written to a temporary name and renamed into place, so a reader never sees half a file.
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"write_pfm needs an (H, W) or (H, W, 3) array; got shape {image.shape}")
    kind = "PF" if image.ndim == 3 else "Pf"
    height, width = image.shape[:2]
    body = np.ascontiguousarray(image[::-1], dtype="<f4").tobytes()
    from recon.lf.imageio import write_bytes_atomic

    write_bytes_atomic(Path(path), f"{kind}\n{width} {height}\n-1.0\n".encode("ascii") + body)
