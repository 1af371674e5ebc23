"""PNG views decode to OpenCV's pixels whichever decoder reads them: every kind of PNG (grey, RGB,
palette, grey+alpha, RGBA; 1 to 16 bits; interlaced; tRNS, gAMA, sBIT, eXIf), written here chunk by chunk
with random pixels, reads as ``cv2.imdecode(IMREAD_UNCHANGED)`` in RGB order without alpha."""

import struct
import zlib

import cv2
import numpy as np
import pytest

import recon.lf.imageio as imageio
from recon.errors import LightFieldFormatError
from recon.lf.imageio import read_image, read_images
from recon.lf.lightfield import to_gray

SAMPLES = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples a pixel
ADAM7 = [(0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)]
W, H = 13, 11  # odd sizes: partial bytes at low bit depths, every Adam7 pass partly filled


def chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def scanlines(samples: np.ndarray, depth: int) -> bytes:
    """Rows of ``(h, w, n)`` samples as PNG scanlines, each after its filter byte (0)."""
    if depth == 16:
        return b"".join(b"\0" + row.astype(">u2").tobytes() for row in samples)
    if depth == 8:
        return b"".join(b"\0" + row.astype(np.uint8).tobytes() for row in samples)
    bits = np.unpackbits(samples.astype(np.uint8)[..., None], axis=-1)[..., 8 - depth:]
    return b"".join(b"\0" + np.packbits(row.reshape(-1)).tobytes() for row in bits)


def make_png(colour: int, depth: int, *, seed: int = 0, trns: bool = False, interlace: bool = False,
             extra: bytes = b"", width: int = W, height: int = H) -> bytes:
    rng = np.random.default_rng(seed)
    top = (1 << depth) - 1
    chunks = b""
    if colour == 3:
        entries = 1 << depth
        chunks += chunk(b"PLTE", rng.integers(0, 256, 3 * entries, dtype=np.uint8).tobytes())
        if trns:
            chunks += chunk(b"tRNS", rng.integers(0, 256, max(1, entries // 2), dtype=np.uint8).tobytes())
    elif trns:  # one transparent grey level or colour, one that occurs in the image
        chunks += chunk(b"tRNS", struct.pack(">" + "H" * SAMPLES[colour], *[1] * SAMPLES[colour]))
    samples = rng.integers(0, top, (height, width, SAMPLES[colour]), endpoint=True)
    samples[0, 0] = 1
    passes = [samples[y0::dy, x0::dx] for x0, y0, dx, dy in ADAM7] if interlace else [samples]
    data = b"".join(scanlines(p, depth) for p in passes if p.size)
    header = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, int(interlace))
    return (imageio.PNG_SIGNATURE + chunk(b"IHDR", header) + extra + chunks
            + chunk(b"IDAT", zlib.compress(data)) + chunk(b"IEND", b""))


def opencv_pixels(data: bytes) -> np.ndarray:
    """What lfrig read before it decoded PNGs by imagecodecs: OpenCV's pixels, BGR(A) to RGB."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB if image.shape[2] == 3 else cv2.COLOR_BGRA2RGB)
    return image


KINDS = ([(0, depth) for depth in (1, 2, 4, 8, 16)] + [(3, depth) for depth in (1, 2, 4, 8)]
         + [(colour, depth) for colour in (2, 4, 6) for depth in (8, 16)])
#: Chunks neither decoder applies: a gamma, and an EXIF orientation (rotate by 90 degrees); sBIT per kind.
ANCILLARY = chunk(b"gAMA", struct.pack(">I", 100000)) + chunk(
    b"eXIf", b"MM\0*" + struct.pack(">IHHHIHHI", 8, 1, 0x0112, 3, 1, 6, 0, 0))


def cases():
    for colour, depth in KINDS:
        for trns in (False, True) if colour in (0, 2, 3) else (False,):
            for interlace in (False, True):
                name = f"colour{colour}-{depth}bit{'-tRNS' if trns else ''}{'-interlaced' if interlace else ''}"
                yield pytest.param(colour, depth, trns, interlace, id=name)


@pytest.mark.parametrize("colour, depth, trns, interlace", list(cases()))
def test_every_kind_of_png_reads_as_opencv_decodes_it(tmp_path, monkeypatch, colour, depth, trns, interlace):
    """``read_image`` and ``read_images`` (as stored, in place, and as grey) give OpenCV's pixels,
    with gAMA, sBIT and eXIf chunks too (neither decoder applies them); OpenCV itself decodes only the
    kinds libpng through imagecodecs gives otherwise: grey with alpha, grey with tRNS."""
    sbit = chunk(b"sBIT", bytes([max(1, depth // 2)] * (3 if colour == 3 else SAMPLES[colour])))
    paths = []
    for i in range(3):
        paths.append(tmp_path / f"view{i}.png")
        paths[-1].write_bytes(make_png(colour, depth, seed=i, trns=trns, interlace=interlace,
                                       extra=ANCILLARY + sbit if i == 1 else b""))
    expected = np.stack([opencv_pixels(path.read_bytes()) for path in paths])
    by_opencv = []
    decode_quietly = imageio.decode_quietly
    monkeypatch.setattr(imageio, "decode_quietly", lambda data: by_opencv.append(1) or decode_quietly(data))

    image = read_image(paths[1])
    assert image.dtype == expected.dtype and np.array_equal(image, expected[1])
    views = read_images(paths)
    assert views.dtype == expected.dtype and np.array_equal(views, expected)
    keep = {1: None}
    grey = read_images(paths, grey=True, keep=keep)
    np.testing.assert_array_equal(grey.view(np.uint32), to_gray(expected).view(np.uint32))
    assert np.array_equal(keep[1], expected[1]) and keep[1].flags.c_contiguous
    assert read_images(paths, decode=False).shape == expected.shape
    assert len(by_opencv) == (0 if colour != 4 and not (colour == 0 and trns) else 1 + 3 + 3 + 1)


def test_a_grey_view_with_trns_reads_as_grey_like_the_others(tmp_path):
    """OpenCV drops a grey PNG's tRNS chunk: a view set whose first view has one reads as grey, the
    same shape with and without decoding (``lfrig info``), and so does one where a later view has it."""
    for first in (True, False):
        paths = []
        for i in range(3):
            paths.append(tmp_path / f"{first}-view{i}.png")
            paths[-1].write_bytes(make_png(0, 8, seed=i, trns=(i == 0) == first))
        expected = np.stack([opencv_pixels(path.read_bytes()) for path in paths])
        assert expected.shape == (3, H, W)
        assert np.array_equal(read_images(paths), expected)
        assert read_images(paths, decode=False).shape == expected.shape


def damaged_image_data(data: bytes) -> bytes:
    """The PNG with its image data zeroed halfway (its chunk's CRC made right again)."""
    start = data.index(b"IDAT") - 4
    length = int.from_bytes(data[start:start + 4], "big")
    body = bytearray(data[start + 4:start + 8 + length])
    body[4 + length // 2:] = bytes(length - length // 2)
    return data[:start + 4] + bytes(body) + struct.pack(">I", zlib.crc32(body)) + data[start + 12 + length:]


def short_image_data(data: bytes) -> bytes:
    """The PNG with a whole zlib stream of half its rows: every chunk sound, too little image data."""
    start = data.index(b"IDAT") - 4
    length = int.from_bytes(data[start:start + 4], "big")
    rows = zlib.decompress(data[start + 8:start + 8 + length])
    return data[:start] + chunk(b"IDAT", zlib.compress(rows[:len(rows) // 2])) + data[start + 12 + length:]


@pytest.mark.parametrize("damage", ["truncated", "image data", "short image data", "bad filter"])
@pytest.mark.parametrize("colour", [2, 4])  # decoded by imagecodecs, by OpenCV
def test_a_damaged_png_is_refused_naming_the_file(tmp_path, capfd, damage, colour):
    good = make_png(colour, 8, interlace=False, width=64, height=40)
    if damage == "truncated":
        data = good[:len(good) - 30]
    elif damage == "image data":
        data = damaged_image_data(good)
    elif damage == "short image data":
        data = short_image_data(good)
    else:
        start = good.index(b"IDAT") - 4
        length = int.from_bytes(good[start:start + 4], "big")
        rows = bytearray(zlib.decompress(good[start + 8:start + 8 + length]))
        rows[0] = 7  # no such filter type
        data = good[:start] + chunk(b"IDAT", zlib.compress(bytes(rows))) + good[start + 12 + length:]
    paths = [tmp_path / "view0.png", tmp_path / "view1.png"]
    paths[0].write_bytes(good)
    paths[1].write_bytes(data)
    for read in (lambda: read_image(paths[1]), lambda: read_images(paths), lambda: read_images(paths, grey=True)):
        with pytest.raises(LightFieldFormatError, match="view1.png: "):
            read()
    assert "PNG" not in capfd.readouterr().err or colour == 4  # imagecodecs prints nothing of its own
