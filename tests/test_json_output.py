"""``--json``: a reporting command prints one JSON object on stdout; progress and warnings go to stderr."""

from __future__ import annotations

import json
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
