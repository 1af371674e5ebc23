"""Issue #13, points 7, 8 and 10: every example of the issue, as a regression test.

A user's mistake through the command line is one line on stderr starting ``lfrig: error:``, exit
status 2, no traceback; through the library it is an :class:`recon.errors.LfrigError` naming the
file or value. Bad values are refused, not used. Messages say what is wrong in lfrig's words only
(no libpng/OpenCV lines before them).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from recon.errors import LfrigError
from recon.lf.imageio import write_png
from recon.lf.pfm import write_pfm
from rig.main import main

ROOT = Path(__file__).resolve().parents[1]
TINY_CAPTURE = ROOT / "fixtures" / "tiny_capture"
TRUTH = ROOT / "fixtures" / "tiny_capture_truth.pfm"
BASELINE = ["--method", "baseline", "--window", "3", "--step", "0.1", "--quiet"]


def one_line_error(capsys_or_fd, status: int, *needles: str) -> str:
    """Assert exit 2 and exactly one non-empty stderr line, lfrig's, containing every needle."""
    err = capsys_or_fd.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2, err
    assert len(lines) == 1 and lines[0].startswith("lfrig: error:"), err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def capture(tmp_path) -> Path:
    shutil.copytree(TINY_CAPTURE, tmp_path / "cap")
    return tmp_path / "cap"


@pytest.fixture
def result_dir(tmp_path, capture) -> Path:
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    return tmp_path / "res"


def rewrite_manifest(capture: Path, edit) -> None:
    lines = (capture / "manifest.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    edit(records)
    (capture / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


# --------------------------------------------------------------------------------------------------
# point 7: tracebacks on bad input, through the CLI


@pytest.mark.parametrize("edit, needle", [
    # a view record without integer u, v names no view: ignored (the integrity work's rule), so the
    # capture reads as incomplete, with the view it lacks named
    (lambda r: r[3].pop("u"), "views/u00_v02.png"),
    (lambda r: r[3].update(u="1"), "views/u00_v02.png"),
    (lambda r: r[3].update(v=[0]), "views/u00_v02.png"),
    (lambda r: r[3].update(file=7), "u00_v02"),
    (lambda r: r[0].update(grid=[3, 3]), "manifest.jsonl: header has no valid grid"),
    (lambda r: r[0]["grid"].update(rows=100000), "manifest.jsonl: header has no valid grid"),
    (lambda r: r[0]["grid"].update(pitch_mm="0.5"), "manifest.jsonl: header grid pitch_mm"),
    (lambda r: r[0]["grid"].update(pitch_mm=-0.5), "manifest.jsonl: header grid pitch_mm"),
])
def test_manifest_fields_of_the_wrong_type_or_missing(capture, capsys, edit, needle):
    rewrite_manifest(capture, edit)
    one_line_error(capsys, main(["info", str(capture)]), needle)


def test_non_utf8_journal(capture, capsys):
    data = (capture / "manifest.jsonl").read_bytes().replace(b'"kind": "view"', b'"kind": "vi\xffew"', 1)
    (capture / "manifest.jsonl").write_bytes(data)
    one_line_error(capsys, main(["info", str(capture)]), "manifest.jsonl: line 2 is not UTF-8")


def test_huge_num_cams_is_refused_not_allocated(tmp_path, capsys):
    scene = tmp_path / "scene"
    scene.mkdir()
    for i in range(9):
        write_png(scene / f"input_Cam{i:03d}.png", np.zeros((8, 8), np.uint8))
    (scene / "parameters.cfg").write_text("[extrinsics]\nnum_cams_x = 100000\nnum_cams_y = 3\n")
    one_line_error(capsys, main(["info", str(scene)]), "num_cams_x = 100000", "1 to 1024")


@pytest.mark.parametrize("step, needle", [("1e-9", "finer than"), ("inf", "argument --step"),
                                          ("nan", "argument --step"), ("-1", "argument --step")])
def test_step_too_fine_or_not_finite(capture, tmp_path, capsys, step, needle):
    status = main(["reconstruct", str(capture), "-o", str(tmp_path / "r"), "--method", "baseline", "--step", step,
                   "--quiet"])
    one_line_error(capsys, status, needle)
    assert not (tmp_path / "r" / "disparity.pfm").exists()


def test_output_naming_a_file(capture, tmp_path, capsys):
    (tmp_path / "afile").write_text("mine")
    status = main(["reconstruct", str(capture), "-o", str(tmp_path / "afile"), *BASELINE])
    one_line_error(capsys, status, "afile", "is a file")
    assert (tmp_path / "afile").read_text() == "mine"


def test_output_naming_a_file_through_the_library(capture, tmp_path):
    from recon.errors import OutputPathError
    from recon.pipeline import reconstruct_to_folder

    (tmp_path / "afile").write_text("mine")
    with pytest.raises(OutputPathError, match="is a file"):
        reconstruct_to_folder(capture, tmp_path / "afile", method="baseline", options={"window": 3})


def _fail_writes_under(monkeypatch, folder: Path, code: int) -> None:
    """Make every file creation under ``folder`` fail with ``code`` (a read-only or full filesystem),
    at the level every writer goes through: ``os.open`` and ``open``/``io.open`` for writing."""
    import builtins
    import io

    folder = Path(folder).resolve()
    real_os_open, real_open = os.open, builtins.open

    def under(path) -> bool:
        try:
            return Path(os.fsdecode(path)).resolve().is_relative_to(folder)
        except (TypeError, ValueError):
            return False

    def os_open(path, flags, *args, **kwargs):
        if under(path) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(code, os.strerror(code), os.fsdecode(path))
        return real_os_open(path, flags, *args, **kwargs)

    def fake_open(file, mode="r", *args, **kwargs):
        if isinstance(file, (str, bytes, os.PathLike)) and under(file) and any(c in mode for c in "wax+"):
            raise OSError(code, os.strerror(code), os.fsdecode(file))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(io, "open", fake_open)


@pytest.mark.parametrize("code, needle", [(errno.EROFS, "read-only"), (errno.ENOSPC, "disk is full")])
def test_read_only_or_full_output_is_one_line_before_the_work(capture, tmp_path, capsys, monkeypatch, code, needle):
    out = tmp_path / "out"
    out.mkdir()
    _fail_writes_under(monkeypatch, out, code)
    import recon.pipeline

    monkeypatch.setattr(recon.pipeline, "run_in_process", lambda *a, **k: pytest.fail("the estimate started"))
    one_line_error(capsys, main(["reconstruct", str(capture), "-o", str(out / "r"), *BASELINE]), str(out), needle)


def test_read_only_output_in_any_command_is_one_line(result_dir, tmp_path, capsys, monkeypatch):
    """An OSError the library does not check for itself (here: export's PLY) still reaches the user as
    one line naming the path."""
    out = tmp_path / "ro"
    out.mkdir()
    _fail_writes_under(monkeypatch, out, errno.EROFS)
    status = main(["export", str(result_dir), "--depth", str(out / "d.pfm")])
    one_line_error(capsys, status, str(out))


def test_an_oserror_without_a_user_path_keeps_its_traceback(monkeypatch):
    import recon.cli

    def broken(args):
        raise OSError(errno.EBADF, "Bad file descriptor")  # no path: a bug, not a user's mistake

    monkeypatch.setattr(recon.cli, "_info", broken)
    with pytest.raises(OSError):
        main(["info", "."])


def test_calibrate_intrinsics_checks_its_output_before_the_solve(tmp_path, capsys, monkeypatch):
    import calib.intrinsics

    monkeypatch.setattr(calib.intrinsics, "calibrate_intrinsics_from_images",
                        lambda *a, **k: pytest.fail("the solve started before the output was checked"))
    out = tmp_path / "ro"
    out.mkdir()
    _fail_writes_under(monkeypatch, out, errno.EROFS)
    image = tmp_path / "board.png"
    write_png(image, np.zeros((16, 16), np.uint8))
    status = main(["calibrate", "intrinsics", str(image), "--board", "9x6", "--square-mm", "8",
                   "-o", str(out / "cam.cameramodel")])
    one_line_error(capsys, status, str(out), "read-only")


def _stage_json(tmp_path, **changes) -> Path:
    record = {"format": "lfrig-stage-calibration", "version": 1, "grid": [9, 9], "pitch_mm": 0.5,
              "step_u_mm": [0, 0.5, 0], "step_v_mm": [0.5, 0, 0], "r_cam_board": [0, 0, 0],
              "t_cam_board_mm": [0, 0, 1000], "rms_px": 0.1, "max_px": 0.3, "n_views": 81, "n_corners": 100,
              "n_outliers": 0}
    from calib import stage

    record["format"], record["version"] = stage.FORMAT, stage.VERSION
    record.update(changes)
    path = tmp_path / "stage.json"
    path.write_text(json.dumps(record))
    return path


@pytest.mark.parametrize("changes, needle", [
    ({"grid": 9}, "malformed"),
    ({"step_u_mm": [0, 0.5]}, "step_u_mm"),
    ({"step_u_mm": "up"}, "malformed"),
    ({"step_v_mm": [0, 0.5, 0]}, "parallel"),
    ({"pitch_mm": -0.5}, "pitch_mm"),
    ({"rms_px": float("nan")}, "rms_px"),
    ({"n_views": "81"}, "n_views"),
    ({"surprise": 1}, "malformed"),
])
def test_malformed_stage_json(tmp_path, changes, needle):
    from calib.errors import CalibError
    from calib.stage import StageCalibration

    path = _stage_json(tmp_path, **changes)
    with pytest.raises(CalibError, match=needle):
        StageCalibration.load(path)
    StageCalibration.load(_stage_json(tmp_path))  # the unchanged record loads


def test_zero_focal_camera_model_through_rectify(tmp_path, capture, capsys):
    import mrcal

    model = mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([0.0, 0.0, 15.5, 15.5])),
                              imagersize=np.array([32, 32]), extrinsics_rt_fromref=np.zeros(6))
    model.write(str(tmp_path / "zero.cameramodel"))
    status = main(["rectify", str(capture), "--model", str(tmp_path / "zero.cameramodel"),
                   "--stage", str(_stage_json(tmp_path)), "-o", str(tmp_path / "rect")])
    one_line_error(capsys, status, "zero.cameramodel", "focal lengths")


@pytest.mark.parametrize("argv, needle", [
    (["capture", "{tmp}/c", "--feed-mm-min", "0"], "--feed-mm-min"),
    (["capture", "{tmp}/c", "--binning", "100000"], "binning 100000"),
    (["capture", "{tmp}/c", "--backlash-mm", "nan"], "--backlash-mm"),
    (["capture", "{tmp}/c", "--pitch-mm", "-0.5", "--dry-run"], "--pitch-mm"),
    (["capture", "{tmp}/c", "--pitch-mm", "0", "--dry-run"], "--pitch-mm"),
    (["capture", "{tmp}/c", "--settle-s", "-1"], "--settle-s"),
    (["capture", "{tmp}/afile"], "is a file"),
    (["batch", "reconstruct", "{cap}", "-o", "{tmp}/b", "--scheduler", "garbage"], "garbage"),
    (["export", "{res}", "--ply", "{tmp}/x.ply", "--focal-px", "-100"], "--focal-px"),
    (["export", "{res}", "--ply", "{tmp}/x.ply", "--pitch-mm", "0"], "--pitch-mm"),
    (["evaluate", "{truth}", "{truth}", "--border", "-1"], "--border"),
    (["demo", "--binning", "100000", "-o", "{tmp}/demo"], "--binning"),
    (["calibrate", "intrinsics", "{tmp}/x.png", "--board", "0x0", "--square-mm", "8", "-o", "{tmp}/m"], "--board"),
    (["calibrate", "intrinsics", "{tmp}/x.png", "--board", "9x6", "--square-mm", "nan", "-o", "{tmp}/m"],
     "--square-mm"),
])
def test_bad_flag_values_are_one_line(tmp_path, capture, result_dir, capsys, argv, needle):
    (tmp_path / "afile").write_text("mine")
    values = {"tmp": tmp_path, "cap": capture, "res": result_dir, "truth": TRUTH}
    one_line_error(capsys, main([a.format(**values) for a in argv]), needle)


# --------------------------------------------------------------------------------------------------
# point 8: bad values accepted silently


@pytest.mark.parametrize("section, key, value", [
    ("extrinsics", "baseline_mm", "-0.5"), ("extrinsics", "baseline_mm", "0"),
    ("lfrig", "focal_px", "0"), ("lfrig", "focal_px", "-1000"),
    ("extrinsics", "focus_distance_m", "0"), ("extrinsics", "focus_distance_m", "-1"),
    ("lfrig", "principal_x_px", "nan"),
])
def test_non_positive_pitch_focal_focus_or_nan_principal_point(capture, capsys, section, key, value):
    text = (capture / "parameters.cfg").read_text()
    if f"{key} =" in text:
        text = "\n".join(f"{key} = {value}" if line.startswith(f"{key} =") else line for line in text.splitlines())
    else:
        text = text.replace(f"[{section}]\n", f"[{section}]\n{key} = {value}\n")
    (capture / "parameters.cfg").write_text(text)
    one_line_error(capsys, main(["info", str(capture)]), "parameters.cfg", key)


def test_nan_principal_point_in_result_json_gives_no_ply(result_dir, tmp_path, capsys):
    record = json.loads((result_dir / "result.json").read_text())
    record["principal_point_px"] = [float("nan"), 15.5]
    (result_dir / "result.json").write_text(json.dumps(record))
    one_line_error(capsys, main(["export", str(result_dir), "--ply", str(tmp_path / "x.ply")]), "principal_point_px")
    assert not (tmp_path / "x.ply").exists()


@pytest.mark.parametrize("scale", [b"nan", b"inf", b"-inf", b"0"])
def test_pfm_scale_must_be_a_finite_non_zero_number(tmp_path, scale):
    from recon.lf.pfm import read_pfm

    path = tmp_path / "x.pfm"
    path.write_bytes(b"Pf\n2 2\n" + scale + b"\n" + bytes(16))
    with pytest.raises(LfrigError, match="broken PFM header"):
        read_pfm(path)


def test_all_nan_estimate_is_an_error_not_mse_nan(tmp_path, capsys):
    write_pfm(tmp_path / "nan.pfm", np.full((64, 64), np.nan, np.float32))
    write_pfm(tmp_path / "gt.pfm", np.zeros((64, 64), np.float32))
    status = main(["evaluate", str(tmp_path / "nan.pfm"), str(tmp_path / "gt.pfm")])
    one_line_error(capsys, status, "nothing to score", "nan.pfm")
    assert "MSE" not in capsys.readouterr().out


def test_backlash_nan_is_refused_by_the_grid():
    from rig.grid import GridError, GridSpec

    with pytest.raises(GridError, match="backlash_mm"):
        GridSpec(backlash_mm=float("nan"))
    with pytest.raises(GridError, match="pitch"):
        GridSpec(pitch_mm=float("inf"))


def test_capture_session_values_are_checked_before_anything_moves(tmp_path):
    from rig.errors import RigError
    from rig.grid import GridSpec
    from rig.session import run_capture

    class Untouchable:
        def __getattr__(self, name):
            pytest.fail(f"the device was used ({name}) before the values were checked")

    for bad in ({"feed_mm_min": 0.0}, {"feed_mm_min": float("nan")}, {"settle_s": -1.0}, {"tolerance_mm": 0.0}):
        with pytest.raises(RigError):
            run_capture(tmp_path / "c", stage=Untouchable(), camera=Untouchable(), grid=GridSpec(), **bad)


# --------------------------------------------------------------------------------------------------
# point 10: unclear messages


def test_damaged_png_is_lfrigs_one_line_without_libpng_or_opencv_lines(capture, capfd):
    view = capture / "views" / "u01_v01.png"
    data = bytearray(view.read_bytes())
    data[60] ^= 0xFF  # inside the image data
    view.write_bytes(bytes(data))
    one_line_error(capfd, main(["info", str(capture)]), "u01_v01.png", "damaged")


def test_truncated_png_is_lfrigs_one_line(capture, capfd):
    view = capture / "views" / "u02_v00.png"
    view.write_bytes(view.read_bytes()[:100])
    one_line_error(capfd, main(["info", str(capture)]), "u02_v00.png", "truncated")


def test_three_channel_ground_truth_says_channels(tmp_path, capsys):
    write_pfm(tmp_path / "est.pfm", np.zeros((64, 64), np.float32))
    write_pfm(tmp_path / "gt.pfm", np.zeros((64, 64, 3), np.float32))
    line = one_line_error(capsys, main(["evaluate", str(tmp_path / "est.pfm"), str(tmp_path / "gt.pfm")]),
                          "gt.pfm", "3 channels")
    assert "64x64 but ground truth is 64x64" not in line


def test_score_names_channels_and_sizes():
    from recon.evaluate import score

    with pytest.raises(LfrigError, match="64x64 with 3 channels"):
        score(np.zeros((64, 64), np.float32), np.zeros((64, 64, 3), np.float32))
    with pytest.raises(LfrigError, match="estimate is 64x32 but ground truth is 64x64"):
        score(np.zeros((32, 64), np.float32), np.zeros((64, 64), np.float32))
    with pytest.raises(LfrigError, match="border"):
        score(np.zeros((64, 64), np.float32), np.zeros((64, 64), np.float32), border=-1)
