"""Reading and writing view images (PNG, 8 or 16 bit), with errors that name the file."""

from __future__ import annotations

import errno
import hashlib
import io
import logging
import math
import os
import re
import signal
import stat
import threading
import warnings
import zlib
from contextlib import contextmanager
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Iterator, NamedTuple, Sequence

import cv2
import imagecodecs
import numpy as np

from recon.errors import FileWriteError, LfrigError, LightFieldFormatError


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

# libpng's warnings through imagecodecs (a benign chunk problem, an interlaced PNG read whole) are
# not the user's to read: the pixels are the same, and a damaged view is reported by lfrig itself.
logging.getLogger("imagecodecs").setLevel(logging.ERROR)


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


#: The largest view a light field may have: sides up to this many pixels ...
MAX_IMAGE_SIDE = 32768
#: ... and at most this many pixels (64 Mpx, beyond any camera on a lab stage). A PNG's size is read
#: from its header before it is decoded, so a small file that claims 20000x20000 pixels is refused
#: instead of being given 30 GiB.
MAX_IMAGE_PIXELS = 1 << 26
#: The largest image file read (a 64 Mpx 16-bit RGB PNG stored uncompressed is 400 MB).
MAX_IMAGE_BYTES = 1 << 30
#: The largest small file read whole: a journal, parameters.cfg, result.json, a sidecar.
MAX_TEXT_BYTES = 256 << 20


def _size_text(size: int) -> str:
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if size >= 1 << shift:
            return f"{size / (1 << shift):.1f} {unit}"
    return f"{size} bytes"


def read_bytes(path: str | os.PathLike, *, error: type[LfrigError] = LightFieldFormatError,
               missing: str = "no such file", max_bytes: int = MAX_TEXT_BYTES) -> bytes:
    """The whole file, or ``error`` naming ``path``: ``"{path}: {missing}"`` when it does not exist,
    ``"{path}: cannot read (reason)"`` when the system refuses, and a size error when the file is not
    a regular file or holds more than ``max_bytes`` (checked before anything is read, so an 8 GiB
    sparse file or ``/dev/zero`` is refused at once)."""
    return read_head(path, max_bytes, error=error, missing=missing, whole=True)[0]


def read_head(path: str | os.PathLike, count: int, *, error: type[LfrigError] = LightFieldFormatError,
              missing: str = "no such file", whole: bool = False) -> tuple[bytes, int]:
    """The first ``count`` bytes of a regular file and its size, with :func:`read_bytes`' errors; with
    ``whole``, a file longer than ``count`` bytes is an error instead."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NOCTTY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise error(f"{path}: {missing}") from None
    except OSError as err:
        raise error(f"{path}: cannot read ({err.strerror})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise error(f"{path}: not a regular file; give the file itself")
        if whole and info.st_size > count:
            raise error(f"{path}: {_size_text(info.st_size)}, more than the {_size_text(count)} such a file "
                        "may hold; check that it is the right file")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(count + 1 if whole else count)
        if whole and len(data) > count:  # grew while being read
            raise error(f"{path}: more than the {_size_text(count)} such a file may hold")
        return data, info.st_size
    except OSError as err:
        raise error(f"{path}: cannot read ({err.strerror})") from None
    finally:
        os.close(fd)


def read_npy(path: str | os.PathLike, *, error: type[LfrigError] = LightFieldFormatError) -> np.ndarray:
    """A ``.npy`` array of numbers or booleans (no pickles), its header checked before the data is read:
    at most :data:`MAX_IMAGE_PIXELS` times 4 elements, and the file as long as the header says.

    Raises ``error`` naming ``path`` for anything else (damaged, truncated, too large, an object array).
    """
    head, size = read_head(path, 4096, error=error)
    stream = io.BytesIO(head)
    try:
        with warnings.catch_warnings():  # a damaged header's SyntaxWarning is not the user's to read
            warnings.simplefilter("ignore")
            version = np.lib.format.read_magic(stream)
            read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
            if version not in read_header:
                raise ValueError(f"format version {version}")
            shape, fortran, dtype = read_header[version](stream, max_header_size=4000)
    except Exception as err:  # noqa: BLE001 - numpy's header parser raises many kinds on a damaged file
        raise error(f"{path}: not a readable .npy file ({type(err).__name__}: {str(err)[:100]})") from None
    if dtype.hasobject or dtype.kind not in "biuf" or dtype.fields is not None:
        raise error(f"{path}: holds {dtype} values; lfrig's .npy files hold numbers")
    count = math.prod(shape)
    if count > 4 * MAX_IMAGE_PIXELS:
        raise error(f"{path}: an array of shape {shape} is larger than lfrig reads")
    need = stream.tell() + count * dtype.itemsize
    if size < need:
        raise error(f"{path}: truncated ({size} bytes, its header promises {need})")
    data, _ = read_head(path, need, error=error)
    array = np.frombuffer(data, dtype=dtype, count=count, offset=need - count * dtype.itemsize)
    return np.array(array.reshape(shape, order="F" if fortran else "C"), dtype=dtype.newbyteorder("="))


def sha256_file(path: str | os.PathLike, *, max_bytes: int = MAX_IMAGE_BYTES,
                error: type[LfrigError] = LightFieldFormatError) -> str:
    """SHA-256 hex digest of a regular file of at most ``max_bytes`` (:func:`read_bytes`' checks)."""
    return hashlib.sha256(read_bytes(path, error=error, max_bytes=max_bytes)).hexdigest()


def png_header(data: bytes) -> tuple[int, int, int, int] | None:
    """``(width, height, bit_depth, colour_type)`` from a PNG's IHDR chunk, or ``None`` when the bytes
    do not start with one."""
    if not data.startswith(PNG_SIGNATURE) or len(data) < 33 or data[8:16] != b"\0\0\0\x0dIHDR":
        return None
    return (int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big"), data[24], data[25])


def checked_png_header(path: str | os.PathLike, data: bytes, *, error: type[LfrigError] = LightFieldFormatError,
                       advice: str = "") -> tuple[int, int, int, int]:
    """:func:`png_header` of a PNG's bytes once they pass :func:`png_problem` and
    :func:`check_image_size`; ``error`` (naming ``path``, ending in ``advice``) otherwise."""
    problem = png_problem(data)
    if problem:
        raise error(f"{path}: {problem}{advice}")
    header = png_header(data)
    if header is None:
        raise error(f"{path}: damaged PNG header (IHDR){advice}")
    check_image_size(path, header[0], header[1])
    return header


def check_image_size(path: str | os.PathLike, width: int, height: int) -> None:
    """Refuse an image larger than :data:`MAX_IMAGE_SIDE` / :data:`MAX_IMAGE_PIXELS` (before decoding)."""
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
        raise LightFieldFormatError(
            f"{path}: image of {width}x{height} pixels is larger than lfrig reads (at most {MAX_IMAGE_SIDE} "
            f"pixels a side and {MAX_IMAGE_PIXELS // (1 << 20)} Mpx); check the file or scale it down"
        )


class PngKind(NamedTuple):
    """What decides a PNG's decoded shape and dtype: its IHDR fields and whether it has a tRNS chunk
    (a transparent colour or palette alpha) before its image data."""
    width: int
    height: int
    bit_depth: int
    colour_type: int
    transparency: bool


def png_kind(data: bytes, header: tuple[int, int, int, int]) -> PngKind:
    """The :class:`PngKind` of PNG bytes that passed :func:`checked_png_header` (``header``)."""
    pos, transparency = len(PNG_SIGNATURE), False
    while pos + 8 <= len(data) and data[pos + 4:pos + 8] != b"IDAT":  # libpng reads tRNS before IDAT only
        transparency = transparency or data[pos + 4:pos + 8] == b"tRNS"
        pos += 12 + int.from_bytes(data[pos:pos + 4], "big")
    return PngKind(*header, transparency)


def _libpng_shape(kind: PngKind) -> tuple[int, ...] | None:
    """The shape imagecodecs' libpng decoding gives a PNG of ``kind`` where its pixels are OpenCV's
    (``IMREAD_UNCHANGED``) in RGB(A) order, else ``None``: for grey with alpha (OpenCV gives BGRA
    of the grey) and grey with a tRNS chunk (OpenCV drops it, imagecodecs makes it alpha).

    Every other kind matches OpenCV's pixels exactly (both are libpng with the same transformations:
    1-, 2- and 4-bit grey expanded to 8 bits, palettes to RGB, tRNS to alpha, 16 bits in native byte
    order, interlacing undone, gAMA, sBIT and an EXIF orientation ignored; ``tests/test_png_decoding.py``)."""
    grey = kind.colour_type == 0
    if kind.colour_type == 4 or (grey and kind.transparency):
        return None
    channels = 1 if grey else 4 if kind.colour_type == 6 or kind.transparency else 3
    return (kind.height, kind.width) + (() if channels == 1 else (channels,))


def read_image(path: Path) -> np.ndarray:
    """Read one image as ``(H, W)`` or ``(H, W, 3)`` RGB in its stored dtype (alpha is dropped).

    Raises
    ------
    LightFieldFormatError
        Naming the file: missing, unreadable, larger than :data:`MAX_IMAGE_BYTES`, a damaged PNG
        (checked by :func:`png_problem` before decoding) or one whose header claims more pixels than
        :func:`check_image_size` allows, or whose image data does not decode; or not an image OpenCV
        can decode (it decodes other formats, and refuses them above :data:`MAX_IMAGE_PIXELS`:
        ``OPENCV_IO_MAX_IMAGE_PIXELS``).
    """
    return np.ascontiguousarray(_decode_bytes(path, *_read_checked(path)))


def _read_checked(path: Path, digests: dict[Path, str] | None = None,
                  check: Callable[[Path, str], None] | None = None) -> tuple[bytes, PngKind | None]:
    """The bytes of one image file after every check of :func:`read_image` but the decoding, and its
    :class:`PngKind` (``None`` for a file that is not a PNG); with ``digests``, the
    SHA-256 of the bytes as read goes into ``digests[path]``; with ``check``, ``check(path,
    sha256_hex)`` is called first (it raises for a file that must not be used)."""
    raw = read_bytes(path, max_bytes=MAX_IMAGE_BYTES)
    if digests is not None or check is not None:
        digest = hashlib.sha256(raw).hexdigest()
        if digests is not None:
            digests[path] = digest
        if check is not None:
            check(path, digest)
    if not raw.startswith(PNG_SIGNATURE):
        return raw, None
    return raw, png_kind(raw, checked_png_header(path, raw, advice="; replace or re-capture it"))


def _decode_bytes(path: Path, raw: bytes, kind: PngKind | None, out: np.ndarray | None = None) -> np.ndarray:
    """The checked bytes of ``path`` (:func:`_read_checked`) decoded as grey or RGB in their stored
    dtype, alpha dropped (a view of the decoded array). A PNG of a kind that has a
    :func:`_libpng_shape` is decoded by imagecodecs, with the GIL released, into ``out`` when given
    (an array of that shape and the stored dtype); any other image by OpenCV."""
    if kind is not None and _libpng_shape(kind) is not None:
        try:
            image = imagecodecs.png_decode(raw, out=out)
        except (imagecodecs.PngError, ValueError):  # damaged image data (the chunks were checked)
            image = None
        rgb = image[:, :, :3] if image is not None and image.ndim == 3 else image
    else:
        image = decode_quietly(np.frombuffer(raw, dtype=np.uint8)) if raw else None
        if image is None or image.ndim == 2:
            rgb = image
        else:  # OpenCV decodes to BGR(A)
            rgb = image[:, :, 2::-1] if image.shape[2] in (3, 4) else image[:, :, ::-1]
    if rgb is None:
        raise LightFieldFormatError(f"{path}: not a readable image (corrupt or not a PNG); replace or re-capture it")
    return rgb


#: Rows of a view :func:`read_images` converts to grey at once: its float32 temporaries (the
#: strip in RGB and in grey, ~0.6 MB for 1198 px) stay small, as many threads convert at once;
#: temporaries of whole views (17 MiB at 1198x906) stayed resident after the reading, ~110 MiB
#: of C heap over the decoding threads.
GREY_STRIP_ROWS = 32


def read_images(paths: Sequence[Path], *, digests: dict[Path, str] | None = None,
                check: Callable[[Path, str], None] | None = None, grey: bool = False,
                keep: dict[int, np.ndarray | None] | None = None, decode: bool = True) -> np.ndarray:
    """Read equally sized images into one ``(N, H, W[, 3])`` array in their stored dtype, or with
    ``grey`` into one ``(N, H, W)`` ``float32`` array of their luminance in ``[0, 1]``
    (:func:`recon.lf.lightfield.to_gray` of the stored images, bit for bit: each image is converted
    by :func:`recon.lf.lightfield.gray_image` in the thread that decodes it, so the stored images
    are never held all at once). PNG decoding runs in threads.

    ``digests``: a dict that receives ``path -> SHA-256`` (hex) of each file's bytes as they were
    read, so that a record of the input needs no second pass over the files. ``check``: called as
    ``check(path, sha256_hex)`` for each file's bytes as read, before they are decoded (a journal's
    checksums are verified this way, in the same pass); what it raises ends the reading. ``keep``:
    a dict whose keys are indices into ``paths``; each one's value is set to that image as stored,
    ``(H, W[, 3])`` (with ``grey``: the centre view's colours for the result folder).

    ``decode=False``: for a caller that needs only the shape and dtype (``lfrig info``). Every
    image's bytes are read and checked as for decoding (``digests``, ``check``, the PNG's chunks
    and header), but only the first image is decoded, and any other whose :class:`PngKind` (size,
    bit depth, colour type, a tRNS chunk) differs from the first's. The array returned then holds
    no pixels: every element is 0, read-only, in no memory (``np.broadcast_to``).

    Raises
    ------
    LightFieldFormatError
        Naming the first unreadable file, or the first file whose size, colour or bit depth differs
        from the first image's.
    """
    from recon.lf.lightfield import gray_image

    if not paths:
        raise ValueError("read_images needs at least one path")
    raw, first_kind = _read_checked(paths[0], digests, check)
    decoded = _decode_bytes(paths[0], raw, first_kind)
    shape, dtype = decoded.shape, decoded.dtype
    out_shape, out_dtype = ((len(paths),) + shape[:2], np.dtype(np.float32)) if grey else ((len(paths),) + shape, dtype)
    if not decode:
        out = np.broadcast_to(np.zeros((), out_dtype), out_shape)
    else:
        check_total_size(paths[0].parent, math.prod(out_shape) * out_dtype.itemsize)
        out = np.empty(out_shape, dtype=out_dtype)
    # a PNG of the first one's kind decodes straight into its place where libpng gives the stored shape
    in_place = not grey and first_kind is not None and _libpng_shape(first_kind) == shape

    def place(i: int, image: np.ndarray) -> None:
        if grey:  # by strips of rows (OpenCV converts row by row): no temporary of a whole float view
            for y in range(0, shape[0], GREY_STRIP_ROWS):
                gray_image(image[y:y + GREY_STRIP_ROWS], out=out[i, y:y + GREY_STRIP_ROWS])
        else:
            out[i] = image
        if keep is not None and i in keep:
            keep[i] = np.ascontiguousarray(image) if grey else out[i]

    def load(i: int) -> None:
        raw, kind = _read_checked(paths[i], digests, check)
        if kind is not None and kind == first_kind:
            if not decode:
                return  # decoded, it would be of the first image's size, colour and bit depth
            if in_place:
                _decode_bytes(paths[i], raw, kind, out=out[i])
                return
        image = _decode_bytes(paths[i], raw, kind)
        if image.shape != shape or image.dtype != dtype:
            raise LightFieldFormatError(
                f"{paths[i]}: image is {_describe(image.shape, image.dtype)} but {paths[0].name} is "
                f"{_describe(shape, dtype)}; all views must have the same size, colour and bit depth"
            )
        if decode:
            place(i, image)

    if decode:
        place(0, decoded)
    with ThreadPoolExecutor(max_workers=min(8, (os.cpu_count() or 1) * 2)) as pool:
        for _ in pool.map(load, range(1, len(paths))):
            pass
    return out


def read_view_grid(paths: Sequence[Path], grid: tuple[int, int], *, grey: bool = False,
                   digests: dict[Path, str] | None = None, check: Callable[[Path, str], None] | None = None,
                   decode: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """The views of a ``(rows, cols)`` grid from ``paths`` (row-major) by :func:`read_images`:
    ``(views, stored_centre)``, ``views`` ``(rows, cols, H, W[, 3])`` as stored, or with ``grey``
    ``(rows, cols, H, W)`` ``float32`` luminance and ``stored_centre`` the centre view as stored
    (``None`` without ``grey``: it is a view of ``views``; and with ``decode=False``, where ``views``
    holds no pixels)."""
    rows, cols = grid
    centre = (rows // 2) * cols + cols // 2
    keep: dict[int, np.ndarray | None] = {centre: None}
    images = read_images(paths, digests=digests, check=check, grey=grey, keep=keep if grey else None, decode=decode)
    return images.reshape((rows, cols) + images.shape[1:]), keep[centre]


def memory_bytes() -> int:
    """The machine's physical memory in bytes (0 when the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        return 0


def check_total_size(where: str | os.PathLike, nbytes: int) -> None:
    """Refuse a light field whose views alone would fill more than half this machine's memory (the
    estimate needs several times as much again)."""
    memory = memory_bytes()
    if memory and nbytes > memory // 2:
        raise LightFieldFormatError(
            f"{where}: the views need {_size_text(nbytes)} of memory, more than half of this machine's "
            f"{_size_text(memory)}; crop or bin the views, or use a larger machine"
        )


def _describe(shape: tuple[int, ...], dtype: np.dtype) -> str:
    h, w = shape[:2]
    colour = "RGB" if len(shape) == 3 else "grey"
    return f"{w}x{h} {colour} {dtype.itemsize * 8}-bit"


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
_WRITES_LOCK = threading.Lock()  # writers in several threads (a result folder's maps) count one by one


def fault_point(path: Path) -> None:
    """Count one write of ``path`` and, when the fault hook asks for it, fail it here."""
    global _writes
    fault = os.environ.get(FAULT_ENV)
    log = os.environ.get(FAULT_LOG_ENV)
    if not fault and not log:
        return
    with _WRITES_LOCK:
        _writes += 1
        count = _writes
        if log:
            with open(log, "a", encoding="utf-8") as f:
                f.write(f"{count}\t{path}\n")
    if fault:
        mode, _, number = fault.partition(":")
        if number.isdigit() and int(number) == count:
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


def open_new(tmp: Path):
    """Open the temporary file ``tmp`` for writing as a new file of this process: whatever has its name
    (a dead run's file, or a link someone planted there) is removed first, and the file is created with
    ``O_EXCL | O_NOFOLLOW``, so the write never lands in another file through a link."""
    _unlink_quietly(tmp)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    return os.fdopen(fd, "wb")


def _unlink_quietly(path: Path) -> None:
    try:
        os.unlink(path)  # a link itself, never its target
    except FileNotFoundError:
        pass
    except IsADirectoryError:
        raise OSError(errno.EISDIR, os.strerror(errno.EISDIR), str(path)) from None


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
        remove_dead_temporaries(path)
        with open_new(tmp) as f:
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
    removed: list[Path] = []
    folder = Path(folder)
    if folder.is_symlink() or not folder.is_dir():
        return removed  # only a folder of the run's own, never through a link
    for file in folder.glob(".*.tmp*"):
        if not re.fullmatch(r"\..+\.\d+\.tmp(\.[^.]*)?", file.name):
            continue
        try:
            if not (stat.S_ISREG(file.lstat().st_mode) or file.is_symlink()):
                continue
            file.unlink()  # a link is removed itself, its target is left alone
        except OSError:
            continue
        removed.append(file)
    return removed


def remove_dead_temporaries(path: Path) -> list[Path]:
    """Remove the temporary files of atomic writes of ``path`` (:func:`temporary_name`) whose process
    has ended: what a write stopped by ``kill -9`` or a power cut left beside a file that is not in a
    locked folder (a PLY, a depth map). A temporary of a running process is left alone."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    removed: list[Path] = []
    if folder.is_symlink() or not folder.is_dir():
        return removed
    pattern = re.compile(re.escape(f".{path.stem}.") + r"(\d+)" + re.escape(f".tmp{path.suffix}"))
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match is None or int(match[1]) == os.getpid() or _alive(int(match[1])):
            continue
        try:
            if entry.is_symlink() or entry.is_file(follow_symlinks=False):
                os.unlink(entry.path)
                removed.append(Path(entry.path))
        except OSError:
            continue
    return removed


def _alive(pid: int) -> bool:
    if pid <= 0:
        return True  # not a process id this module wrote: keep the file
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


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
        remove_dead_temporaries(path)
        _unlink_quietly(tmp)  # the writer then creates it afresh: never through a planted link
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
