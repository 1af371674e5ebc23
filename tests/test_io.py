"""Light-field folders: both layouts read back what was written; bad input gives one clear line."""

import json

import cv2
import numpy as np
import pytest

from rig.main import main
from recon.errors import LfrigError
from recon.lf import read_lightfield, write_lightfield
from recon.lf.lightfield import LightField
from recon.errors import CaptureLayoutError
from recon.lf.capture import CaptureWriter, read_capture

CFG = """[intrinsics]
focal_length_mm = 100
sensor_size_mm = 35
image_resolution_x_px = 8
image_resolution_y_px = 6

[extrinsics]
num_cams_x = 3
num_cams_y = 3
baseline_mm = 30
focus_distance_m = 8

[meta]
disp_min = -1.5
disp_max = 0.5
"""


def random_views(rows=3, cols=3, h=6, w=8, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (rows, cols, h, w, 3), dtype=np.uint8)


def write_benchmark(folder, views, cfg=CFG):
    folder.mkdir(exist_ok=True)
    rows, cols = views.shape[:2]
    for u in range(rows):
        for v in range(cols):
            cv2.imwrite(str(folder / f"input_Cam{u * cols + v:03d}.png"), views[u, v, :, :, ::-1])
    if cfg is not None:
        (folder / "parameters.cfg").write_text(cfg)
    return folder


def test_benchmark_layout_is_row_major_rgb_with_parameters(tmp_path):
    views = random_views()
    lf = read_lightfield(write_benchmark(tmp_path / "scene", views))
    np.testing.assert_array_equal(lf.views, views)
    assert lf.grid_shape == (3, 3) and lf.centre_index == (1, 1)
    assert lf.pitch_mm == 30 and lf.disparity_range == (-1.5, 0.5)
    assert lf.focal_px == pytest.approx(100 / 35 * 8)
    assert lf.disparity_offset == pytest.approx(lf.focal_px * 30 / 8000)


def test_benchmark_without_parameters_takes_the_grid_from_the_view_count(tmp_path):
    lf = read_lightfield(write_benchmark(tmp_path / "scene", random_views(), cfg=None))
    assert lf.grid_shape == (3, 3) and lf.pitch_mm is None and lf.disparity_range is None


def test_capture_layout_round_trip(tmp_path):
    lf = LightField(views=random_views(), pitch_mm=0.5, focal_px=7000.0, disparity_range=(3.0, 4.0))
    write_lightfield(tmp_path / "cap", lf)
    back = read_lightfield(tmp_path / "cap")
    np.testing.assert_array_equal(back.views, lf.views)
    assert back.pitch_mm == 0.5 and back.focal_px == 7000.0 and back.disparity_range == (3.0, 4.0)
    assert back.metadata["layout"] == "lfrig-capture"


def header(pitch=0.5):
    grid = {"rows": 2, "cols": 2, "pitch_mm": pitch}
    return {"grid": grid, "settings": {"grid": grid, "order": "serpentine"}}


def test_capture_resumes_and_refuses_other_settings(tmp_path):
    image = np.zeros((4, 5, 3), np.uint8)
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        w.write_view(0, 0, image, {"commanded_mm": [0, 0, 0]})
        w.write_view(0, 1, image + 1)
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        assert set(w.completed) == {(0, 0), (0, 1)}
        assert w.completed[(0, 0)]["commanded_mm"] == [0, 0, 0]
    with pytest.raises(CaptureLayoutError, match="other settings.*grid"):
        CaptureWriter(tmp_path / "c", header=header(pitch=0.6))


def test_capture_drops_views_whose_file_changed_or_vanished(tmp_path):
    image = np.zeros((4, 5, 3), np.uint8)
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        w.write_view(0, 0, image)
        w.write_view(1, 1, image)
    (tmp_path / "c/views/u00_v00.png").unlink()
    (tmp_path / "c/views/u01_v01.png").write_bytes(b"garbage")
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        assert w.completed == {}


def test_capture_ignores_a_torn_last_journal_line(tmp_path):
    image = np.zeros((4, 5, 3), np.uint8)
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        w.write_view(0, 0, image)
    with open(tmp_path / "c/manifest.jsonl", "a") as f:
        f.write('{"kind": "view", "u": 0, "v"')
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        assert set(w.completed) == {(0, 0)}


def test_incomplete_capture_says_how_to_resume(tmp_path):
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        w.write_view(0, 0, np.zeros((4, 5), np.uint8))
    with pytest.raises(CaptureLayoutError, match="3 of 4 views missing.*again to resume"):
        read_capture(tmp_path / "c")


def test_capture_manifest_is_json_lines(tmp_path):
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        w.write_view(1, 0, np.zeros((4, 5), np.uint8))
    lines = [json.loads(line) for line in (tmp_path / "c/manifest.jsonl").read_text().splitlines()]
    assert lines[0]["kind"] == "header" and lines[0]["format"] == "lfrig-capture"
    assert lines[1]["file"] == "views/u01_v00.png" and len(lines[1]["sha256"]) == 64


# --- bad input through the command line: one line naming the file, exit 2, no traceback ----------

def run_cli(capsys, *args):
    status = main(list(map(str, args)))
    captured = capsys.readouterr()
    return status, captured.err


def broken(tmp_path, kind):
    folder = write_benchmark(tmp_path / "scene", random_views())
    if kind == "missing":
        (folder / "input_Cam004.png").unlink()
        return folder, "input_Cam004.png"
    if kind == "extra":
        cv2.imwrite(str(folder / "input_Cam009.png"), np.zeros((6, 8, 3), np.uint8))
        return folder, "input_Cam009.png"
    if kind == "mixed":
        cv2.imwrite(str(folder / "input_Cam005.png"), np.zeros((7, 8, 3), np.uint8))
        return folder, "input_Cam005.png"
    if kind == "unreadable":
        (folder / "input_Cam002.png").write_bytes(b"\x89PNG not really")
        return folder, "input_Cam002.png"
    if kind == "cfg":
        (folder / "parameters.cfg").write_text("this is [not an ini file\n")
        return folder, "parameters.cfg"
    if kind == "cfg-value":
        (folder / "parameters.cfg").write_text(CFG.replace("disp_min = -1.5", "disp_min = 2"))
        return folder, "parameters.cfg"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["missing", "extra", "mixed", "unreadable", "cfg", "cfg-value"])
def test_bad_light_field_gives_one_line_naming_the_file(tmp_path, capsys, kind):
    folder, name = broken(tmp_path, kind)
    status, err = run_cli(capsys, "info", folder)
    assert status == 2
    assert err.startswith("lfrig: error: ") and err.count("\n") == 1
    assert name in err and "Traceback" not in err


def test_broken_pfm_through_evaluate(tmp_path, capsys):
    (tmp_path / "gt.pfm").write_bytes(b"Pf\n2 2\n-1.0\n")
    (tmp_path / "e.pfm").write_bytes(b"Pf\n2 2\n-1.0\n" + bytes(16))
    status, err = run_cli(capsys, "evaluate", tmp_path / "e.pfm", tmp_path / "gt.pfm")
    assert status == 2 and "gt.pfm" in err and "truncated" in err and err.count("\n") == 1


def test_not_a_light_field(tmp_path):
    with pytest.raises(LfrigError, match="no light field here"):
        read_lightfield(tmp_path)


def test_complete_marker_is_written_once_and_cleared_by_a_retake(tmp_path):
    image = np.zeros((4, 5), np.uint8)
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        for u in range(2):
            for v in range(2):
                w.write_view(u, v, image)
        w.mark_complete()
        w.mark_complete()
    kinds = [json.loads(line)["kind"] for line in (tmp_path / "c/manifest.jsonl").read_text().splitlines()]
    assert kinds.count("complete") == 1
    with CaptureWriter(tmp_path / "c", header=header()) as w:
        assert w.marked_complete
        w.write_view(0, 0, image)
        assert not w.marked_complete


def test_principal_point_survives_the_capture_layout(tmp_path):
    lf = LightField(views=random_views(), pitch_mm=0.5, focal_px=900.0, principal_point_px=(3.25, 2.5))
    write_lightfield(tmp_path / "cap", lf)
    assert read_lightfield(tmp_path / "cap").principal_point_px == (3.25, 2.5)


@pytest.mark.parametrize("channels", [0, 3, 4])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_views_are_decoded_in_place_as_rgb(tmp_path, channels, dtype):
    """Grey stays grey; BGR and BGRA files (as OpenCV writes them) come back RGB without alpha, from
    ``read_image`` and straight into ``read_images``' array alike."""
    from recon.lf.imageio import read_image, read_images

    rng = np.random.default_rng(channels)
    shape = (5, 7) if channels == 0 else (5, 7, channels)
    stored = [rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True) for _ in range(3)]
    paths = []
    for i, image in enumerate(stored):
        paths.append(tmp_path / f"view{i}.png")
        assert cv2.imwrite(str(paths[-1]), image)
    expected = [image if channels == 0 else image[:, :, 2::-1] for image in stored]
    views = read_images(paths)
    assert views.dtype == dtype and views.shape == (3,) + expected[0].shape
    for i, path in enumerate(paths):
        assert np.array_equal(read_image(path), expected[i]) and np.array_equal(views[i], expected[i])


@pytest.mark.parametrize("channels", [0, 3, 4])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_views_read_as_grey_are_to_gray_of_the_stored_views_bit_for_bit(tmp_path, channels, dtype):
    """``read_images(grey=True)`` converts each view as it is decoded, by strips of rows: the same
    float32 bits as ``to_gray`` of the stored views (13 px wide: OpenCV's last ``W % 8`` pixels of a
    row take another path; more rows than a strip), and ``keep`` gets the view as stored."""
    from recon.lf.imageio import GREY_STRIP_ROWS, read_images
    from recon.lf.lightfield import to_gray

    rng = np.random.default_rng(channels + 7)
    height = 2 * GREY_STRIP_ROWS + 5
    shape = (height, 13) if channels == 0 else (height, 13, channels)
    paths = []
    for i in range(4):
        paths.append(tmp_path / f"view{i}.png")
        assert cv2.imwrite(str(paths[-1]), rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True))
    stored = read_images(paths)
    keep = {2: None}
    grey = read_images(paths, grey=True, keep=keep)
    assert grey.dtype == np.float32 and grey.shape == (4, height, 13)
    np.testing.assert_array_equal(grey.view(np.uint32), to_gray(stored).view(np.uint32))
    np.testing.assert_array_equal(keep[2], stored[2])


@pytest.mark.parametrize("layout", ["benchmark", "capture"])
def test_a_light_field_read_as_grey_keeps_its_centre_view_as_stored(tmp_path, layout):
    from recon.lf.lightfield import to_gray

    views = random_views(rows=3, cols=5, h=6, w=11)
    if layout == "benchmark":
        cfg = CFG.replace("num_cams_x = 3", "num_cams_x = 5").replace("resolution_x_px = 8", "resolution_x_px = 11")
        folder = write_benchmark(tmp_path / "scene", views, cfg=cfg)
    else:
        folder = tmp_path / "cap"
        write_lightfield(folder, LightField(views=views, pitch_mm=0.5))
    stored, grey = read_lightfield(folder), read_lightfield(folder, grey=True)
    assert grey.views.shape == (3, 5, 6, 11) and grey.grid_shape == (3, 5) and grey.image_shape == (6, 11)
    np.testing.assert_array_equal(grey.views.view(np.uint32), to_gray(stored.views).view(np.uint32))
    assert grey.gray() is grey.views  # no second copy for the estimators
    np.testing.assert_array_equal(grey.centre_view(), views[1, 2])
    assert stored.stored_centre is None
    assert grey.metadata.keys() == stored.metadata.keys() and grey.pitch_mm == stored.pitch_mm


def test_a_damaged_view_is_refused_when_read_as_grey_too(tmp_path):
    folder = tmp_path / "cap"
    write_lightfield(folder, LightField(views=random_views(), pitch_mm=0.5))
    view = folder / "views" / "u01_v02.png"
    cv2.imwrite(str(view), random_views(seed=3)[0, 0, :, :, ::-1])
    with pytest.raises(CaptureLayoutError, match="u01_v02.png"):
        read_lightfield(folder, grey=True)


@pytest.mark.parametrize("layout", ["benchmark", "capture"])
def test_a_light_field_read_without_decoding_is_all_but_the_pixels(tmp_path, layout, monkeypatch):
    """``decode=False`` (``lfrig info``) decodes the first view only, gives the same shapes, dtype
    and metadata, and still refuses a view of another size."""
    import recon.lf.imageio as imageio

    views = random_views()
    if layout == "benchmark":
        folder, odd = write_benchmark(tmp_path / "scene", views), "input_Cam005.png"
    else:
        folder, odd = tmp_path / "cap", "views/u01_v02.png"
        write_lightfield(folder, LightField(views=views, pitch_mm=0.5))
    stored = read_lightfield(folder)
    decoded = []
    decode_bytes = imageio._decode_bytes
    monkeypatch.setattr(imageio, "_decode_bytes", lambda *args, **kw: decoded.append(1) or decode_bytes(*args, **kw))
    bare = read_lightfield(folder, decode=False)
    assert len(decoded) == 1 and bare.views.shape == stored.views.shape and bare.views.dtype == stored.views.dtype
    assert not bare.views.any() and not bare.views.flags.writeable and set(bare.views.strides) == {0}
    assert bare.metadata == stored.metadata and bare.pitch_mm == stored.pitch_mm
    cv2.imwrite(str(folder / odd), np.zeros((7, 8, 3), np.uint8))
    with pytest.raises(LfrigError, match=odd.split("/")[-1]):
        read_lightfield(folder, decode=False, verify=False)
