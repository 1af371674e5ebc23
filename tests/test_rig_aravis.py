"""The Aravis camera: pixel-format decoding (pure), and the driver against Aravis's own simulated
GenICam camera ``Fake_1`` (not written here). ``./setup.sh`` installs Aravis and PyGObject; tests that
need them skip on a machine without them but FAIL under CI (env ``CI`` set)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

from rig.main import main
from rig.aravis import (
    PIXEL_FORMATS,
    AravisCamera,
    CameraTimeoutError,
    decode_frame,
    describe,
    list_devices,
    packed_size,
)
from rig.camera import CameraError

FAKE = "Fake_1"
ROI = (0, 0, 48, 32)


def require_aravis() -> None:
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as error:
        message = f"Aravis/PyGObject not installed ({error}); ./setup.sh installs them"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)


@pytest.fixture
def aravis() -> None:
    require_aravis()


# --------------------------------------------------------------------------------------------------
# Decoding, against packers written bit by bit from the PFNC / GigE Vision descriptions


def pack_bits_lsb_first(values: list[int], bits: int) -> bytes:
    """PFNC ``...p`` packing: the bit stream of consecutive values, least significant bit first."""
    stream = 0
    for i, value in enumerate(values):
        stream |= value << (i * bits)
    nbytes = (len(values) * bits + 7) // 8
    return stream.to_bytes(nbytes, "little")


def pack_mono12_gv(values: list[int]) -> bytes:
    out = bytearray()
    for a, b in zip(values[0::2], values[1::2]):
        out += bytes([a >> 4, ((b & 0xF) << 4) | (a & 0xF), b >> 4])
    return bytes(out)


def test_mono8_and_mono16_layouts():
    data = np.arange(12, dtype=np.uint8)
    image = decode_frame(data.tobytes(), pixel_format="Mono8", width=4, height=3)
    assert image.dtype == np.uint8 and image.shape == (3, 4) and image[2, 3] == 11
    words = np.array([0, 1, 256, 65535, 4660, 7], "<u2")
    image16 = decode_frame(words.tobytes(), pixel_format="Mono16", width=3, height=2)
    assert image16.dtype == np.uint16 and image16.tolist() == [[0, 1, 256], [65535, 4660, 7]]


@pytest.mark.parametrize("bits", [10, 12, 14])
def test_unpacked_high_bit_depths_are_msb_aligned(bits):
    rng = np.random.default_rng(bits)
    values = rng.integers(0, 2**bits, size=20, dtype=np.uint16)
    image = decode_frame(values.astype("<u2").tobytes(), pixel_format=f"Mono{bits}", width=5, height=4)
    assert image.dtype == np.uint16
    assert np.array_equal(image.reshape(-1) >> (16 - bits), values)  # lossless, top bits used
    assert image.max() <= 65535 and (image & ((1 << (16 - bits)) - 1)).max() == 0


@pytest.mark.parametrize("name,bits", [("Mono12p", 12), ("Mono10p", 10), ("Mono12Packed", 12)])
def test_packed_formats_against_bitwise_packers(name, bits):
    rng = np.random.default_rng(7)
    width, height = 6, 4  # 24 pixels: whole groups for both packings
    values = [int(v) for v in rng.integers(0, 2**bits, size=width * height)]
    values[:3] = [0, 2**bits - 1, 0x5A5 & (2**bits - 1)]  # extremes and a bit pattern
    data = pack_mono12_gv(values) if name == "Mono12Packed" else pack_bits_lsb_first(values, bits)
    assert len(data) == packed_size(PIXEL_FORMATS[name], width, height)
    image = decode_frame(data, pixel_format=name, width=width, height=height)
    assert (image.reshape(-1) >> (16 - bits)).tolist() == values


@pytest.mark.parametrize("pattern", ["RG", "GR", "GB", "BG"])
@pytest.mark.parametrize("bits", [8, 16])
def test_bayer_patterns_give_the_right_colours(pattern, bits):
    """A uniformly coloured scene seen through each mosaic must come back in that colour (RGB order)."""
    scene = {"R": 200, "G": 90, "B": 30}
    top = 255 if bits == 8 else 65535
    height, width = 8, 10
    mosaic = np.zeros((height, width), np.uint8 if bits == 8 else np.uint16)
    # the pattern names the 2x2 cell's row 0 (c00 c01); row 1 holds the other G and the other colour
    c00, c01 = pattern[0], pattern[1]
    opposite = {"R": "B", "B": "R"}
    if c00 == "G":
        c10, c11 = opposite[c01], "G"
    else:
        c10, c11 = "G", opposite[c00]
    for dy, dx, colour in ((0, 0, c00), (0, 1, c01), (1, 0, c10), (1, 1, c11)):
        mosaic[dy::2, dx::2] = scene[colour] * top // 255
    data = mosaic.astype("<u2").tobytes() if bits == 16 else mosaic.tobytes()
    rgb = decode_frame(data, pixel_format=f"Bayer{pattern}{bits}", width=width, height=height)
    assert rgb.shape == (height, width, 3) and rgb.dtype == mosaic.dtype
    centre = rgb[2:-2, 2:-2].reshape(-1, 3).astype(float) * 255 / top
    assert np.allclose(centre, [scene["R"], scene["G"], scene["B"]], atol=1.0)


def test_bgr8_is_returned_as_rgb():
    data = bytes([1, 2, 3] * 4)  # B=1, G=2, R=3
    image = decode_frame(data, pixel_format="BGR8", width=2, height=2)
    assert image.shape == (2, 2, 3) and image[0, 0].tolist() == [3, 2, 1]
    assert decode_frame(data, pixel_format="RGB8", width=2, height=2)[0, 0].tolist() == [1, 2, 3]


def test_truncated_frame_and_unknown_format_are_clear_errors():
    with pytest.raises(CameraError, match=r"Mono8 frame of 4x3 needs 12 bytes, the camera sent 11"):
        decode_frame(bytes(11), pixel_format="Mono8", width=4, height=3)
    with pytest.raises(CameraError, match=r"'YUV422_8' is not supported; choose one of Mono8"):
        decode_frame(bytes(24), pixel_format="YUV422_8", width=4, height=3)


# --------------------------------------------------------------------------------------------------
# Against Aravis's simulated camera


def test_fake_camera_is_listed(aravis):
    ids = [d["id"] for d in list_devices(include_fake=True)]
    assert FAKE in ids


def test_settings_are_applied_and_read_back(aravis):
    with AravisCamera(FAKE, roi=(8, 4, 64, 48), binning=2, exposure_us=2500, gain_db=3,
                      pixel_format="Mono16", trigger="software") as camera:
        image = camera.trigger()
        settings = camera.settings()
    assert image.shape == (48, 64) and image.dtype == np.uint16
    back = settings["readback"]
    assert back["pixel_format"] == "Mono16" and back["roi"] == [8, 4, 64, 48] and back["binning"] == [2, 2]
    assert back["exposure_us"] == 2500 and back["gain"] == 3 and back["gain_unit"] == "raw"  # Fake has GainRaw only
    assert back["trigger_mode"] == "On" and back["trigger_source"] == "Software"
    assert settings["device_id"] == FAKE and settings["frames"] == 1


def test_bayer_camera_gives_rgb(aravis):
    with AravisCamera(FAKE, roi=ROI, pixel_format="BayerRG8") as camera:
        image = camera.trigger()
    assert image.shape == (32, 48, 3) and image.dtype == np.uint8


@pytest.mark.parametrize("trigger", ["software", "free", "Line0"])
def test_every_frame_is_fresh(aravis, trigger):
    """Frames queue up while nobody asks (the Fake streams at 25 Hz whatever its trigger settings);
    each trigger must still return one received after the call began, never a queued one; free-running,
    one received at least an exposure plus a frame period (40 ms) after it."""
    with AravisCamera(FAKE, roi=ROI, exposure_us=5000, trigger=trigger) as camera:
        ids = []
        for _ in range(3):
            time.sleep(0.25)  # several frames are delivered into the queue meanwhile
            camera.trigger()
            last = camera.settings()["last_frame"]
            bound_ns = (5000 * 1000 + 40_000_000) if trigger == "free" else 0
            assert last["received_ns"] >= last["trigger_ns"] + bound_ns
            ids.append(last["frame_id"])
        assert ids == sorted(ids) and len(set(ids)) == 3


def test_bad_settings_are_one_line_errors(aravis):
    with pytest.raises(CameraError, match=r"exposure 5 us is outside its range \[10, 1e\+07\] us"):
        AravisCamera(FAKE, exposure_us=5)
    with pytest.raises(CameraError, match=r"offers no pixel format 'Mono12'; it offers .*Mono8"):
        AravisCamera(FAKE, pixel_format="Mono12")
    with pytest.raises(CameraError, match=r"has no trigger line 'Line3'; its trigger sources are Line0, Software"):
        AravisCamera(FAKE, trigger="Line3")
    with pytest.raises(CameraError, match=r"cannot open Aravis camera Nope_9.*lfrig camera list"):
        AravisCamera("Nope_9")
    with pytest.raises(CameraError, match=r"hardware trigger output needs a trigger line"):
        AravisCamera(FAKE, trigger="software", hardware_trigger=lambda on: None)


def _starve(camera: AravisCamera) -> None:
    """Make the simulated camera stop delivering: its frame rate to the minimum (0.1 Hz) through its own
    GenICam feature, so no frame arrives (or only one that the free-running freshness rule rejects)."""
    camera.device.set_float("AcquisitionFrameRate", 0.1)


def test_a_camera_that_stops_delivering_times_out_clearly(aravis):
    with AravisCamera(FAKE, roi=ROI, trigger="free", timeout_s=0.5) as camera:
        camera.trigger()
        _starve(camera)
        started = time.monotonic()
        with pytest.raises(CameraTimeoutError, match=r"camera Fake_1 delivered no fresh frame within 0.5 s"):
            camera.trigger()
        assert time.monotonic() - started < 3.0


# --------------------------------------------------------------------------------------------------
# Capture sessions with the fake stage


def capture_args(out: Path, *extra: str) -> list[str]:
    return ["capture", str(out), "--camera", f"aravis:{FAKE}", "--rows", "3", "--cols", "3", "--roi", *map(str, ROI),
            "--exposure-us", "2000", "--gain-db", "2", "--quiet", *extra]


def records(path: Path) -> list[dict]:
    return [json.loads(line) for line in (path / "manifest.jsonl").read_text().splitlines() if line.strip()]


def test_capture_completes_journals_resumes_and_reconstructs(aravis, tmp_path, capsys):
    out = tmp_path / "cap"
    assert main(capture_args(out)) == 0
    views = [r for r in records(out) if r.get("kind") == "view"]
    assert len(views) == 9
    for record in views:
        back = record["camera"]["readback"]
        assert back["exposure_us"] == 2000 and back["gain"] == 2 and back["pixel_format"] == "Mono8"
        assert back["trigger_mode"] == "On" and back["trigger_source"] == "Software"
        assert record["camera"]["last_frame"]["frame_id"] > 0
    frame_ids = [r["camera"]["last_frame"]["frame_id"] for r in views]
    assert len(set(frame_ids)) == 9  # one distinct frame per view
    assert records(out)[-1]["kind"] == "complete"
    # resuming a complete capture takes nothing; other settings are refused by name
    assert main(capture_args(out)) == 0
    assert "0 taken now" in capsys.readouterr().out
    assert main(capture_args(out)[:-1] + ["--exposure-us", "3000", "--quiet"]) == 2
    assert "camera.exposure_us: capture has 2000.0, now 3000.0" in capsys.readouterr().err
    assert main(["reconstruct", str(out), "-o", str(tmp_path / "rec"), "--method", "baseline",
                 "--disparity-range", "-1", "1", "--step", "0.5", "--quiet"]) == 0
    assert (tmp_path / "rec" / "disparity.pfm").is_file()


def test_camera_that_stops_mid_capture_aborts_resumably(aravis, tmp_path, capsys):
    from rig.aravis import open_aravis
    from rig.devices import open_stage
    from rig.grid import GridSpec
    from rig.session import CaptureAborted, run_capture

    out = tmp_path / "cap"
    grid = GridSpec(rows=3, cols=3, pitch_mm=0.5, centre_mm=(-50.0, -50.0, -10.0))
    devices = open_stage("fake")
    camera, request = open_aravis(f"aravis:{FAKE}", roi=ROI, trigger="free", timeout_s=0.5, clock=devices.clock)
    taken = 0
    real_trigger = camera.trigger

    def trigger():
        nonlocal taken
        if taken == 4:
            _starve(camera)
        taken += 1
        return real_trigger()

    camera.trigger = trigger  # type: ignore[method-assign]
    try:
        with pytest.raises(CaptureAborted) as caught:
            run_capture(out, stage=devices.stage, camera=camera, grid=grid, camera_request=request,
                        clock=devices.clock, progress=None, handle_sigint=False)
    finally:
        camera.close()
        devices.close()
    message = str(caught.value)
    assert "delivered no fresh frame within 0.5 s" in message and "4 of 9 views" in message
    assert "run the same command again to resume" in message
    assert len([r for r in records(out) if r.get("kind") == "view"]) == 4
    # the same settings through the command line resume it: 5 more views, complete
    assert main(["capture", str(out), "--camera", f"aravis:{FAKE}", "--rows", "3", "--cols", "3",
                 "--roi", *map(str, ROI), "--trigger", "free", "--frame-timeout-s", "2", "--quiet"]) == 0
    assert "9 of 9 views (5 taken now), complete" in capsys.readouterr().out


def test_cli_error_for_a_missing_device_is_one_line(aravis, tmp_path, capsys):
    assert main(["capture", str(tmp_path / "c"), "--camera", "aravis:Nope_9", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("lfrig: error: cannot open Aravis camera Nope_9")


def test_hardware_trigger_pulses_the_stage_output(aravis, tmp_path):
    """With --trigger Line0 --hw-trigger each view pulses M8 on the (simulated GRBL) stage. The Fake
    camera streams regardless of its trigger line, so this checks the wiring, not the camera."""
    from rig.aravis import open_aravis
    from rig.devices import open_stage
    from rig.grid import GridSpec
    from rig.session import run_capture

    grid = GridSpec(rows=2, cols=2, pitch_mm=0.5, centre_mm=(-50.0, -50.0, -10.0))
    devices = open_stage("fake")
    try:
        camera, request = open_aravis(f"aravis:{FAKE}", roi=ROI, trigger="Line0",
                                      hardware_trigger=devices.stage.set_output, clock=devices.clock)
        with camera:
            result = run_capture(tmp_path / "cap", stage=devices.stage, camera=camera, grid=grid,
                                 camera_request=request, clock=devices.clock, progress=None, handle_sigint=False)
            assert camera.settings()["readback"]["trigger_source"] == "Line0"
        events = [on for _, on, *_ in devices.controller.output_events]
    finally:
        devices.close()
    assert result.complete and events == [True, False] * 4


def test_camera_commands(aravis, capsys):
    assert main(["camera", "list", "--fake"]) == 0
    assert f"aravis:{FAKE}  Aravis Fake" in capsys.readouterr().out
    assert main(["camera", "info", f"aravis:{FAKE}"]) == 0
    out = capsys.readouterr().out
    assert "2048 x 2048 px" in out and "Mono8" in out and "sources Line0, Software" in out
    assert main(["camera", "info", f"aravis:{FAKE}", "--all", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["features"]["AcquisitionControl"]["ExposureTimeAbs"] == "10000"
    assert main(["camera", "info", "fake"]) == 2
    assert "expected aravis:, aravis:DEVICE_ID or opencv:INDEX|PATH" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------------
# Aravis's simulated GigE Vision camera: a real GVCP/GVSP server on the loopback interface, which
# (unlike Fake_1) takes a frame only when triggered


class GigEFake:
    """``Aravis.GvFakeCamera`` serving on ``lo``; :meth:`stop` is a pulled cable."""

    address = "127.0.0.1"

    def __init__(self) -> None:
        self.server = None

    def start(self) -> "GigEFake":
        from gi.repository import Aravis

        self.server = Aravis.GvFakeCamera.new("lo", "GV01")
        assert self.server.is_running()
        return self

    def stop(self) -> None:
        import gc

        self.server = None  # the last reference: Aravis stops its threads and closes the sockets
        gc.collect()


@pytest.fixture
def gige(aravis):
    fake = GigEFake().start()
    yield fake
    fake.stop()


def test_gige_camera_takes_exactly_one_frame_per_software_trigger(gige):
    with AravisCamera(gige.address, roi=ROI) as camera:
        ids = []
        for _ in range(3):
            camera.trigger()
            ids.append(camera.settings()["last_frame"]["frame_id"])
            time.sleep(0.3)
            assert camera._flush() == 0  # nothing arrives unasked: the camera really waits for the trigger
        info = describe(camera)
    assert ids == [ids[0], ids[0] + 1, ids[0] + 2]
    assert info["protocol"] == "GigE Vision" and info["serial"] == "GV01"


def test_gige_line_trigger_that_never_fires_times_out(gige):
    with AravisCamera(gige.address, roi=ROI, trigger="Line0", timeout_s=0.5) as camera:
        with pytest.raises(CameraTimeoutError, match=r"no fresh frame within 0.5 s after the trigger; is Line0 wired"):
            camera.trigger()
        assert camera.settings()["readback"]["trigger_source"] == "Line0"


def test_gige_hw_trigger_without_wiring_is_one_line_and_resumable(gige, tmp_path, capsys):
    """--hw-trigger pulses the stage's M8, but nothing connects it to the simulated camera's Line0."""
    out = tmp_path / "cap"
    args = ["capture", str(out), "--camera", f"aravis:{gige.address}", "--rows", "2", "--cols", "2", "--roi",
            *map(str, ROI), "--trigger", "Line0", "--hw-trigger", "--frame-timeout-s", "0.5", "--quiet"]
    assert main(args) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("lfrig:")]
    assert len(err) == 1 and "is Line0 wired to the trigger output (the stage's M8) and firing?" in err[0]
    assert "0 of 4 views" in err[0] and "run the same command again to resume" in err[0]


@pytest.mark.slow
def test_gige_cable_pulled_mid_capture_then_resumed(gige, tmp_path, capsys):
    from rig.aravis import open_aravis
    from rig.devices import open_stage
    from rig.grid import GridSpec
    from rig.session import CaptureAborted, run_capture

    out = tmp_path / "cap"
    grid = GridSpec(rows=3, cols=3, pitch_mm=0.5, centre_mm=(-50.0, -50.0, -10.0))
    devices = open_stage("fake")
    camera, request = open_aravis(f"aravis:{gige.address}", roi=ROI, timeout_s=1, clock=devices.clock)
    taken = 0
    real_trigger = camera.trigger

    def trigger():
        nonlocal taken
        if taken == 3:
            gige.stop()
        taken += 1
        return real_trigger()

    camera.trigger = trigger  # type: ignore[method-assign]
    try:
        with pytest.raises(CaptureAborted) as caught:
            run_capture(out, stage=devices.stage, camera=camera, grid=grid, camera_request=request,
                        clock=devices.clock, progress=None, handle_sigint=False)
    finally:
        camera.close()
        devices.close()
    assert "software trigger failed" in str(caught.value) and "3 of 9 views" in str(caught.value)
    gige.start()  # plugged back in
    assert main(["capture", str(out), "--camera", f"aravis:{gige.address}", "--rows", "3", "--cols", "3",
                 "--roi", *map(str, ROI), "--quiet"]) == 0
    assert "9 of 9 views (6 taken now), complete" in capsys.readouterr().out
