"""``lfrig camera snap`` and the OpenCV side of ``camera list`` / ``camera info``: the fake camera,
Aravis's ``Fake_1`` and OpenCV reading a video file that OpenCV's own writer made (no /dev/video* here:
the device folder of the listing is a temporary folder whose ``video0`` links to that file)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from rig.main import main
from rig.snap import focus_measure, frame_stats, full_scale
from tests.test_rig_aravis import require_aravis

SMALL = ["--binning", "8", "--supersample", "1"]


def write_video(path: Path, values: list[int], size=(64, 48)) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, size)
    assert writer.isOpened()
    for value in values:
        writer.write(np.full((size[1], size[0], 3), value, np.uint8))
    writer.release()
    return path


def reported(text: str) -> dict:
    m = re.search(r"(\d+) x (\d+) px, .*min (\d+), max (\d+); clipped ([\d.]+) % at 0, ([\d.]+) % at the top", text)
    assert m, text
    w, h, lo, hi = (int(g) for g in m.groups()[:4])
    return {"w": w, "h": h, "min": lo, "max": hi, "low": float(m.group(5)), "high": float(m.group(6))}


@pytest.mark.parametrize("bits", [8, 16])
def test_snap_fake_writes_the_frame_it_reports(tmp_path, capsys, bits):
    out = tmp_path / "snap.png"
    assert main(["camera", "snap", "fake", "-o", str(out), "--bit-depth", str(bits), *SMALL]) == 0
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image.dtype == (np.uint8 if bits == 8 else np.uint16)
    got = reported(capsys.readouterr().out)
    assert (got["w"], got["h"]) == (image.shape[1], image.shape[0]) == (160, 122)
    assert (got["min"], got["max"]) == (image.min(), image.max()) and got["max"] > got["min"]
    assert not list(tmp_path.glob(".*tmp*"))  # written through a temporary file, renamed into place
    assert main(["camera", "snap", "fake", "-o", str(out), "--bit-depth", str(bits), *SMALL, "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert (record["path"], record["width"], record["min"], record["max"]) == (str(out), 160, got["min"], got["max"])
    assert record["top"] == (255 if bits == 8 else 65535) and record["clipped_high"] == 0.0


def test_snap_aravis_fake_1_mono16(tmp_path, capsys):
    require_aravis()
    out = tmp_path / "a.png"
    assert main(["camera", "snap", "aravis:Fake_1", "-o", str(out), "--pixel-format", "Mono16",
                 "--roi", "0", "0", "64", "48"]) == 0
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image.shape == (48, 64) and image.dtype == np.uint16
    got = reported(capsys.readouterr().out)
    assert (got["min"], got["max"]) == (image.min(), image.max())


def test_snap_opencv_reads_a_real_stream(tmp_path, capsys):
    video = write_video(tmp_path / "v.avi", [0, 50, 100, 150, 200, 250])
    out = tmp_path / "o.png"
    assert main(["camera", "snap", f"opencv:{video}", "-o", str(out)]) == 0
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image.shape == (48, 64, 3)
    # the default drops 4 buffered frames, so the fifth frame (value 200) is the one written
    assert abs(int(np.median(image)) - 200) <= 3
    assert reported(capsys.readouterr().out)["w"] == 64


def test_snap_bad_input_is_one_line(tmp_path, capsys):
    cases = [
        (["camera", "snap", "nocam", "-o", str(tmp_path / "a.png")], "expected 'fake'"),
        (["camera", "snap", "fake", "-o", str(tmp_path / "a.jpg")], "give a .png file name"),
        (["camera", "snap", "fake", "-o", str(tmp_path / "missing" / "a.png")], "does not exist"),
        (["camera", "snap", "fake", "-o", str(tmp_path)], "give a .png"),
        (["camera", "snap", f"opencv:{tmp_path / 'none.avi'}", "-o", str(tmp_path / "a.png")], "cannot open camera"),
    ]
    (tmp_path / "link.png").symlink_to(tmp_path / "elsewhere.png")
    cases.append((["camera", "snap", "fake", "-o", str(tmp_path / "link.png")], "symbolic link"))
    for argv, words in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("lfrig: error: ") and words in err[0], (argv, err)
    assert not (tmp_path / "elsewhere.png").exists() and not (tmp_path / "a.png").exists()


def test_stats_count_clipping_against_the_cameras_full_scale():
    image = np.array([[0, 0, 10, 4080], [4080, 4095, 100, 200]], np.uint16) << 4  # 12 bits, MSB-aligned
    top = full_scale(image, {"significant_bits": 12, "bit_shift": 4})
    assert top == 0xFFF0
    stats = frame_stats(image, top=top)
    assert (stats.clipped_low, stats.clipped_high) == (2 / 8, 1 / 8)
    assert full_scale(image, {}) == 65535 and frame_stats(image, top=65535).clipped_high == 0
    assert full_scale(image.astype(np.uint8), None) == 255


def test_focus_measure_prefers_the_sharp_image_and_is_zero_on_a_flat_one():
    rng = np.random.default_rng(0)
    sharp = (rng.random((60, 80)) * 255).astype(np.uint8)
    blurred = cv2.GaussianBlur(sharp, (0, 0), 2.0)
    assert focus_measure(sharp, top=255) > 10 * focus_measure(blurred, top=255) > 0
    assert focus_measure(np.full((60, 80), 77, np.uint8), top=255) == 0.0
    # a region: sharp half against blurred half of one image
    both = np.concatenate([blurred[:, :40], sharp[:, 40:]], axis=1)
    assert focus_measure(both, top=255, roi=(40, 0, 40, 60)) > 10 * focus_measure(both, top=255, roi=(0, 0, 40, 60))
    # the same at 16 bits: the measure does not depend on the bit depth
    assert focus_measure(sharp.astype(np.uint16) * 257, top=65535) == pytest.approx(focus_measure(sharp, top=255))


def test_camera_list_and_info_show_video_devices(tmp_path, capsys):
    video = write_video(tmp_path / "v.avi", [10, 20, 30])
    dev = tmp_path / "dev"
    dev.mkdir()
    (dev / "video0").symlink_to(video)
    (dev / "video1").write_bytes(b"")  # a node OpenCV cannot open
    (dev / "videoX").write_bytes(b"")  # not a video node name
    assert main(["camera", "list", "--dev-dir", str(dev), "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)["opencv"]
    assert [e["path"] for e in listing] == [str(dev / "video0"), str(dev / "video1")]
    first, second = listing
    assert first["opens"] and (first["width_px"], first["height_px"], first["fps"], first["fourcc"]) == (64, 48, 10, "MJPG")
    assert first["frame"] == {"shape": [48, 64, 3], "dtype": "uint8"}
    assert not second["opens"]
    assert main(["camera", "list", "--dev-dir", str(dev)]) == 0
    out = capsys.readouterr().out
    assert f"opencv:{dev / 'video0'}  64 x 48 px, 10 fps, MJPG" in out and "OpenCV cannot open it" in out
    assert main(["camera", "info", f"opencv:{video}"]) == 0
    assert "64 x 48 px, 10 fps, MJPG" in capsys.readouterr().out


def test_camera_list_says_when_there_is_no_video_device(tmp_path, capsys):
    assert main(["camera", "list", "--dev-dir", str(tmp_path)]) == 0
    assert f"no video device found ({tmp_path}/video*" in capsys.readouterr().out
    assert main(["camera", "list", "--dev-dir", str(tmp_path / "nope")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert main(["camera", "info", "opencv:7"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "OpenCV cannot open it" in err[0]


def test_a_missing_opencv_device_is_one_line_on_stderr(tmp_path):
    """Also at the file-descriptor level: OpenCV's own warnings about the device are not printed."""
    import subprocess
    import sys

    for argv in (["camera", "snap", "opencv:9", "-o", str(tmp_path / "a.png")], ["camera", "info", "opencv:9"]):
        done = subprocess.run([sys.executable, "-m", "rig.main", *argv], cwd=Path(__file__).resolve().parents[1],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("lfrig: error: ") and "opencv" in lines[0].lower(), lines
