"""``--config FILE``: method options from a TOML file or a result.json; a flag wins over the file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recon.cli import method_options
from recon.lf.pfm import read_pfm
from rig.main import build_parser, main

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
TINY = FIXTURES / "tiny_capture"


def record(folder: Path) -> dict:
    return json.loads((folder / "result.json").read_text())


def one_error_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("lfrig: error:"), captured.err
    return lines[0]


@pytest.mark.parametrize("flags", [
    ["--method", "baseline", "--window", "5", "--step", "0.1"],
    ["--window-sizes", "3", "5", "7", "--no-joint", "--gamma", "0.3"],  # entropy (the default method)
])
def test_a_result_json_reproduces_its_map(tmp_path, flags):
    first, again = tmp_path / "first", tmp_path / "again"
    assert main(["reconstruct", str(TINY), "-o", str(first), *flags, "--quiet"]) == 0
    assert main(["reconstruct", str(TINY), "-o", str(again), "--config", str(first / "result.json"), "--quiet"]) == 0
    assert record(again)["method"] == record(first)["method"]
    assert record(again)["options"] == record(first)["options"]
    assert np.array_equal(read_pfm(again / "disparity.pfm"), read_pfm(first / "disparity.pfm"), equal_nan=True)


def test_toml_options_and_a_flag_wins(tmp_path):
    toml = tmp_path / "fast.toml"
    toml.write_text('method = "baseline"\nwindow = 3\nstep = 0.1\ndisparity_range = [-1, 1.5]\n')
    out = tmp_path / "out"
    assert main(["reconstruct", str(TINY), "-o", str(out), "--config", str(toml), "--window", "5", "--quiet"]) == 0
    rec = record(out)
    assert rec["method"] == "baseline"
    assert rec["options"]["window"] == 5 and rec["options"]["step"] == 0.1
    assert rec["options"]["disparity_range"] == [-1.0, 1.5]


def test_booleans_and_lists_become_the_entropy_options():
    parser = build_parser()
    path = FIXTURES.parent / "docs" / "examples" / "entropy-options.toml"
    args = parser.parse_args(["batch", "reconstruct", str(TINY), "-o", "unused", "--config", str(path), "--gamma", "0.5"])
    options = method_options(args)
    assert args.method == "entropy"
    assert options["preset"] == "paper" and options["window_sizes"] == (3, 5, 7, 9) and options["joint"] is False
    assert options["gamma"] == 0.5  # the flag, not the file's 0.3


@pytest.mark.parametrize("text, expected", [
    ("windw = 3\n", "unknown option 'windw'; did you mean 'window'?"),
    ("window_size = [3, 5]\n", "did you mean 'window_sizes'?"),
    ("window = 0\n", "option 'window': argument --window: 0 is not a positive integer"),
    ("window_sizes = [3.5]\n", "option 'window_sizes': argument --window-sizes: invalid int value: '3.5'"),
    ("method = \"sgm\"\n", "option 'method': argument --method: invalid choice: 'sgm'"),
    ("gamma = nan\n", "option 'gamma': argument --gamma: 'nan' is not a finite number"),
    ("[windows]\nwindow_sizes = [3]\n", "[windows] is a table"),
    ("window = \n", "not valid TOML"),
])
def test_bad_options_files_are_one_line(tmp_path, capsys, text, expected):
    toml = tmp_path / "bad.toml"
    toml.write_text(text)
    assert main(["reconstruct", str(TINY), "-o", str(tmp_path / "out"), "--config", str(toml), "--quiet"]) == 2
    line = one_error_line(capsys)
    assert str(toml) in line and expected in line, line
    assert not (tmp_path / "out").exists()


def test_missing_and_json_options_files(tmp_path, capsys):
    assert main(["reconstruct", str(TINY), "-o", str(tmp_path / "out"), "--config", str(tmp_path / "none.toml")]) == 2
    assert "no such options file" in one_error_line(capsys)
    (tmp_path / "list.json").write_text("[1, 2]")
    assert main(["reconstruct", str(TINY), "-o", str(tmp_path / "out"), "--config", str(tmp_path / "list.json")]) == 2
    assert "one object of option names" in one_error_line(capsys)
    (tmp_path / "plain.json").write_text('{"method": "baseline", "window": 3, "step": 0.25}')
    assert main(["reconstruct", str(TINY), "-o", str(tmp_path / "out"), "--config", str(tmp_path / "plain.json"),
                 "--quiet"]) == 0
    assert record(tmp_path / "out")["options"]["window"] == 3
