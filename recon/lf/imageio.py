"""Reading and writing view images (PNG, 8 or 16 bit), with errors that name the file."""

from __future__ import annotations

import errno
import hashlib
import os
import re
import signal
import threading
import zlib
from contextlib import contextmanager
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from recon.errors import FileWriteError, LightFieldFormatError


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


def decode_quietly(data: np.ndarray) -> np.ndarray | None:
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


def read_bytes(path: str | os.PathLike, *, error: type[LightFieldFormatError] = LightFieldFormatError,
               missing: str = "no such file") -> bytes:
    """The whole file, or ``error`` naming ``path``: ``"{path}: {missing}"`` when it does not exist,
    ``"{path}: cannot read (reason)"`` when the system refuses."""
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise error(f"{path}: {missing}") from None
    except OSError as err:
        raise error(f"{path}: cannot read ({err.strerror})") from None


def read_image(path: Path) -> np.ndarray:
    """Read one image as ``(H, W)`` or ``(H, W, 3)`` RGB in its stored dtype (alpha is dropped).

    Raises
    ------
    LightFieldFormatError
        Naming the file: missing, unreadable, a damaged PNG (checked by :func:`png_problem` before
        decoding), or not an image OpenCV can decode.
    """
    data = np.frombuffer(read_bytes(path), dtype=np.uint8)
    if data[:8].tobytes() == PNG_SIGNATURE:
        problem = png_problem(data.tobytes())
        if problem:
            raise LightFieldFormatError(f"{path}: {problem}; replace or re-capture it")
    image = decode_quietly(data) if data.size else None
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


#: Environment variables of the fault-injection hook used by the fault tests (``tests/test_faults.py``):
#: ``LFRIG_FAULT=kill:N`` sends SIGKILL to this process in the middle of its N-th file write (the
#: temporary file half written), ``LFRIG_FAULT=enospc:N`` makes the N-th write fail as a full disk
#: would (``OSError(ENOSPC)`` after half the bytes). ``LFRIG_FAULT_LOG=FILE`` appends one line per
#: write (``N<TAB>path``) so a test can count the writes of a command. Unset, they cost one lookup.
FAULT_ENV = "LFRIG_FAULT"
FAULT_LOG_ENV = "LFRIG_FAULT_LOG"
_writes = 0


def fault_point(path: Path) -> None:
    """Count one write of ``path`` and, when the fault hook asks for it, fail it here."""
    global _writes
    fault = os.environ.get(FAULT_ENV)
    log = os.environ.get(FAULT_LOG_ENV)
    if not fault and not log:
        return
    _writes += 1
    if log:
        with open(log, "a", encoding="utf-8") as f:
            f.write(f"{_writes}\t{path}\n")
    if fault:
        mode, _, number = fault.partition(":")
        if number.isdigit() and int(number) == _writes:
            if mode == "kill":
                os.kill(os.getpid(), signal.SIGKILL)
            if mode == "enospc":
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def write_error(path: Path, error: OSError) -> FileWriteError:
    """The user-facing error for a failed write of ``path``."""
    reason = error.strerror or str(error)
    hint = "free some space" if error.errno in (errno.ENOSPC, errno.EDQUOT) else "check the folder"
    return FileWriteError(f"{path}: cannot write ({reason}); {hint} and run the command again")


def _sync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def temporary_name(path: Path) -> Path:
    """The temporary file beside ``path`` that an atomic write of ``path`` goes through.

    Hidden (a leading dot) and named with the process id, so two processes writing the same file
    never share it and readers that list a folder skip it; it keeps the suffix, because some writers
    (open3d, OpenCV) choose the format by it: ``.model.1234.tmp.ply`` for ``model.ply``.
    """
    return path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")


def write_bytes_atomic(path: Path, data: bytes) -> str:
    """Write ``data`` to ``path`` so that a reader sees either the old file or the whole new one.

    The bytes go to a temporary file in the same folder (:func:`temporary_name`), are flushed to
    disk, and the file is renamed into place; the folder is synced so the rename survives a power
    cut. Returns the SHA-256 hex digest.

    Raises
    ------
    FileWriteError
        When the file cannot be written (a full disk, no permission); the temporary file is removed
        and ``path`` keeps its previous content.
    """
    path = Path(path)
    tmp = temporary_name(path)
    try:
        with open(tmp, "wb") as f:
            half = len(data) // 2
            f.write(data[:half])
            f.flush()
            fault_point(path)
            f.write(data[half:])
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _sync_folder(path.parent)
    except OSError as error:
        tmp.unlink(missing_ok=True)
        raise write_error(path, error) from None
    return hashlib.sha256(data).hexdigest()


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Remove the temporary files that interrupted atomic writes left in ``folder`` (not below it).

    Call it only while holding the folder's lock (:mod:`recon.lf.lock`): then no other lfrig process
    is writing there, and every temporary is a leftover of one that died. Returns what was removed.
    """
    removed = []
    for file in Path(folder).glob(".*.tmp*"):
        if re.fullmatch(r"\..+\.\d+\.tmp(\.[^.]*)?", file.name) and file.is_file():
            try:
                file.unlink()
            except OSError:
                continue
            removed.append(file)
    return removed


@contextmanager
def atomic_output(path: Path, *, what: str = "file") -> Iterator[Path]:
    """For writers that want a file name (open3d, mrcal, numpy): yield a temporary name beside
    ``path``; when the block ends without an error, sync that file and rename it over ``path``.

    The temporary file must exist and be non-empty when the block ends, else nothing is renamed and
    a :class:`FileWriteError` names ``path``. On any error the temporary file is removed and
    ``path`` keeps its previous content.
    """
    path = Path(path)
    tmp = temporary_name(path)
    try:
        yield tmp
        size = tmp.stat().st_size if tmp.exists() else 0
        if size == 0:
            raise FileWriteError(f"{path}: the {what} was not written (nothing on disk); check the folder and free space")
        fault_point(path)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _sync_folder(path.parent)
    except OSError as error:
        tmp.unlink(missing_ok=True)
        raise write_error(path, error) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_png(path: Path, image: np.ndarray) -> str:
    """Write an image as PNG atomically; returns the file's SHA-256."""
    return write_bytes_atomic(path, encode_png(image))
