"""``--json``: a reporting command prints one JSON object on stdout; progress and warnings go to stderr."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np

from recon.lf import read_lightfield
from rig.main import main

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
TINY = FIXTURES / "tiny_capture"
FAST = ["--method", "baseline", "--disparity-range", "-1", "1.5", "--step", "0.25"]


def stdout_object(capsys) -> tuple[dict, str]:
    captured = capsys.readouterr()
    return json.loads(captured.out), captured.err  # the whole of stdout is one object


def test_reconstruct_and_export_json(tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["reconstruct", str(TINY), "-o", str(out), *FAST, "--json"]) == 0
    data, err = stdout_object(capsys)
    assert data["output"] == str(out) and data["method"] == "baseline" and data["options"]["step"] == 0.25
    assert data["disparity"] == str(out / "disparity.pfm") and data["seconds"] > 0
    assert "baseline [" in err  # progress stays on stderr
    assert main(["export", str(out), "--ply", str(tmp_path / "m.ply"), "--depth", str(tmp_path / "d.pfm"),
                 "--poses", str(tmp_path / "poses"), "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert data["ply"] == str(tmp_path / "m.ply") and data["depth"] == [str(tmp_path / "d.pfm")]
    assert data["pixels_unreliable"] >= 0 and Path(data["poses"]).exists()


def test_export_poisson_says_it_is_meshing(tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["reconstruct", str(TINY), "-o", str(out), *FAST, "--quiet"]) == 0
    capsys.readouterr()
    assert main(["export", str(out), "--ply", str(tmp_path / "p.ply"), "--poisson", "--keep-all"]) == 0
    captured = capsys.readouterr()
    assert "meshing (Poisson" in captured.err and "wrote" in captured.out
    assert re.search(r"export \[#+\] 100.0%  meshing \(Poisson", captured.err)  # and when it ended
    assert main(["export", str(out), "--ply", str(tmp_path / "q.ply"), "--poisson", "--keep-all", "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and "wrote" in captured.out


def test_import_json_carries_the_warnings(tmp_path, capsys):
    lf = read_lightfield(TINY)
    src = tmp_path / "mirrored"
    src.mkdir()
    for u in range(3):
        for v in range(3):
            cv2.imwrite(str(src / f"view_{u}_{2 - v}.png"), lf.views[u, v][:, :, ::-1])
    assert main(["import", str(src), "-o", str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.png", "--rows", "3",
                 "--cols", "3", "--pitch-mm", "0.5", "--json"]) == 0
    data, err = stdout_object(capsys)
    assert data["output"] == str(tmp_path / "cap") and data["complete"] is True
    order = [w for w in data["warnings"] if "mirrored" in w]
    assert len(order) == 1 and len(data["warnings"]) == 2  # and that it has no focal length
    assert any("only give disparity" in w for w in data["warnings"])
    assert "lfrig: warning:" in err and "import [" in err


def test_evaluate_and_info_json(tmp_path, capsys):
    truth = FIXTURES / "tiny_capture_truth.pfm"
    assert main(["evaluate", str(truth), str(truth), "--border", "2", "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert data["mse_x100"] == 0 and np.isclose(data["badpix_0.07"], 0)
    assert main(["info", str(TINY), "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert data["grid"] == [3, 3]


def leaf_parsers(parser, path=()):
    """``(command words, parser)`` of every command that runs (no further action to choose)."""
    import argparse

    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield " ".join(path), parser
        return
    for name, sub in subs[0].choices.items():
        yield from leaf_parsers(sub, (*path, name))


#: Commands that report nothing a script would read: a live server and a keyboard loop.
NOT_REPORTING = {"camera preview", "stage jog"}


def test_every_reporting_command_has_json():
    from rig.main import build_parser

    commands = dict(leaf_parsers(build_parser()))
    assert NOT_REPORTING <= set(commands) and len(commands) >= 20
    missing = [name for name, parser in commands.items()
               if name not in NOT_REPORTING and "--json" not in parser._option_string_actions]
    assert missing == []
    helps = {parser._option_string_actions["--json"].help for name, parser in commands.items() if name not in NOT_REPORTING}
    assert len(helps) == 1  # one helper, one meaning


def test_stage_commands_json(capsys):
    assert main(["stage", "home", "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert data["state"] == "Idle" and data["version"] == "1.1h" and data["url"].startswith("fakegrbl://")
    assert data["mpos_mm"] == [-1.0, -1.0, -1.0]  # homed: pulled off the switches
    assert main(["stage", "move", "-10", "-20", "-3", "--home", "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert data["state"] == "Idle" and data["mpos_mm"] == [-10.0, -20.0, -3.0]
    for action in ("status", "unlock"):
        assert main(["stage", action, "--json"]) == 0
        data, _ = stdout_object(capsys)
        assert {"state", "mpos_mm", "url", "version"} <= set(data)


def test_capture_and_dry_run_json(tmp_path, capsys):
    grid = ["--rows", "2", "--cols", "2", "--binning", "8", "--supersample", "1"]
    assert main(["capture", str(tmp_path / "plan"), "--dry-run", *grid, "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert [m["view"] for m in data["moves"] if m["view"]] == [[0, 0], [0, 1], [1, 1], [1, 0]]  # serpentine
    assert len(data["extent_mm"]) == 3 and len(data["limits_mm"]) == 3 and data["off_step_grid"] == []
    assert "4 views" in data["summary"] and not (tmp_path / "plan").exists()
    assert main(["capture", str(tmp_path / "cap"), *grid, "--json"]) == 0
    data, err = stdout_object(capsys)
    assert data == {"path": str(tmp_path / "cap"), "views": 4, "total": 4, "taken": 4, "complete": True}
    assert "capture [" in err


def test_camera_commands_json(tmp_path, capsys):
    from tests.test_rig_snap import write_video

    video = write_video(tmp_path / "v.avi", [0, 50, 100, 150, 200, 250])
    assert main(["camera", "snap", f"opencv:{video}", "-o", str(tmp_path / "a.png"), "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert data["path"] == str(tmp_path / "a.png") and data["width"] == 64 and data["height"] == 48
    assert main(["camera", "info", f"opencv:{video}", "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert data["opens"] is True and data["width_px"] == 64
    (tmp_path / "dev").mkdir()
    assert main(["camera", "list", "--dev-dir", str(tmp_path / "dev"), "--json"]) == 0
    data, _ = stdout_object(capsys)
    assert data["opencv"] == [] and isinstance(data["aravis"], list)


def test_batch_json_holds_one_record_per_capture(tmp_path, capsys):
    import shutil

    shutil.copytree(TINY, tmp_path / "caps" / "a")
    out = tmp_path / "results"
    assert main(["batch", "reconstruct", str(tmp_path / "caps" / "a"), "-o", str(out), *FAST, "--workers", "1",
                 "--export", "none", "--json"]) == 0
    data, err = stdout_object(capsys)
    assert data["output"] == str(out) and [(c["name"], c["status"]) for c in data["captures"]] == [("a", "ok")]
    assert "[1/1] a: done" in err  # the per-capture lines go to stderr
