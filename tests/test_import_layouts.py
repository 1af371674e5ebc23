"""``lfrig import`` of other layouts: a flipped or transposed grid, the mirrored-order warning, the
Stanford archive's names, a mosaic image, an HDF5 light field, and a benchmark folder's ground truth."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.lf import read_lightfield
from recon.lf.importer import import_views, order_warnings
from recon.lf.pfm import read_pfm, write_pfm
from rig.main import main
from tests.conftest import SHARED, require_hci_scene

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
TINY = FIXTURES / "tiny_capture"
TRUTH = FIXTURES / "tiny_capture_truth.pfm"
FAST = ["--method", "baseline", "--disparity-range", "-1", "1.5", "--step", "0.25", "--quiet"]


def write_image(path: Path, image: np.ndarray) -> None:
    assert cv2.imwrite(str(path), image[:, :, ::-1] if image.ndim == 3 else image)


def export_as(folder: Path, views: np.ndarray, name_of) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for u in range(views.shape[0]):
        for v in range(views.shape[1]):
            write_image(folder / name_of(u, v), views[u, v])
    return folder


def warnings_in(err: str) -> list[str]:
    """The warnings about the views' order (the one that the capture lacks a focal length is not one)."""
    return [line for line in err.splitlines() if line.startswith("lfrig: warning:") and "only give disparity" not in line]


def one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("lfrig:")]
    assert len(lines) == 1, lines
    return lines[0]


@pytest.fixture(scope="module")
def tiny():
    return read_lightfield(TINY)


# --------------------------------------------------------------------------------------------------
# Flips, transposition and the order check


def test_mirrored_columns_warn_and_flip_v_repairs_them(tmp_path, tiny, capsys):
    src = export_as(tmp_path / "mirrored", tiny.views, lambda u, v: f"view_{u}_{2 - v}.png")
    args = ["import", str(src), "--pattern", "view_{u}_{v}.png", "--rows", "3", "--cols", "3", "--pitch-mm", "0.5",
            "--quiet"]
    assert main([*args, "-o", str(tmp_path / "as_is")]) == 0
    warned = warnings_in(capsys.readouterr().err)
    assert len(warned) == 1 and "mirrored" in warned[0] and "--flip-v" in warned[0] and str(src) in warned[0]
    assert main([*args, "--flip-v", "-o", str(tmp_path / "flipped")]) == 0
    assert warnings_in(capsys.readouterr().err) == []
    assert np.array_equal(read_lightfield(tmp_path / "flipped").views, tiny.views)
    header = json.loads((tmp_path / "flipped" / "manifest.jsonl").read_text().splitlines()[0])
    assert header["imported"]["flip_v"] is True and header["imported"]["flip_u"] is False


def test_flip_u_and_transpose(tmp_path, tiny):
    # a 2x3 grid saved with rows and columns swapped and the (then) columns reversed
    views = tiny.views[:2]
    src = export_as(tmp_path / "swapped", views, lambda u, v: f"img_{v}_{1 - u}.png")
    out = import_views(src, tmp_path / "cap", pattern="img_{u}_{v}.png", rows=3, cols=2, pitch_mm=0.5,
                       transpose=True, flip_u=True, check_order=False)
    back = read_lightfield(out)
    assert back.grid_shape == (2, 3) and np.array_equal(back.views, views)


def test_serpentine_files_read_as_raster_warn(tmp_path, tiny, capsys):
    src = tmp_path / "frames"
    src.mkdir()
    from recon.lf.importer import capture_order

    for i, (u, v) in enumerate(capture_order(3, 3, order="serpentine")):
        write_image(src / f"frame{i:02d}.png", tiny.views[u, v])
    assert main(["import", str(src), "-o", str(tmp_path / "raster"), "--order", "raster", "--rows", "3", "--cols", "3",
                 "--pitch-mm", "0.5", "--quiet"]) == 0
    warned = warnings_in(capsys.readouterr().err)
    assert len(warned) == 1 and "rows of the grid disagree" in warned[0] and "--order" in warned[0]
    assert main(["import", str(src), "-o", str(tmp_path / "serp"), "--order", "serpentine", "--rows", "3", "--cols", "3",
                 "--pitch-mm", "0.5", "--quiet"]) == 0
    assert warnings_in(capsys.readouterr().err) == []


def test_order_check_is_silent_on_a_scene_at_the_focus_plane(tiny):
    flat = {(u, v): tiny.views[1, 1] for u in range(3) for v in range(3)}  # no parallax: nothing to tell
    assert order_warnings(flat, rows=3, cols=3) == []
    assert order_warnings({(0, v): tiny.views[1, v] for v in range(3)}, rows=1, cols=3) == []


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["slanted-v1", "occlusion-v1"])
def test_order_check_on_rendered_scenes(scene):
    lf = read_lightfield(require_hci_scene(SHARED / "data" / "blender-dev" / scene))
    rows, cols = lf.grid_shape
    views = {(u, v): lf.views[u, v] for u in range(rows) for v in range(cols)}
    assert order_warnings(views, rows=rows, cols=cols) == []
    mirrored = {(u, cols - 1 - v): image for (u, v), image in views.items()}
    assert "one axis looks mirrored" in " ".join(order_warnings(mirrored, rows=rows, cols=cols))


# --------------------------------------------------------------------------------------------------
# Stanford names, mosaic, HDF5


def test_stanford_archive_names(tmp_path, tiny, capsys):
    src = export_as(tmp_path / "stanford", tiny.views,
                    lambda u, v: f"out_{u:02d}_{v:02d}_{-780.134705 + 10 * u:.6f}_{-3355.331299 + 10 * v:.6f}_.png")
    (src / "out_00_00_preview.png").write_bytes(b"")  # not a view: ignored
    assert main(["import", str(src), "-o", str(tmp_path / "cap"), "--pattern", "stanford", "--rows", "3", "--cols", "3",
                 "--pitch-mm", "0.5", "--quiet"]) == 0
    assert np.array_equal(read_lightfield(tmp_path / "cap").views, tiny.views)
    # the same by an explicit pattern with its float position fields
    assert main(["import", str(src), "-o", str(tmp_path / "cap2"), "--pattern", "out_{row:02d}_{col:02d}_{y}_{x}_.png",
                 "--rows", "3", "--cols", "3", "--pitch-mm", "0.5", "--quiet"]) == 0
    assert np.array_equal(read_lightfield(tmp_path / "cap2").views, tiny.views)
    capsys.readouterr()
    assert main(["import", str(src), "-o", str(tmp_path / "bad"), "--pattern", "out_{u}_{v}_{y:02d}_{x}_.png",
                 "--rows", "3", "--cols", "3", "--pitch-mm", "0.5", "--quiet"]) == 2
    assert "{y} takes no format" in one_error_line(capsys.readouterr().err)


def test_mosaic(tmp_path, tiny, capsys):
    rows, cols, h, w = tiny.views.shape[:4]
    mosaic = tiny.views.transpose(0, 2, 1, 3, 4).reshape(rows * h, cols * w, 3)
    write_image(tmp_path / "mosaic.png", mosaic)
    assert main(["import", str(tmp_path / "mosaic.png"), "-o", str(tmp_path / "cap"), "--mosaic", "3x3",
                 "--pitch-mm", "0.5", "--quiet"]) == 0
    back = read_lightfield(tmp_path / "cap")
    assert np.array_equal(back.views, tiny.views)
    capsys.readouterr()
    assert main(["import", str(tmp_path / "mosaic.png"), "-o", str(tmp_path / "bad"), "--mosaic", "5x5",
                 "--pitch-mm", "0.5", "--quiet"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "mosaic.png" in line and "5x5" in line and not (tmp_path / "bad").exists()
    assert main(["import", str(tmp_path / "mosaic.png"), "-o", str(tmp_path / "bad"), "--mosaic", "3by3",
                 "--pitch-mm", "0.5"]) == 2
    assert "ROWSxCOLS" in capsys.readouterr().err


def write_h5(path: Path, lf: np.ndarray, **datasets) -> Path:
    import h5py

    with h5py.File(path, "w") as f:
        f.create_dataset("LF", data=lf)
        f.attrs["dH"] = 0.5
        f.attrs["focalLength"] = 1000.0
        f.attrs["shift"] = 0.25
        for name, data in datasets.items():
            f.create_dataset(name, data=data)
    return path


def test_hdf5_light_field_with_ground_truth_scores_like_the_original(tmp_path, tiny, capsys):
    truth = read_pfm(TRUTH)
    h5 = write_h5(tmp_path / "lf.h5", tiny.views, GT_DISP=truth)
    assert main(["import", str(h5), "-o", str(tmp_path / "cap"), "--quiet"]) == 0
    back = read_lightfield(tmp_path / "cap")
    assert np.array_equal(back.views, tiny.views)
    assert (back.pitch_mm, back.focal_px, back.disparity_offset) == (0.5, 1000.0, 0.25)
    assert np.array_equal(read_pfm(tmp_path / "cap" / "gt_disp_lowres.pfm"), truth)
    assert main(["reconstruct", str(tmp_path / "cap"), "-o", str(tmp_path / "rec"), *FAST]) == 0
    assert json.loads((tmp_path / "rec" / "result.json").read_text())["scores"]


def test_hdf5_float_views_and_depth_truth(tmp_path, tiny):
    depth = np.full((32, 32), 400.0)
    h5 = write_h5(tmp_path / "lf.h5", tiny.views.astype(np.float32) / 255, GT_DEPTH=np.broadcast_to(depth, (3, 3, 32, 32)))
    import_views(h5, tmp_path / "cap", check_order=False)
    back = read_lightfield(tmp_path / "cap")
    assert back.views.dtype == np.uint16 and np.array_equal(np.round(back.views / 257.0), tiny.views)
    # disparity = focalLength * dH / depth - shift
    assert np.allclose(read_pfm(tmp_path / "cap" / "gt_disp_lowres.pfm"), 1000.0 * 0.5 / 400.0 - 0.25)


def test_bad_hdf5(tmp_path, tiny, capsys):
    import h5py

    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.create_dataset("views", data=tiny.views)
    (tmp_path / "broken.h5").write_bytes(b"not hdf5")
    for name, expected in (("other.h5", "no dataset 'LF'"), ("broken.h5", "not a readable HDF5 file")):
        assert main(["import", str(tmp_path / name), "-o", str(tmp_path / "cap"), "--quiet"]) == 2
        line = one_error_line(capsys.readouterr().err)
        assert name in line and expected in line and not (tmp_path / "cap").exists()


# --------------------------------------------------------------------------------------------------
# Benchmark folders keep their ground truth


def test_benchmark_folder_keeps_ground_truth_and_scores(tmp_path, tiny):
    bench = export_as(tmp_path / "bench", tiny.views, lambda u, v: f"input_Cam{u * 3 + v:03d}.png")
    shutil.copyfile(TINY / "parameters.cfg", bench / "parameters.cfg")
    shutil.copyfile(TRUTH, bench / "gt_disp_lowres.pfm")
    write_pfm(bench / "gt_depth_lowres.pfm", np.full((32, 32), 7.0, np.float32))
    out = import_views(bench, tmp_path / "cap")
    assert read_lightfield(out).metadata["ground_truth"] == str(out / "gt_disp_lowres.pfm")
    assert (out / "gt_depth_lowres.pfm").read_bytes() == (bench / "gt_depth_lowres.pfm").read_bytes()
    scores = []
    for lf_dir, rec in ((bench, tmp_path / "rec_a"), (out, tmp_path / "rec_b")):
        assert main(["reconstruct", str(lf_dir), "-o", str(rec), *FAST]) == 0
        scores.append(json.loads((rec / "result.json").read_text())["scores"])
    assert scores[0] and scores[0] == scores[1]


def test_reorienting_a_grid_with_ground_truth_is_refused_when_it_moves_the_truth(tmp_path, tiny, capsys):
    truth = read_pfm(TRUTH)
    h5 = write_h5(tmp_path / "lf.h5", tiny.views, GT_DISP=truth)
    assert main(["import", str(h5), "-o", str(tmp_path / "t"), "--transpose", "--quiet"]) == 2
    assert "ground truth" in one_error_line(capsys.readouterr().err) and not (tmp_path / "t").exists()
    # an odd grid's flip keeps the centre view where it is: allowed
    assert main(["import", str(h5), "-o", str(tmp_path / "f"), "--flip-v", "--no-order-check", "--quiet"]) == 0
    assert np.array_equal(read_lightfield(tmp_path / "f").views, tiny.views[:, ::-1])
    even = write_h5(tmp_path / "even.h5", np.ascontiguousarray(tiny.views[:2, :2]), GT_DISP=truth)
    assert main(["import", str(even), "-o", str(tmp_path / "e"), "--flip-v", "--quiet"]) == 2
    assert "even grid side" in one_error_line(capsys.readouterr().err)
