"""Regression tests of issue #13, points 1-6: nothing lost, nothing half-written.

Each test reproduces what the probe found (a torn journal, a short PLY, an out-of-grid record, two
captures in one folder, views and masks the manifest points anywhere, stale maps after a rerun) and
checks the fixed behaviour. The kill -9 / full-disk sweeps over every write are in test_faults.py.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from recon.errors import CaptureLayoutError, ExportError, FileWriteError, LfrigError
from recon.lf.capture import CaptureWriter, read_capture
from recon.lf.lock import LOCK_NAME, FolderLock, FolderLockedError
from rig.main import main

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"
SMALL = ["--rows", "3", "--cols", "3", "--binning", "8", "--supersample", "1", "--quiet"]


def header(rows=2, cols=2):
    grid = {"rows": rows, "cols": cols, "pitch_mm": 0.5}
    return {"grid": grid, "settings": {"grid": grid}}


def image(seed=0):
    return np.random.default_rng(seed).integers(0, 255, (6, 8, 3), dtype=np.uint8)


def journal(path: Path) -> list[dict]:
    return [json.loads(line) for line in (path / "manifest.jsonl").read_text().splitlines()]


def tear_last_line(manifest: Path, keep_bytes: int = 20) -> None:
    """What a crash or a full disk mid-append leaves: the last line cut short, no newline."""
    data = manifest.read_bytes()
    start = data.rstrip(b"\n").rfind(b"\n") + 1
    manifest.write_bytes(data[: start + keep_bytes])


# --- 1. a torn journal line ----------------------------------------------------------------------


@pytest.mark.parametrize("tail", ["cut", "zeros"])
def test_a_torn_journal_tail_is_cut_before_the_resume_appends(tmp_path, tail):
    folder = tmp_path / "c"
    with CaptureWriter(folder, header=header()) as w:
        for k, (u, v) in enumerate([(0, 0), (0, 1), (1, 0)]):
            w.write_view(u, v, image(k))
    manifest = folder / "manifest.jsonl"
    if tail == "cut":
        tear_last_line(manifest)
    else:  # a crash can leave the file longer, the new block full of zeros
        with open(manifest, "ab") as f:
            f.write(b"\0" * 100)
    with CaptureWriter(folder, header=header()) as w:
        assert set(w.completed) == ({(0, 0), (0, 1)} if tail == "cut" else {(0, 0), (0, 1), (1, 0)})
        for k, (u, v) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
            if (u, v) not in w.completed:
                w.write_view(u, v, image(k))
        w.mark_complete()
    records = journal(folder)  # every line is JSON again: the torn one was cut, not buried
    assert records[-1]["kind"] == "complete"
    assert read_capture(folder).grid_shape == (2, 2)


def test_a_torn_journal_through_the_command_line_resumes_and_stays_readable(tmp_path, capsys):
    out = tmp_path / "cap"
    assert main(["capture", str(out), *SMALL]) == 0
    manifest = out / "manifest.jsonl"
    lines = manifest.read_bytes().splitlines(keepends=True)
    # the crash came while the 5th view's line was appended: views 6.. were never taken
    views_seen = 0
    kept = []
    for line in lines:
        if b'"kind": "view"' in line:
            views_seen += 1
            if views_seen == 5:
                kept.append(line[:30])
                break
        kept.append(line)
    manifest.write_bytes(b"".join(kept))
    assert main(["capture", str(out), *SMALL]) == 0
    assert "9 of 9 views (5 taken now), complete" in capsys.readouterr().out
    assert main(["info", str(out)]) == 0
    assert main(["capture", str(out), *SMALL]) == 0
    assert all(isinstance(r, dict) for r in journal(out))


def test_a_failed_append_leaves_no_torn_line(tmp_path, monkeypatch):
    folder = tmp_path / "c"
    with CaptureWriter(folder, header=header()) as w:
        w.write_view(0, 0, image())
        monkeypatch.setenv("LFRIG_FAULT", "enospc:3")  # write 1: the view, 2: nothing yet... count below
        import recon.lf.imageio as imageio

        monkeypatch.setattr(imageio, "_writes", 0)
        # write 1 is the PNG of (0, 1), write 2 its journal line, write 3 the PNG of (1, 0), 4 its line
        monkeypatch.setenv("LFRIG_FAULT", "enospc:2")
        with pytest.raises(FileWriteError, match=r"manifest.jsonl: cannot write \(No space left on device\)"):
            w.write_view(0, 1, image(1))
        monkeypatch.delenv("LFRIG_FAULT")
        w.write_view(1, 0, image(2))  # the writer goes on after the failed line
    assert [r.get("u") for r in journal(folder)[1:]] == [0, 1]
    with CaptureWriter(folder, header=header()) as w:
        assert set(w.completed) == {(0, 0), (1, 0)}


# --- 2. exports through the atomic writer --------------------------------------------------------


def _cloud(n=2000):
    from recon.cloud import PointCloud

    rng = np.random.default_rng(1)
    points = rng.uniform(100, 200, (n, 3))
    normals = np.tile([0.0, 0.0, -1.0], (n, 1))
    return PointCloud(points_mm=points, normals=normals, colours=rng.uniform(0, 1, (n, 3)).astype(np.float32),
                      pixels=np.zeros((n, 2), np.int64))


def test_a_ply_write_that_fails_midway_is_an_error_and_replaces_nothing(tmp_path, monkeypatch):
    """The disk fills up half-way through the PLY: an ExportError naming the file, the old file intact."""
    import recon.lf.imageio as imageio
    from recon.export import write_cloud_ply

    target = tmp_path / "model.ply"
    target.write_bytes(b"previous complete file")

    def full(path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(imageio, "fault_point", full)
    with pytest.raises(ExportError, match=r"model\.ply: cannot write \(No space left on device\)"):
        write_cloud_ply(target, _cloud())
    assert target.read_bytes() == b"previous complete file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.ply"]  # no temporary left


def test_a_ply_is_written_whole_and_read_back(tmp_path):
    import open3d

    from recon.export import write_cloud_ply

    for ascii in (False, True):
        target = tmp_path / f"m{ascii}.ply"
        write_cloud_ply(target, _cloud(500), ascii=ascii)
        assert len(open3d.io.read_point_cloud(str(target)).points) == 500
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_depth_maps_on_a_full_disk_are_errors_and_leave_no_empty_file(tmp_path, monkeypatch):
    import recon.lf.imageio as imageio
    from recon.depth import DepthFormatError, read_depth, write_depth

    depth = np.full((8, 10), 950.0)
    write_depth(tmp_path / "d.png", depth)
    before = (tmp_path / "d.png").read_bytes()
    for name in ("d.png", "d.pfm", "d.npy"):
        monkeypatch.setattr(imageio, "_writes", 0)
        monkeypatch.setenv("LFRIG_FAULT", "enospc:1")
        with pytest.raises(DepthFormatError, match="No space left on device"):
            write_depth(tmp_path / name, depth * 2)
    monkeypatch.delenv("LFRIG_FAULT")
    assert (tmp_path / "d.png").read_bytes() == before and np.allclose(read_depth(tmp_path / "d.png"), 950.0, atol=0.1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.png", "d.png.json"]


def test_the_atomic_writer_removes_its_temporary_file_on_failure(tmp_path, monkeypatch):
    import recon.lf.imageio as imageio

    (tmp_path / "x.bin").write_bytes(b"old")
    monkeypatch.setattr(imageio, "_writes", 0)
    monkeypatch.setenv("LFRIG_FAULT", "enospc:1")
    with pytest.raises(FileWriteError, match=r"x\.bin: cannot write .*free some space"):
        imageio.write_bytes_atomic(tmp_path / "x.bin", b"new" * 1000)
    assert [p.name for p in tmp_path.iterdir()] == ["x.bin"] and (tmp_path / "x.bin").read_bytes() == b"old"


# --- 3. a journal entry outside the grid ---------------------------------------------------------


def test_a_record_outside_the_grid_does_not_block_completion(tmp_path, capsys):
    out = tmp_path / "cap"
    assert main(["capture", str(out), *SMALL]) == 0
    # an edited or damaged record: u=99, naming a real view with its real checksum
    first = next(r for r in journal(out) if r.get("kind") == "view")
    with open(out / "manifest.jsonl", "a") as f:
        f.write(json.dumps({**first, "u": 99}) + "\n")
    # the probe: "10 of 9 views written; cannot mark complete" on every resume
    assert main(["capture", str(out), *SMALL]) == 0
    assert "9 of 9 views" in capsys.readouterr().out
    assert journal(out)[-1]["kind"] == "complete"
    assert read_capture(out).grid_shape == (3, 3)


# --- 4. one capture per folder -------------------------------------------------------------------


def test_a_second_capture_on_a_locked_folder_refuses_at_once(tmp_path, capsys):
    out = tmp_path / "cap"
    with FolderLock(out, what="capture"):
        started = time.perf_counter()
        assert main(["capture", str(out), *SMALL]) == 2
        assert time.perf_counter() - started < 5
    err = capsys.readouterr().err
    assert f"{out}: another capture is running in this folder" in err and "Traceback" not in err
    assert not (out / "manifest.jsonl").exists()  # nothing was written, no device was driven
    assert main(["capture", str(out), *SMALL]) == 0  # released: it runs


def test_a_lock_held_by_a_killed_process_does_not_block(tmp_path, capsys):
    out = tmp_path / "cap"
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time; from recon.lf.lock import FolderLock; l = FolderLock(sys.argv[1], what='capture'); "
         "print('locked', flush=True); time.sleep(120)", str(out)],
        stdout=subprocess.PIPE, text=True, cwd=ROOT,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(FolderLockedError, match="another capture is running"):
            CaptureWriter(out, header=header())
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
    finally:
        if holder.poll() is None:
            holder.kill()
        holder.stdout.close()
    assert (out / LOCK_NAME).exists()  # the file stays; the lock died with its process
    assert main(["capture", str(out), *SMALL]) == 0


def test_two_writers_in_one_process_exclude_each_other_and_rectify_outputs_too(tmp_path):
    from recon.lf import write_lightfield
    from recon.lf.lightfield import LightField

    with CaptureWriter(tmp_path / "c", header=header()):
        with pytest.raises(FolderLockedError):
            CaptureWriter(tmp_path / "c", header=header())
    lf = LightField(views=np.stack([np.stack([image(k) for k in range(2)])] * 2), pitch_mm=0.5)
    with FolderLock(tmp_path / "rect", what="capture"):
        with pytest.raises(FolderLockedError):
            write_lightfield(tmp_path / "rect", lf)


def test_a_second_reconstruction_into_a_locked_result_folder_refuses(tmp_path, capsys):
    with FolderLock(tmp_path / "o", what="reconstruction"):
        assert main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(tmp_path / "o"), "--method",
                     "baseline", "--window", "5", "--quiet"]) == 2
    assert "another reconstruction is running" in capsys.readouterr().err


# --- 5. reads check the manifest -----------------------------------------------------------------


@pytest.fixture
def capture(tmp_path):
    from recon.lf import write_lightfield
    from recon.lf.lightfield import LightField

    views = np.stack([np.stack([image(3 * u + v) for v in range(3)]) for u in range(3)])
    write_lightfield(tmp_path / "cap", LightField(views=views, pitch_mm=0.5, focal_px=100.0))
    return tmp_path / "cap"


def test_swapped_views_are_found_unless_the_user_opts_out(capture, capsys):
    a, b = capture / "views/u00_v00.png", capture / "views/u01_v02.png"
    data_a, data_b = a.read_bytes(), b.read_bytes()
    a.write_bytes(data_b)
    b.write_bytes(data_a)
    with pytest.raises(CaptureLayoutError, match=r"u00_v00\.png: content does not match the checksum"):
        read_capture(capture)
    assert main(["info", str(capture)]) == 2
    assert "--no-verify" in capsys.readouterr().err
    assert main(["info", str(capture), "--no-verify"]) == 0
    lf = read_capture(capture, verify=False)
    np.testing.assert_array_equal(lf.views[0, 0], image(5))


def test_verifying_reads_each_view_once(capture, monkeypatch):
    # The checksums are taken from the bytes read for decoding, not from a second read of the files.
    opened = []
    real_open = os.open

    def counting_open(path, *args, **kwargs):
        opened.append(Path(path).name)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", counting_open)
    read_capture(capture)
    assert sorted(name for name in opened if name.endswith(".png")) == sorted(
        p.name for p in (capture / "views").iterdir())


@pytest.mark.parametrize("file", ["../other/x.png", "/dev/zero", "views/u00_v01.png", "views/../views/u00_v00.png"])
def test_a_view_file_must_be_its_own_name_inside_the_folder(capture, file):
    outside = capture.parent / "other"
    outside.mkdir(exist_ok=True)
    shutil.copy(capture / "views/u00_v00.png", outside / "x.png")
    manifest = capture / "manifest.jsonl"
    records = journal(capture)
    for r in records:
        if r.get("u") == 0 and r.get("v") == 0:
            r["file"] = file
    manifest.write_text("".join(json.dumps(r) + "\n" for r in records))
    with pytest.raises(CaptureLayoutError, match=r"journalled as file .* a view must be views/u00_v00\.png"):
        read_capture(capture, verify=False)


def test_a_view_that_is_a_symlink_out_of_the_folder_is_refused(capture):
    outside = capture.parent / "elsewhere.png"
    shutil.copy(capture / "views/u01_v01.png", outside)
    (capture / "views/u01_v01.png").unlink()
    (capture / "views/u01_v01.png").symlink_to(outside)
    with pytest.raises(CaptureLayoutError, match="not a link elsewhere"):
        read_capture(capture, verify=False)


def test_a_bad_view_record_is_retaken_by_a_resume(tmp_path):
    folder = tmp_path / "c"
    with CaptureWriter(folder, header=header()) as w:
        for k, (u, v) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
            w.write_view(u, v, image(k))
        w.mark_complete()
    with open(folder / "manifest.jsonl", "a") as f:
        f.write(json.dumps({"kind": "view", "u": 1, "v": 1, "file": "../x.png", "sha256": "0"}) + "\n")
    with pytest.raises(CaptureLayoutError, match="journalled as file '../x.png'"):
        read_capture(folder)
    with CaptureWriter(folder, header=header()) as w:
        assert set(w.completed) == {(0, 0), (0, 1), (1, 0)}
        w.write_view(1, 1, image(3))
        w.mark_complete()
    assert read_capture(folder).grid_shape == (2, 2)


def _result(tmp_path) -> Path:
    out = tmp_path / "res"
    assert main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(out), "--method", "baseline",
                 "--window", "5", "--quiet"]) == 0
    return out


@pytest.mark.parametrize("mask", ["../outside.png", "/dev/zero", "sub/../../outside.png", "link.png", "."])
def test_a_results_mask_must_be_a_file_inside_the_folder(tmp_path, mask):
    from recon.result import read_result

    out = _result(tmp_path)
    shutil.copy(out / "centre_view.png", tmp_path / "outside.png")
    (out / "link.png").symlink_to(tmp_path / "outside.png")
    record = json.loads((out / "result.json").read_text())
    record["mask"] = mask
    (out / "result.json").write_text(json.dumps(record))
    with pytest.raises(ExportError, match="mask"):
        read_result(out)


# --- 6. a result folder holds one run ------------------------------------------------------------


def test_a_rerun_leaves_only_its_own_files(tmp_path, capsys):
    out = tmp_path / "res"
    from recon.result import ENTROPY_MAPS

    assert main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(out), "--quiet",
                 "--ply", str(out / "model.ply")]) == 0
    assert all((out / name).is_file() for name in ENTROPY_MAPS) and (out / "model.ply").is_file()
    (out / "notes.txt").write_text("the user's own file")
    assert main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(out), "--method", "baseline",
                 "--window", "5", "--quiet"]) == 0
    names = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert names == ["centre_view.png", "disparity.pfm", "disparity.png", "notes.txt", "result.json"]
    assert json.loads((out / "result.json").read_text())["files"] == [
        "disparity.pfm", "disparity.png", "centre_view.png", "result.json"]
    assert main(["export", str(out), "--report", str(tmp_path / "report")]) == 0
    page = (tmp_path / "report" / "index.html").read_text()
    # no figure of the entropy run's region map (the footer may name the C library "regions" that
    # this process loaded for that run)
    assert "regions.png" not in page and "region types" not in page.lower()
    assert not (tmp_path / "report" / "regions.png").exists()


def test_a_rerun_removes_the_files_the_previous_record_listed(tmp_path):
    from recon.pipeline import reconstruct_to_folder

    out = tmp_path / "res"
    (out / "sub").mkdir(parents=True)
    reconstruct_to_folder(FIXTURES / "tiny_capture", out, method="baseline", options={"window": 5},
                          ply=out / "sub" / "old.ply")
    assert "sub/old.ply" in json.loads((out / "result.json").read_text())["files"]
    reconstruct_to_folder(FIXTURES / "tiny_capture", out, method="baseline", options={"window": 5})
    assert not (out / "sub" / "old.ply").exists()
    record = json.loads((out / "result.json").read_text())
    record["files"] = ["../../escape.txt"]  # a listed name outside the folder is never removed
    (tmp_path / "escape.txt").write_text("keep")
    (out / "result.json").write_text(json.dumps(record))
    reconstruct_to_folder(FIXTURES / "tiny_capture", out, method="baseline", options={"window": 5})
    assert (tmp_path / "escape.txt").read_text() == "keep"


def test_every_error_here_is_an_lfrig_error():
    for error in (FileWriteError, FolderLockedError, CaptureLayoutError, ExportError):
        assert issubclass(error, LfrigError)
    assert errno.ENOSPC  # the fault hook raises OSError(ENOSPC), turned into FileWriteError
