"""Issue #22: hostile files and paths, one regression test per point.

Links planted where lfrig writes (the lock, ``views/``, temporary names), values that would put
points at absurd distances or ask for absurd memory, files whose size lies, signals, concurrency,
and the last tracebacks. A user's mistake is one line ``lfrig: error: ...`` and exit status 2;
nothing outside the folders a command was given is written, truncated or deleted.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from recon.lf.imageio import write_png
from recon.lf.pfm import read_pfm, write_pfm
from rig.main import main
from test_bad_input import capture, one_line_error  # noqa: F401 - the same error check and capture fixture

ROOT = Path(__file__).resolve().parents[1]
TINY_CAPTURE = ROOT / "fixtures" / "tiny_capture"
BASELINE = ["--method", "baseline", "--window", "3", "--step", "0.1", "--quiet"]
LFRIG = [sys.executable, "-c", "import sys; from rig.main import main; sys.exit(main())"]


@pytest.fixture
def victim(tmp_path) -> Path:
    """A file of the user's that no command of a test is given: it must stay as it is."""
    folder = tmp_path / "home"
    folder.mkdir()
    path = folder / "victim.txt"
    path.write_text("precious\n")
    return path


def benchmark_folder(folder: Path, capture: Path = TINY_CAPTURE) -> Path:
    """The tiny capture's views and parameters in the benchmark's layout."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, view in enumerate(sorted((capture / "views").iterdir())):
        shutil.copy(view, folder / f"input_Cam{i:03d}.png")
    shutil.copy(capture / "parameters.cfg", folder / "parameters.cfg")
    return folder


def plain_views(folder: Path, name_of, *, rows: int = 3, cols: int = 3, size: int = 16) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    for u in range(rows):
        for v in range(cols):
            write_png(folder / name_of(u, v), rng.integers(0, 255, (size, size), dtype=np.uint8))
    return folder


def peak_memory_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def set_parameter(cfg: Path, key: str, value: str) -> None:
    lines = [f"{key} = {value}" if line.split("=")[0].strip() == key else line for line in cfg.read_text().splitlines()]
    assert any(line.startswith(f"{key} =") for line in lines), key
    cfg.write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------------------------------
# 1. the lock file


def test_a_lock_file_that_is_a_link_is_refused_and_its_target_untouched(tmp_path, capture, victim, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / ".lfrig.lock").symlink_to(victim)
    status = main(["reconstruct", str(capture), "-o", str(out), *BASELINE])
    one_line_error(capsys, status, ".lfrig.lock", "symbolic link")
    assert victim.read_text() == "precious\n"
    assert not (out / "result.json").exists()


def test_a_lock_file_that_is_a_fifo_is_refused_without_waiting(tmp_path):
    from recon.lf.lock import FolderLock, FolderLockError

    os.mkfifo(tmp_path / ".lfrig.lock")
    with pytest.raises(FolderLockError, match="not a regular file"):
        FolderLock(tmp_path)


def test_a_failed_capture_leaves_no_folder_with_a_lock(tmp_path, capsys):
    out = tmp_path / "c"
    status = main(["capture", str(out), "--stage", f"grbl://{tmp_path / 'no-such-port'}", "--camera", "fake",
                   "--rows", "3", "--cols", "3", "--centre-mm", "10", "10", "-5", "--quiet"])
    one_line_error(capsys, status, "no-such-port")
    assert not out.exists()


# --------------------------------------------------------------------------------------------------
# 2. a resume through a symlinked views/


def test_a_resume_refuses_a_views_folder_that_is_a_link(tmp_path, capture):
    from recon.errors import CaptureLayoutError
    from recon.lf.capture import CaptureWriter

    elsewhere = tmp_path / "elsewhere"
    shutil.move(capture / "views", elsewhere)
    (capture / "views").symlink_to(elsewhere)
    stale = elsewhere / ".u00_v00.4242.tmp.png"
    stale.write_bytes(b"somebody else's file")
    header = json.loads((capture / "manifest.jsonl").read_text().splitlines()[0])
    with pytest.raises(CaptureLayoutError, match="symbolic link"):
        CaptureWriter(capture, header={"grid": header["grid"], "settings": header["settings"]})
    assert stale.read_bytes() == b"somebody else's file"
    assert sorted(p.name for p in elsewhere.iterdir()) == sorted([p.name for p in (TINY_CAPTURE / "views").iterdir()] + [stale.name])


def test_an_atomic_write_never_writes_through_a_planted_temporary_link(tmp_path, victim):
    from recon.lf.imageio import temporary_name, write_bytes_atomic

    target = tmp_path / "x.json"
    temporary_name(target).symlink_to(victim)  # the name this process will use
    write_bytes_atomic(target, b"{}")
    assert victim.read_text() == "precious\n" and target.read_bytes() == b"{}"
    assert not temporary_name(target).exists()


# --------------------------------------------------------------------------------------------------
# 3. import accepts nothing lfrig then refuses


@pytest.mark.parametrize("flags", [["--pitch-mm", "inf"], ["--pitch-mm", "1e-320"], ["--focal-px", "inf"],
                                   ["--disparity-range", "nan", "nan"], ["--disparity-range", "5", "1"],
                                   ["--disparity-range", "0", "inf"], ["--principal-point-px", "1e308", "3"]])
def test_import_refuses_what_readers_refuse(tmp_path, flags, capsys):
    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png")
    argv = ["import", str(src), "-o", str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.png",
            "--rows", "3", "--cols", "3", "--pitch-mm", "0.5", *flags, "--quiet"]
    one_line_error(capsys, main(argv))
    assert not (tmp_path / "cap").exists()


def test_import_refuses_more_rows_than_readers_read(tmp_path, capsys):
    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png", rows=1025, cols=1, size=1)
    argv = ["import", str(src), "-o", str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.png",
            "--rows", "1025", "--cols", "1", "--pitch-mm", "0.5", "--quiet"]
    one_line_error(capsys, main(argv), "--rows", "1024")
    assert not (tmp_path / "cap").exists()


@pytest.mark.parametrize("options", [{"pitch_mm": float("inf")}, {"focal_px": float("nan")}, {"rows": 100000},
                                     {"disparity_range": (5.0, 1.0)}, {"disparity_range": (-1e12, 1e12)}])
def test_import_views_checks_its_values_again(tmp_path, options):
    from recon.lf.importer import ViewImportError, import_views

    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png")
    kwargs = {"pattern": "view_{u}_{v}.png", "rows": 3, "cols": 3, "pitch_mm": 0.5, **options}
    with pytest.raises(ViewImportError):
        import_views(src, tmp_path / "cap", **kwargs)
    assert not (tmp_path / "cap").exists()


# --------------------------------------------------------------------------------------------------
# 4. disparity ranges bounded by what the image can hold


@pytest.mark.parametrize("low, high", [("-1e12", "1e12"), ("-1000", "1000")])
def test_a_disparity_range_beyond_the_image_is_refused_on_read(capture, low, high):
    from recon.errors import LightFieldFormatError
    from recon.lf import read_lightfield

    set_parameter(capture / "parameters.cfg", "disp_min", low)
    set_parameter(capture / "parameters.cfg", "disp_max", high)
    with pytest.raises(LightFieldFormatError, match="disparity range"):
        read_lightfield(capture)


def test_a_disparity_range_flag_beyond_the_image_is_refused(tmp_path, capture, capsys):
    status = main(["reconstruct", str(capture), "-o", str(tmp_path / "out"), "--method", "baseline",
                   "--disparity-range", "-1000", "1000", "--quiet"])
    one_line_error(capsys, status, "disparity range")


def test_max_disparity_follows_the_farthest_view():
    from recon.lf.params import max_disparity_px

    assert max_disparity_px((9, 9), (512, 512)) == 128.0
    assert max_disparity_px((3, 9), (32, 64)) == 16.0  # columns: 4 steps over 64 px
    assert max_disparity_px((1, 1), (8, 8)) == float("inf")


# --------------------------------------------------------------------------------------------------
# 5. the baseline with a single candidate


def test_the_baseline_with_a_single_candidate(tmp_path, capture, capsys):
    status = main(["reconstruct", str(capture), "-o", str(tmp_path / "out"), "--method", "baseline",
                   "--disparity-range", "0", "0.01", "--step", "1e9", "--quiet"])
    assert status == 0, capsys.readouterr().err
    assert np.all(read_pfm(tmp_path / "out" / "disparity.pfm") == 0)


# --------------------------------------------------------------------------------------------------
# 6. sizes checked before reading


def png_claiming(width: int, height: int) -> bytes:
    """A small, well-formed PNG whose header claims ``width`` x ``height`` 8-bit grey pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * (width + 1)))
            + chunk(b"IEND", b""))


def test_a_view_whose_header_claims_a_huge_image_is_refused_before_decoding(tmp_path, capsys):
    bench = benchmark_folder(tmp_path / "bench")
    (bench / "input_Cam004.png").write_bytes(png_claiming(40000, 30000))
    status = main(["info", str(bench)])
    one_line_error(capsys, status, "input_Cam004.png", "40000x30000", "larger than")


def test_a_sparse_view_is_not_read_whole(tmp_path, capsys):
    bench = benchmark_folder(tmp_path / "bench")
    os.truncate(bench / "input_Cam004.png", 8 << 30)  # 8 GiB, no blocks on disk
    before = peak_memory_mib()
    status = main(["info", str(bench)])
    one_line_error(capsys, status, "input_Cam004.png", "8.0 GiB")
    assert peak_memory_mib() - before < 512


def test_a_sparse_confidence_map_is_not_read_whole(tmp_path, capture, capsys):
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    capsys.readouterr()
    confidence = tmp_path / "res" / "confidence.pfm"
    confidence.write_bytes(b"Pf\n32 32\n-1.0\n")
    os.truncate(confidence, 8 << 30)  # a header, then 8 GiB of nothing: only the 4 KiB it describes are read
    before = peak_memory_mib()
    assert main(["export", str(tmp_path / "res"), "--ply", str(tmp_path / "m.ply"), "--points", "--keep-all"]) == 0
    assert (tmp_path / "m.ply").is_file()
    assert peak_memory_mib() - before < 512


def test_a_sparse_import_source_is_not_read_whole(tmp_path, capsys):
    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png")
    os.truncate(src / "view_1_1.png", 8 << 30)
    before = peak_memory_mib()
    status = main(["import", str(src), "-o", str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.png",
                   "--rows", "3", "--cols", "3", "--pitch-mm", "0.5", "--quiet"])
    one_line_error(capsys, status, "view_1_1.png", "8.0 GiB")
    assert peak_memory_mib() - before < 512


def test_a_resume_does_not_read_a_sparse_view_whole(capture):
    from recon.lf.capture import CaptureWriter

    os.truncate(capture / "views" / "u01_v01.png", 8 << 30)
    header = json.loads((capture / "manifest.jsonl").read_text().splitlines()[0])
    before = peak_memory_mib()
    with CaptureWriter(capture, header={"grid": header["grid"], "settings": header["settings"]}) as writer:
        assert (1, 1) not in writer.completed and len(writer.completed) == 8  # to be taken again
    assert peak_memory_mib() - before < 512


def test_a_pfm_header_claiming_a_huge_map_is_refused(tmp_path):
    from recon.errors import LightFieldFormatError

    path = tmp_path / "x.pfm"
    path.write_bytes(b"Pf\n100000 100000\n-1.0\n" + bytes(64))
    with pytest.raises(LightFieldFormatError, match="larger than"):
        read_pfm(path)


# --------------------------------------------------------------------------------------------------
# 7. no absurd geometry reaches a PLY


@pytest.mark.parametrize("key, value", [("principal_point_px", [1e308, 3.0]), ("pitch_mm", 1e-320),
                                        ("disparity_offset", 1e308), ("focal_px", 1e300)])
def test_absurd_camera_in_result_json_is_refused(tmp_path, capture, key, value, capsys):
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    capsys.readouterr()
    record = json.loads((tmp_path / "res" / "result.json").read_text())
    record[key] = value
    (tmp_path / "res" / "result.json").write_text(json.dumps(record))
    status = main(["export", str(tmp_path / "res"), "--ply", str(tmp_path / "m.ply"), "--keep-all"])
    one_line_error(capsys, status, key)
    assert not (tmp_path / "m.ply").exists()


def test_a_tiny_disparity_is_at_infinity_not_a_point_far_away(tmp_path, capture, capsys):
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    disparity = read_pfm(tmp_path / "res" / "disparity.pfm")
    disparity[:] = 1e-40
    disparity[:4, :4] = 1.0
    write_pfm(tmp_path / "res" / "disparity.pfm", disparity)
    assert main(["export", str(tmp_path / "res"), "--ply", str(tmp_path / "m.ply"), "--points", "--keep-all"]) == 0
    import open3d as o3d

    points = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "m.ply")).points)
    assert len(points) == 16 and np.isfinite(points).all() and np.abs(points).max() < 1e6


def test_a_resolution_that_is_not_the_views_is_refused(capture):
    from recon.errors import LightFieldFormatError
    from recon.lf import read_lightfield

    set_parameter(capture / "parameters.cfg", "image_resolution_x_px", "1e300")
    with pytest.raises(LightFieldFormatError, match="image_resolution_x_px"):
        read_lightfield(capture)


def test_camera_bounds_at_the_library_entry():
    from recon.camera import Camera

    for bad in ({"pitch_mm": 1e-320}, {"focal_px": 1e300}, {"disparity_offset": 1e308},
                {"principal_point_px": (1e308, 0.0)}):
        with pytest.raises(ValueError):
            Camera(**{"focal_px": 1000.0, "pitch_mm": 0.5, **bad})


# --------------------------------------------------------------------------------------------------
# 8. concurrent imports to one target


def test_an_import_whose_target_fills_meanwhile_is_one_error(tmp_path):
    from recon.lf.importer import ViewImportError, import_views

    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png")
    target = tmp_path / "cap"

    def other_import_finishes(fraction: float, message: str) -> None:
        if fraction > 0.5 and not target.exists():  # the writing half: the other import wins the race
            shutil.copytree(TINY_CAPTURE, target)

    with pytest.raises(ViewImportError, match="another process"):
        import_views(src, target, pattern="view_{u}_{v}.png", rows=3, cols=3, pitch_mm=0.5,
                     progress=other_import_finishes)
    assert sorted(p.name for p in target.iterdir()) == sorted(p.name for p in TINY_CAPTURE.iterdir())
    assert not any(".import-" in p.name for p in tmp_path.iterdir())


# --------------------------------------------------------------------------------------------------
# 9. the last tracebacks


def test_result_json_options_not_an_object(tmp_path, capture, capsys):
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    capsys.readouterr()
    record = json.loads((tmp_path / "res" / "result.json").read_text())
    record["options"] = [1, 2]
    (tmp_path / "res" / "result.json").write_text(json.dumps(record))
    status = main(["export", str(tmp_path / "res"), "--ply", str(tmp_path / "m.ply")])
    one_line_error(capsys, status, "options")


@pytest.mark.parametrize("content", [b"\x93NUMPY garbage", b"", "object"])
def test_a_corrupt_regions_npy_in_export_report(tmp_path, capture, content, capsys):
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    capsys.readouterr()
    regions = tmp_path / "res" / "regions.npy"
    if content == "object":
        np.save(regions, np.array([{"a": 1}] * 4, dtype=object), allow_pickle=True)
    else:
        regions.write_bytes(content)
    status = main(["export", str(tmp_path / "res"), "--report", str(tmp_path / "report")])
    one_line_error(capsys, status, "regions.npy")


@pytest.mark.parametrize("address", ["nonsense:::", ":8787", "127.0.0.1:99999", "[::1:80"])
def test_batch_dashboard_address_is_checked(tmp_path, capture, address, capsys):
    status = main(["batch", "reconstruct", str(capture), "-o", str(tmp_path / "out"), "--dashboard-address", address])
    one_line_error(capsys, status, "--dashboard-address")


def test_connect_checks_the_dashboard_address_too():
    from recon.scale import ScaleError
    from recon.scale.cluster import connect

    with pytest.raises(ScaleError, match="every interface"):
        with connect(dashboard_address=":8787"):
            pass


@pytest.mark.parametrize("width", ["09999999999999999999", "0999999999"])  # Python refuses / a 1 GB name
def test_an_import_pattern_with_a_huge_width(tmp_path, width, capsys):
    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png")
    status = main(["import", str(src), "-o", str(tmp_path / "cap"), "--pattern", f"view_{{u:{width}d}}_{{v}}.png",
                   "--rows", "3", "--cols", "3", "--pitch-mm", "0.5", "--quiet"])
    one_line_error(capsys, status, "pattern")


def test_ctrl_c_while_the_commands_load(monkeypatch, capsys):
    import importlib

    def interrupted(name):
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib, "import_module", interrupted)
    assert main(["info", "x"]) == 130
    assert capsys.readouterr().err.strip() == "lfrig: interrupted"


def test_ctrl_c_in_the_first_second_of_a_real_command(tmp_path):
    for delay_s in (0.6, 1.2):  # after the interpreter started, while the command modules load
        process = subprocess.Popen([*LFRIG, "info", str(TINY_CAPTURE)], stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, cwd=tmp_path)
        time.sleep(delay_s)
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=60)
        assert b"Traceback" not in err, err.decode()
        assert process.returncode in (0, 130, -signal.SIGINT), (process.returncode, err.decode())


# --------------------------------------------------------------------------------------------------
# 10. an output inside an input


@pytest.mark.parametrize("inside", ["views", "views/sub", "."])
def test_reconstruct_refuses_an_output_inside_the_capture_data(capture, inside, capsys):
    from recon.lf import read_lightfield

    status = main(["reconstruct", str(capture), "-o", str(capture / inside), *BASELINE])
    one_line_error(capsys, status, "give a folder of its own")
    read_lightfield(capture)  # still a whole capture
    assert not (capture / "result.json").exists()


# --------------------------------------------------------------------------------------------------
# 11. a run removes its own stale temporaries


SIGNAL_IMPORT = """
import os, signal, sys
import recon.lf.capture as capture
from rig.main import main

write_view = capture.CaptureWriter.write_view
def stop_after_two(self, u, v, *args, **kwargs):
    entry = write_view(self, u, v, *args, **kwargs)
    if len(self.completed) == 2:
        os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    return entry
capture.CaptureWriter.write_view = stop_after_two
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP"])
def test_an_import_stopped_by_a_signal_leaves_no_temporary_folder(tmp_path, name):
    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png")
    process = subprocess.run([sys.executable, "-c", SIGNAL_IMPORT, name, "import", str(src), "-o",
                              str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.png", "--rows", "3", "--cols", "3",
                              "--pitch-mm", "0.5", "--quiet"], capture_output=True, cwd=tmp_path, timeout=120)
    assert process.returncode == 128 + getattr(signal, name), process.stderr.decode()
    assert b"Traceback" not in process.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]


def dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_an_import_removes_what_a_killed_import_left(tmp_path):
    from recon.lf.importer import import_views
    from recon.lf.lock import FolderLock

    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png")
    stale = tmp_path / f".cap.import-{dead_pid()}.tmp"
    FolderLock(stale).release()  # what a killed import leaves: a folder with its (free) lock ...
    (stale / "views").mkdir()
    (stale / "views" / "u00_v00.png").write_bytes(b"partial copy")  # ... and a partial copy
    import_views(src, tmp_path / "cap", pattern="view_{u}_{v}.png", rows=3, cols=3, pitch_mm=0.5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "src"]


def test_an_export_removes_what_a_killed_export_left(tmp_path, capture):
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    stale = tmp_path / f".m.{dead_pid()}.tmp.ply"
    stale.write_bytes(b"ply\nhalf a mesh")
    assert main(["export", str(tmp_path / "res"), "--ply", str(tmp_path / "m.ply"), "--points"]) == 0
    assert not stale.exists() and (tmp_path / "m.ply").is_file()


@pytest.mark.parametrize("write", [1, 2])
def test_export_depth_on_a_full_disk_leaves_nothing_half_done(tmp_path, capture, monkeypatch, write, capsys):
    import recon.lf.imageio as imageio
    from recon.depth import read_depth

    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    out = tmp_path / "depth"
    out.mkdir()
    capsys.readouterr()
    monkeypatch.setenv("LFRIG_FAULT", f"enospc:{write}")
    monkeypatch.setattr(imageio, "_writes", 0)
    status = main(["export", str(tmp_path / "res"), "--depth", str(out / "d.png"), "--keep-all"])
    one_line_error(capsys, status, "d.png")
    left = sorted(p.name for p in out.iterdir())
    assert left in ([], ["d.png"]), left  # nothing, or a whole PNG that carries its own scale
    if left:
        assert np.isfinite(read_depth(out / "d.png")).any()


# --------------------------------------------------------------------------------------------------
# 12. quietly accepted


def test_an_all_nan_ground_truth_is_said(tmp_path, capsys):
    bench = benchmark_folder(tmp_path / "bench")
    write_pfm(bench / "gt_disp_lowres.pfm", np.full((32, 32), np.nan, np.float32))
    status = main(["reconstruct", str(bench), "-o", str(tmp_path / "out"), *BASELINE])
    one_line_error(capsys, status, "gt_disp_lowres.pfm", "no finite value")


def test_export_depth_of_an_all_empty_map_says_so(tmp_path, capture, capsys):
    assert main(["reconstruct", str(capture), "-o", str(tmp_path / "res"), *BASELINE]) == 0
    capsys.readouterr()
    write_pfm(tmp_path / "res" / "disparity.pfm", np.full((32, 32), np.nan, np.float32))
    status = main(["export", str(tmp_path / "res"), "--depth", str(tmp_path / "d.pfm")])
    one_line_error(capsys, status, "no pixel has a depth")
    assert not (tmp_path / "d.pfm").exists()


def test_an_import_does_not_follow_a_link_out_of_src(tmp_path, victim, capsys):
    src = plain_views(tmp_path / "src", lambda u, v: f"view_{u}_{v}.png")
    (src / "view_2_2.png").unlink()
    outside = tmp_path / "home" / "photo.png"
    shutil.copy(src / "view_0_0.png", outside)
    (src / "view_2_2.png").symlink_to(outside)
    status = main(["import", str(src), "-o", str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.png",
                   "--rows", "3", "--cols", "3", "--pitch-mm", "0.5", "--quiet"])
    one_line_error(capsys, status, "view_2_2.png", "outside")
    assert not (tmp_path / "cap").exists()


def test_padded_duplicate_names_do_not_shift_the_grid(tmp_path, capsys):
    names = [f"img{i}.png" for i in range(1, 9)] + ["img01.png"]  # img1 twice; img0 missing
    src = plain_views(tmp_path / "src", lambda u, v: names[3 * u + v])
    status = main(["import", str(src), "-o", str(tmp_path / "cap"), "--order", "raster", "--rows", "3",
                   "--cols", "3", "--pitch-mm", "0.5", "--quiet"])
    one_line_error(capsys, status, "img1.png", "img01.png")
    assert not (tmp_path / "cap").exists()


def test_an_aravis_roi_beyond_the_sensor_is_refused():
    from rig.errors import RigError

    pytest.importorskip("gi")
    from rig.aravis import AravisCamera

    try:
        camera = AravisCamera("Fake_1")
    except RigError as error:  # no Aravis on this machine
        pytest.skip(str(error))
    camera.close()
    with pytest.raises(RigError, match="beyond the 2048x2048 sensor"):
        AravisCamera("Fake_1", roi=(100000, 5, 48, 32))
