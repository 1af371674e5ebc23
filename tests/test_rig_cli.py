"""``lfrig capture`` and ``lfrig stage`` end to end with the fake stage and the fake camera."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

from rig.main import main

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["--binning", "8", "--supersample", "1"]  # 160 x 122 px frames


def views_in(path: Path) -> Counter:
    manifest = path / "manifest.jsonl"
    if not manifest.is_file():
        return Counter()
    lines = [l for l in manifest.read_text().splitlines() if l.strip()]
    records = []
    for line in lines:
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            pass  # a line being appended right now
    return Counter((r["u"], r["v"]) for r in records if r.get("kind") == "view")


def test_capture_fake_small_grid_and_info(tmp_path, capsys):
    out = tmp_path / "cap"
    assert main(["capture", str(out), "--rows", "3", "--cols", "4", "--quiet", *SMALL]) == 0
    assert sorted(views_in(out).values()) == [1] * 12
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "3 x 4 views" in text and "160 x 122" in text
    # running it again takes nothing new
    assert main(["capture", str(out), "--rows", "3", "--cols", "4", "--quiet", *SMALL]) == 0
    assert "0 taken now" in capsys.readouterr().out


def test_capture_refuses_other_settings_by_name(tmp_path, capsys):
    out = tmp_path / "cap"
    assert main(["capture", str(out), "--rows", "2", "--cols", "2", "--quiet", *SMALL]) == 0
    assert main(["capture", str(out), "--rows", "2", "--cols", "2", "--pitch-mm", "1", "--quiet", *SMALL]) == 2
    err = capsys.readouterr().err
    assert "pitch_mm: capture has 0.5, now 1.0" in err and "new folder" in err


def test_dry_run_lists_moves_and_checks_limits(tmp_path, capsys):
    assert main(["capture", str(tmp_path / "x"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "114 moves, 81 views, 33 backlash take-up moves" in out
    assert "all moves within the travel" in out
    assert not (tmp_path / "x").exists()
    assert main(["capture", str(tmp_path / "x"), "--dry-run", "--centre-mm", "-1", "-50", "-10"]) == 2
    assert "outside the stage's travel" in capsys.readouterr().err
    assert main(["capture", str(tmp_path / "x"), "--dry-run", "--limits-mm", "-60", "0", "-60", "0", "-20", "0"]) == 0


def test_real_stage_needs_a_centre(tmp_path, capsys):
    assert main(["capture", str(tmp_path / "x"), "--stage", "grbl:///dev/null-nothing", "--dry-run"]) == 2
    assert "--centre-mm" in capsys.readouterr().err


def test_fault_on_the_command_line_then_resume(tmp_path, capsys):
    out = tmp_path / "cap"
    args = ["capture", str(out), "--rows", "3", "--cols", "3", "--quiet", *SMALL]
    assert main([*args, "--stage", "fake?fault=alarm_mid_move&after=4"]) == 2
    err = capsys.readouterr().err
    assert "ALARM:1" in err and "hard limit" in err and "run the same command again to resume" in err
    first = views_in(out)
    assert 0 < sum(first.values()) < 9
    assert main(args) == 0
    assert sorted(views_in(out).values()) == [1] * 9


def test_stage_commands(capsys):
    assert main(["stage", "status"]) == 0
    assert capsys.readouterr().out.startswith("Alarm  MPos X=0.000")
    assert main(["stage", "move", "-10", "-20", "-5", "--home"]) == 0
    assert "Idle  MPos X=-10.000, Y=-20.000, Z=-5.000" in capsys.readouterr().out
    assert main(["stage", "move", "-10", "-20", "-5"]) == 2  # a fresh controller is locked until homed
    err = capsys.readouterr().err
    assert "error:9" in err and "warning: GRBL reset when the port opened" in err
    assert main(["stage", "home"]) == 0
    assert "Idle  MPos X=-1.000, Y=-1.000, Z=-1.000" in capsys.readouterr().out


def test_sigint_part_way_then_resume_takes_each_view_once(tmp_path):
    out = tmp_path / "cap"
    command = [sys.executable, "-m", "rig.main", "capture", str(out), "--binning", "8", "--supersample", "2"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while sum(views_in(out).values()) < 3:
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, "the capture did not start"
            time.sleep(0.005)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, stderr
    assert "finishing the current view" in stderr and "run the same command again to resume" in stderr
    first = views_in(out)
    assert set(first.values()) == {1} and 3 <= len(first) < 81
    log = (out / "session.log").read_text()
    assert "stopped on request" in log
    second = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert second.returncode == 0, second.stderr
    assert f"({81 - len(first)} taken now), complete" in second.stdout
    final = views_in(out)
    assert len(final) == 81 and set(final.values()) == {1}
    assert main(["info", str(out)]) == 0


def test_fake_capture_reconstructs_to_the_fake_scenes_disparity(tmp_path):
    """Done-when of the capture issue: an ideal fake rig's capture, reconstructed by `lfrig reconstruct`,
    matches the disparity the fake camera knows to be true."""
    import numpy as np

    from recon.lf.pfm import read_pfm
    from rig.devices import FAKE_CENTRE_MM
    from rig.fakecam import FakeCamera, FakeRig

    out = tmp_path / "cap"
    assert main(["capture", str(out), "--fake-rig", "ideal", "--quiet", *SMALL]) == 0
    assert main(["reconstruct", str(out), "-o", str(tmp_path / "rec"), "--quiet", "--disparity-range", "0.2", "0.8"]) == 0
    estimate = read_pfm(tmp_path / "rec" / "disparity.pfm")
    camera = FakeCamera(None, rig=FakeRig.ideal(ref_mm=FAKE_CENTRE_MM), binning=8)
    truth = camera.rectified_truth(pitch_mm=0.5, centre_mm=FAKE_CENTRE_MM)["disparity_px"]
    inner = (slice(10, -10), slice(10, -10))
    error = np.abs(estimate[inner] - truth[inner])
    assert np.median(error) < 0.02, np.median(error)
    assert np.mean(error > 0.07) < 0.1, np.mean(error > 0.07)
    print(f"median |d - d_true| = {np.median(error):.4f} px, BadPix0.07 = {100 * np.mean(error > 0.07):.1f} %")


def test_stage_move_help(capsys):
    assert main(["stage", "move", "--help"]) == 0  # main returns argparse's exit status
    assert "X Y Z" in capsys.readouterr().out


def test_capture_without_homing_after_a_reset_warns(tmp_path, capsys):
    out = tmp_path / "cap"
    assert main(["capture", str(out), "--no-home", "--rows", "2", "--cols", "2", "--quiet", *SMALL]) == 2
    err = capsys.readouterr().err
    assert "warning: GRBL reset when the port opened" in err and "error:9" in err  # $22=1: locked as well


def test_a_capture_that_fails_before_its_first_view_leaves_nothing(tmp_path, capsys):
    """#21.10: a capture refused before its first view (here a camera that does not open) leaves no
    folder, lock or journal, so the corrected command starts afresh."""
    out = tmp_path / "new" / "cap"
    assert main(["capture", str(out), "--camera", "opencv:/nonexistent/video9", "--quiet", *SMALL]) == 2
    assert "cannot open camera" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()  # a folder the user made stays, empty
    assert main(["capture", str(tmp_path / "mine"), "--camera", "opencv:/nonexistent/video9", "--quiet", *SMALL]) == 2
    assert list((tmp_path / "mine").iterdir()) == []
