"""Fault sweeps (issue #13): kill -9 and a full disk at every write of capture, rectify, reconstruct,
export and calibrate.

Every file lfrig writes goes through one place (``recon.lf.imageio``: ``write_bytes_atomic``,
``atomic_output``, and the journal's append), which counts its writes and, when the environment asks
(``LFRIG_FAULT=kill:N`` / ``enospc:N``), kills the process with SIGKILL half-way through the N-th
write or fails it with ``OSError(ENOSPC)``. Each sweep first counts a command's writes, then for
every N runs the command in a forked child (the modules are loaded and compiled once, so a run costs
milliseconds, not an interpreter start) with the fault at N, and checks:

- after the fault: every file under its final name is complete (a PNG decodes, a PFM/NPY/PLY holds
  what its header says, JSON parses, the camera model loads), a capture journal has no damaged line
  and a capture that says it is complete reads back with all checksums right; a reconstruction
  folder with ``result.json`` holds every map it lists. Anything else is clearly incomplete (no
  ``complete`` record, no ``result.json``) or the previous complete state;
- a full disk is one line on stderr naming the file, exit 2, no traceback;
- the same command run again (no fault) repairs or resumes: it succeeds, and its output equals a run
  that never failed.

Real filesystems: a small tmpfs is mounted where the test may (root, Linux) for a capture and a PLY
export that really run out of space; elsewhere those two tests inject ENOSPC instead. One capture is
also killed from outside (``kill -9`` of the real ``lfrig`` process after its n-th view appears).
Everything is seeded (the fake camera is deterministic) and small (binning 8, 3x3 grids).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

import recon.lf.imageio as imageio
from recon.lf.capture import MANIFEST, _journal_lines, read_capture
from rig.main import main

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"
CAPTURE = ["--rows", "3", "--cols", "3", "--binning", "8", "--supersample", "1", "--quiet", "--settle-s", "0"]
CHILD_TIMEOUT_S = 120.0


def lfrig(args: list) -> int:
    """``lfrig ARGS`` here, in this process."""
    return main([str(a) for a in args])


# --------------------------------------------------------------------------------------------------
# running a command with a fault
# --------------------------------------------------------------------------------------------------


class Runner:
    """The helper process of ``tests/fault_runner.py``: ``run(args, fault=...)`` forks a child there."""

    def __init__(self) -> None:
        env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue", "PYTHONPATH": str(ROOT)}
        for key in (imageio.FAULT_ENV, imageio.FAULT_LOG_ENV):
            env.pop(key, None)
        self.proc = subprocess.Popen([sys.executable, str(ROOT / "tests" / "fault_runner.py")], cwd=ROOT, env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def ask(self, request: dict) -> dict:
        self.proc.stdin.write(json.dumps(request, default=str) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            pytest.fail("the fault runner died")
        answer = json.loads(line)
        if answer["status"] in ("timeout", "error", "unknown request"):
            pytest.fail(f"fault runner: {request}: {answer}")
        return answer

    def run(self, args, *, fault: str | None = None, log: Path | None = None) -> dict:
        return self.ask({"run": [str(a) for a in args], "fault": fault, "log": str(log) if log else None})

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=60)
        self.proc.stdout.close()


@pytest.fixture(scope="module")
def runner():
    r = Runner()
    yield r
    r.close()


def count_writes(runner: Runner, args: list, tmp_path: Path) -> list[str]:
    """The files a command writes, in order (one entry per write, through the hook's log)."""
    log = tmp_path / f"writes-{uuid.uuid4().hex}.log"
    answer = runner.run(args, log=log)
    assert answer["status"] == 0, answer
    return [line.split("\t", 1)[1] for line in log.read_text().splitlines()]


def sweep(runner, args, tmp_path, *, reset, check, compare, min_writes):
    """For each write N of ``lfrig ARGS`` and each fault: reset the folders, run with the fault,
    check the state, run again without a fault and compare with the clean run."""
    reset()
    assert runner.ask({"warm": [str(a) for a in args]})["status"] == 0  # compile before forking
    reset()
    writes = count_writes(runner, args, tmp_path)
    assert len(writes) >= min_writes, writes
    reference = compare()
    for number in range(1, len(writes) + 1):
        for mode in ("kill", "enospc"):
            reset()
            answer = runner.run(args, fault=f"{mode}:{number}")
            status, err = answer["status"], answer["err"]
            where = f"{mode} at write {number} of {len(writes)} ({writes[number - 1]})"
            if mode == "kill":
                assert status == -signal.SIGKILL, f"{where}: exit {status}\n{err}"
            else:
                assert status == 2, f"{where}: exit {status}\n{err}"
                lines = [line for line in err.splitlines() if line.startswith("lfrig: ")]
                assert len(lines) == 1 and "No space left on device" in lines[0], f"{where}: {err}"
                assert "Traceback" not in err, f"{where}: {err}"
            check(where)
            again = runner.run(args)
            assert again["status"] == 0, f"{where}: the rerun failed\n{again['err']}"
            assert compare() == reference, f"{where}: the rerun differs from a clean run"
    return writes


# --------------------------------------------------------------------------------------------------
# what "complete" means, per file
# --------------------------------------------------------------------------------------------------


def ply_is_complete(path: Path) -> None:
    from recon.export import _check_ply

    data = path.read_bytes()
    head = data[: data.find(b"end_header")].decode("ascii")
    counts = {line.split()[1]: int(line.split()[2]) for line in head.splitlines() if line.startswith("element")}
    _check_ply(path, path, vertices=counts.get("vertex", 0), faces=counts.get("face", 0), ascii="ascii" in head)


#: Where the report's scripts and licence are copied from.
REPORT_PACKAGE = Path(__file__).resolve().parents[1] / "recon" / "report"


def file_is_complete(path: Path) -> None:
    """Raise (an assertion or the reader's error) unless ``path`` holds a whole file of its kind."""
    suffix = path.suffix.lower()
    if suffix == ".png":
        assert imageio.read_image(path).size > 0
    elif suffix == ".pfm":
        from recon.lf.pfm import read_pfm

        read_pfm(path)
    elif suffix == ".npy":
        np.load(path)
    elif suffix == ".json":
        json.loads(path.read_text())
    elif suffix == ".ply":
        ply_is_complete(path)
    elif suffix == ".html":
        assert path.read_text().rstrip().endswith("</html>"), path
    elif suffix == ".cfg":
        from recon.lf.params import read_parameters

        read_parameters(path)
    elif suffix == ".cameramodel":
        import mrcal

        mrcal.cameramodel(str(path))
    elif suffix in (".log", ".lock", ".jsonl"):
        pass
    elif suffix in (".js", ".txt") and path.parent.name == "report":  # the 3D view's scripts and licence
        from recon.report.model import MODEL_JS

        text = path.read_bytes()
        if path.name == MODEL_JS:
            assert text.startswith(b"window.LFRIG_MODEL = ") and text.endswith(b";\n"), path
        else:
            sources = [p for p in (REPORT_PACKAGE / path.name, REPORT_PACKAGE / "vendor" / path.name) if p.is_file()]
            assert sources and text == sources[0].read_bytes(), path
    else:
        raise AssertionError(f"{path}: unexpected file")


def visible_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts))


def restore_and_check(previous: Path, out: Path):
    """``(reset, check)`` for :func:`sweep`: ``reset()`` puts a copy of the complete ``previous``
    folder at ``out``; ``check(where)`` asserts that every visible file under ``out`` is whole."""

    def reset():
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(previous, out)

    def check(where):
        for file in visible_files(out):
            file_is_complete(file)

    return reset, check


def check_capture_folder(folder: Path, where: str) -> None:
    """A capture after a fault: its files are whole, its journal undamaged; complete only if it is."""
    for file in visible_files(folder):
        file_is_complete(file)
    if not (folder / MANIFEST).exists():
        return  # nothing journalled yet: clearly not a capture, a rerun starts afresh
    lines, _ = _journal_lines(folder / MANIFEST)
    records = [json.loads(line) for _, line in lines]  # every complete line is JSON
    if records and records[-1].get("kind") == "complete":
        read_capture(folder)  # says complete: must be, checksums and all
    else:
        from recon.errors import CaptureLayoutError

        with pytest.raises(CaptureLayoutError, match="incomplete"):
            read_capture(folder)


def views_digest(folder: Path) -> str:
    lf = read_capture(folder)
    return hashlib.sha256(lf.views.tobytes()).hexdigest() + f" {lf.pitch_mm} {lf.focal_px}"


# --------------------------------------------------------------------------------------------------
# the sweeps
# --------------------------------------------------------------------------------------------------


def test_capture_survives_a_kill_or_full_disk_at_every_write(tmp_path, runner):
    out = tmp_path / "cap"
    args = ["capture", out, *CAPTURE]
    writes = sweep(
        runner, args, tmp_path,
        reset=lambda: shutil.rmtree(out, ignore_errors=True),
        check=lambda where: check_capture_folder(out, where),
        compare=lambda: views_digest(out),
        min_writes=3 * 3 * 2 + 3,  # header, a view and its journal line each, parameters, complete
    )
    assert sum(w.endswith(".png") for w in writes) == 9 and sum(w.endswith(MANIFEST) for w in writes) == 11


def test_a_resume_after_a_fault_in_the_middle_takes_only_what_is_missing(tmp_path, runner):
    out = tmp_path / "cap"
    # write 1 is the header, then view k is its PNG (write 2k) and its journal line (2k + 1)
    assert runner.run(["capture", out, *CAPTURE], fault="kill:11")["status"] == -signal.SIGKILL
    torn = (out / MANIFEST).read_bytes()
    assert not torn.endswith(b"\n")  # the fault really tore the line
    again = runner.run(["capture", out, *CAPTURE])
    assert again["status"] == 0 and "(5 taken now), complete" in again["out"], again
    lines, end = _journal_lines(out / MANIFEST)
    assert end == (out / MANIFEST).stat().st_size and [json.loads(line)["kind"] for _, line in lines].count("view") == 9


def test_reconstruct_survives_a_kill_or_full_disk_at_every_write(tmp_path, runner):
    out = tmp_path / "res"
    previous = tmp_path / "previous"
    assert lfrig(["reconstruct", FIXTURES / "tiny_capture", "-o", previous, "--method", "baseline", "--window", "3",
                 "--quiet", "--ply", previous / "model.ply"]) == 0
    args = ["reconstruct", FIXTURES / "tiny_capture", "-o", out, "--method", "baseline", "--window", "5", "--quiet",
            "--ply", out / "model.ply"]

    # a complete previous result (other options) is in the folder when the fault comes
    reset, every_file_complete = restore_and_check(previous, out)

    def check(where):
        from recon.result import read_result

        every_file_complete(where)
        if (out / "result.json").exists():
            record = json.loads((out / "result.json").read_text())
            read_result(out)
            assert all((out / name).is_file() for name in record["files"] if name != "model.ply"), where

    def compare():
        record = json.loads((out / "result.json").read_text())
        return (sorted(p.name for p in visible_files(out)), record["options"],
                hashlib.sha256((out / "disparity.pfm").read_bytes()).hexdigest())

    sweep(runner, args, tmp_path, reset=reset, check=check, compare=compare, min_writes=5)


def test_export_survives_a_kill_or_full_disk_at_every_write(tmp_path, runner):
    result = tmp_path / "res"
    assert lfrig(["reconstruct", FIXTURES / "tiny_capture", "-o", result, "--method", "baseline", "--window", "5",
                 "--quiet"]) == 0
    out = tmp_path / "export"
    args = ["export", result, "--ply", out / "model.ply", "--points", "--depth", out / "depth.png",
            "--depth", out / "depth.pfm", "--depth", out / "depth.npy", "--report", out / "report"]
    previous = tmp_path / "previous"
    previous.mkdir()
    assert lfrig(["export", result, "--ply", previous / "model.ply", "--depth", previous / "depth.png",
                 "--depth", previous / "depth.pfm", "--depth", previous / "depth.npy",
                 "--report", previous / "report"]) == 0

    reset, check = restore_and_check(previous, out)

    def compare():
        return sorted((p.relative_to(out).as_posix(), hashlib.sha256(p.read_bytes()).hexdigest())
                      for p in visible_files(out) if p.suffix != ".html")

    sweep(runner, args, tmp_path, reset=reset, check=check, compare=compare, min_writes=6)


def _pinhole_model(path: Path, *, width=160, height=122, focal_px=400.0) -> None:
    import mrcal

    model = mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([focal_px, focal_px, (width - 1) / 2,
                                                                         (height - 1) / 2])),
                              imagersize=np.array([width, height]))
    model.write(str(path))


def _stage(pitch_mm=0.5):
    sys.path.insert(0, str(ROOT / "tests"))
    try:
        from fault_runner import stage
    finally:
        sys.path.pop(0)
    return stage(pitch_mm)


def test_rectify_survives_a_kill_or_full_disk_at_every_write(tmp_path, runner):
    capture = tmp_path / "cap"
    assert lfrig(["capture", capture, *CAPTURE]) == 0
    model, stage = tmp_path / "cam.cameramodel", tmp_path / "stage.json"
    _pinhole_model(model)
    _stage().save(stage)
    out = tmp_path / "rect"
    args = ["rectify", capture, "--model", model, "--stage", stage, "-o", out]
    sweep(runner, args, tmp_path,
          reset=lambda: shutil.rmtree(out, ignore_errors=True),
          check=lambda where: check_capture_folder(out, where),
          compare=lambda: views_digest(out), min_writes=21)


def test_calibrate_survives_a_kill_or_full_disk_at_every_write(tmp_path, runner):
    """The calibration commands' writes (camera model, residual picture, stage.json). In the runner the
    solves are replaced by their results (``fault_runner.stand_in_calibration``: a pinhole model, a
    stage geometry): what is swept here is the writing; the solves have their tests in test_calib.py."""
    import cv2

    from calib.stage import load_model

    assert runner.ask({"stand_in": "calibrate"})["status"] == 0
    model_source = tmp_path / "source.cameramodel"
    _pinhole_model(model_source)
    board = tmp_path / "boards" / "board.png"
    board.parent.mkdir()
    cv2.imwrite(str(board), np.zeros((122, 160), np.uint8))
    out = tmp_path / "calib"
    previous = tmp_path / "previous"
    previous.mkdir()
    _pinhole_model(previous / "cam.cameramodel", focal_px=300.0)
    _stage(0.4).save(previous / "stage.json")
    shutil.copy(board, previous / "cam.residuals.png")

    reset, check = restore_and_check(previous, out)

    def compare():
        return sorted((p.name, hashlib.sha256(p.read_bytes()).hexdigest()) for p in visible_files(out)
                      if p.suffix != ".cameramodel") + [load_model(out / "cam.cameramodel").intrinsics()[1].tolist()]

    sweep(runner, ["calibrate", "intrinsics", board, "--board", "9x6", "--square-mm", "8", "-o", out / "cam.cameramodel",
                   "--quiet"], tmp_path, reset=reset, check=check, compare=compare, min_writes=2)
    sweep(runner, ["calibrate", "stage", board.parent, "--model", model_source, "--board", "10x7", "--square-mm", "10",
                   "-o", out / "stage.json", "--quiet"], tmp_path, reset=reset, check=check, compare=compare,
          min_writes=1)


# --------------------------------------------------------------------------------------------------
# a real full filesystem, and a kill from outside
# --------------------------------------------------------------------------------------------------


@pytest.fixture
def small_fs(tmp_path):
    """``mount(size_kib)``: a tmpfs of that size at a fresh folder, or ``None`` where mounting is not
    allowed (not root, not Linux, a container without the capability): the test then injects ENOSPC."""
    mounted: list[Path] = []

    def mount(size_kib: int) -> Path | None:
        folder = tmp_path / f"fs{len(mounted)}"
        folder.mkdir()
        if not sys.platform.startswith("linux") or os.geteuid() != 0 or shutil.which("mount") is None:
            return None
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(folder)],
                              capture_output=True, timeout=30)
        if done.returncode != 0:
            return None
        mounted.append(folder)
        return folder

    yield mount
    for folder in mounted:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True, timeout=30)


def _grow(folder: Path, size_kib: int) -> None:
    subprocess.run(["mount", "-o", f"remount,size={size_kib}k", str(folder)], check=True, timeout=30)


def test_a_capture_onto_a_full_filesystem_stops_clearly_and_resumes(tmp_path, small_fs, capfd, monkeypatch):
    fs = small_fs(64)  # a 160x122 view is ~35 KiB as PNG: the disk fills within the first views
    root = fs if fs is not None else tmp_path
    out = root / "cap"
    if fs is None:
        monkeypatch.setenv(imageio.FAULT_ENV, "enospc:6")
        monkeypatch.setattr(imageio, "_writes", 0)
    assert lfrig(["capture", str(out), *CAPTURE]) == 2
    err = capfd.readouterr().err
    assert "No space left on device" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    check_capture_folder(out, "full disk")
    if fs is not None:
        _grow(fs, 8192)
    else:
        monkeypatch.delenv(imageio.FAULT_ENV)
    assert lfrig(["capture", str(out), *CAPTURE]) == 0
    assert read_capture(out).grid_shape == (3, 3)


def test_a_ply_export_onto_a_full_filesystem_is_an_error_and_leaves_the_old_file(tmp_path, small_fs, capfd,
                                                                                   monkeypatch):
    """The probe's case: open3d wrote 65,536 of 372,364 bytes and reported success."""
    result = tmp_path / "res"
    assert lfrig(["reconstruct", FIXTURES / "tiny_capture", "-o", result, "--method", "baseline", "--window", "5",
                 "--quiet"]) == 0
    fs = small_fs(48)
    root = fs if fs is not None else tmp_path / "out"
    root.mkdir(exist_ok=True)
    (root / "model.ply").write_bytes(b"ply previous")
    (root / "ballast").write_bytes(b"\0" * (40 * 1024 if fs is not None else 1))
    if fs is None:
        monkeypatch.setenv(imageio.FAULT_ENV, "enospc:1")
        monkeypatch.setattr(imageio, "_writes", 0)
    status = lfrig(["export", str(result), "--ply", str(root / "model.ply"), "--points", "--ascii"])
    err = capfd.readouterr().err
    assert status == 2 and "model.ply" in err and "Traceback" not in err, err
    assert (root / "model.ply").read_bytes() == b"ply previous"
    assert sorted(p.name for p in root.iterdir()) == ["ballast", "model.ply"]


def test_a_capture_killed_from_outside_resumes_to_the_same_views(tmp_path):
    """A real ``kill -9`` of the real ``lfrig`` process, after its 4th view is journalled."""
    out, clean = tmp_path / "cap", tmp_path / "clean"
    assert lfrig(["capture", str(clean), *CAPTURE]) == 0
    proc = subprocess.Popen([sys.executable, "-m", "rig.main", "capture", str(out), *CAPTURE, "--settle-s", "0.3"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + CHILD_TIMEOUT_S
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / MANIFEST).exists() and (out / MANIFEST).read_bytes().count(b'"kind": "view"') >= 4:
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the capture ended before it could be killed; " + proc.stderr.read().decode()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()
    check_capture_folder(out, "kill -9 from outside")
    assert lfrig(["capture", str(out), *CAPTURE]) == 0
    assert views_digest(out) == views_digest(clean)
