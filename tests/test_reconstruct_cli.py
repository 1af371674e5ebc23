"""``lfrig reconstruct`` end to end on the committed tiny capture."""

import json
from pathlib import Path

import numpy as np
import pytest

from rig.main import main
from recon.lf.pfm import read_pfm

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def test_reconstruct_writes_results_and_a_ply(tmp_path, capsys):
    out = tmp_path / "out"
    status = main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(out), "--method", "baseline",
                   "--window", "5", "--quiet", "--ply", str(out / "model.ply")])
    assert status == 0
    for name in ("disparity.pfm", "disparity.png", "centre_view.png", "result.json", "model.ply"):
        assert (out / name).is_file(), name
    record = json.loads((out / "result.json").read_text())
    assert record["method"] == "baseline" and record["focal_px"] == 1000.0 and record["pitch_mm"] == 0.5
    estimate = read_pfm(out / "disparity.pfm")
    truth = read_pfm(FIXTURES / "tiny_capture_truth.pfm")
    # The front square's inside is recovered; the capture is tiny, so only its centre is asked for.
    assert np.median(np.abs(estimate[13:19, 13:19] - truth[13:19, 13:19])) < 0.05
    assert "mesh" in capsys.readouterr().out


def test_reconstruct_rejects_an_inverted_range(tmp_path, capsys):
    status = main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(tmp_path), "--disparity-range", "1", "-1"])
    assert status == 2 and "MIN must be less than MAX" in capsys.readouterr().err


def test_an_option_the_method_rejects_is_a_one_line_error(tmp_path, capsys):
    status = main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(tmp_path / "o"), "--method", "baseline",
                   "--window", "4"])
    assert status == 2 and "baseline: window must be an odd number" in capsys.readouterr().err
    assert not (tmp_path / "o" / "disparity.pfm").exists()  # refused before any work


def test_a_bug_inside_an_estimator_keeps_its_traceback(tmp_path, monkeypatch):
    """A ValueError raised while the estimate runs is a bug, not a user's mistake: it is not turned
    into a one-line LfrigError."""
    import pytest

    import recon.baseline
    from recon.pipeline import reconstruct_to_folder

    def broken(*args, **kwargs):
        raise ValueError("operands could not be broadcast together")

    monkeypatch.setattr(recon.baseline, "estimate_baseline", broken)
    with pytest.raises(ValueError, match="broadcast"):
        reconstruct_to_folder(FIXTURES / "tiny_capture", tmp_path / "o", method="baseline", options={"window": 5})


def test_help_shows_the_everyday_flags_and_help_tuning_every_option_by_step(capsys):
    import dataclasses

    from recon.entropy.options import GROUPS, TITLES

    assert main(["reconstruct", "--help"]) == 0
    everyday = capsys.readouterr().out
    assert len(everyday.splitlines()) < 100
    for flag in ("--method", "--preset", "--disparity-range", "--step", "--output", "--help-tuning"):
        assert flag in everyday, flag
    assert "--gamma" not in everyday and "--boundary-mix" not in everyday
    assert main(["reconstruct", "--help-tuning"]) == 0
    tuning = capsys.readouterr().out
    for step, group in GROUPS.items():
        assert f"{step} ({TITLES[step]})" in tuning
        for f in dataclasses.fields(group):
            if f.name not in ("disparity_range", "step"):
                assert "--" + f.name.replace("_", "-") in tuning, f.name


@pytest.mark.parametrize("argv", [
    ["--occlusion-views", "foo"], ["--disparity-bin", "0"], ["--initial-window", "4"],
    ["--intensity-scale", "0"], ["--initial-range", "5", "-5"], ["--gamma", "-1"], ["--tv-iterations", "-1"],
])
def test_a_bad_tuning_value_is_refused_while_parsing(tmp_path, capsys, monkeypatch, argv):
    """Issue #22, point 9: one line, exit 2, before the light field is even read."""
    import recon.lf

    monkeypatch.setattr(recon.lf, "read_lightfield", lambda *a, **k: pytest.fail("read before the check"))
    status = main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(tmp_path / "out"), "--quiet", *argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1 and lines[0].startswith("lfrig: error:"), err
    assert argv[0] in lines[0] and argv[0][2:].replace("-", "_") in lines[0]
    assert not (tmp_path / "out").exists()


def test_tuning_flags_still_reach_the_estimator(tmp_path):
    out = tmp_path / "out"
    assert main(["reconstruct", str(FIXTURES / "tiny_capture"), "-o", str(out), "--quiet", "--preset", "paper",
                 "--gamma", "0.3", "--window-sizes", "3", "5", "--no-boundary-snap"]) == 0
    options = json.loads((out / "result.json").read_text())["options"]
    assert options["gamma"] == 0.3 and options["window_sizes"] == [3, 5] and options["boundary_snap"] is False
    assert options["grey_bins"] == 256  # the preset's


def test_the_views_read_as_grey_give_the_files_of_the_views_as_stored(tmp_path):
    """``reconstruct_to_folder`` reads a folder's views as grey and filters them in place (a noisy
    wall: both view filters act): every file but ``result.json`` is the same, byte for byte, as
    from the light field read as stored, 8-bit RGB."""
    from recon.lf import read_lightfield, write_lightfield
    from recon.lf.lightfield import LightField
    from recon.pipeline import reconstruct_to_folder
    from recon.synthetic import Layer, noise_texture, render

    rng = np.random.default_rng(5)
    wall = np.full((48, 64), 0.5, np.float32)  # a plain wall under noise, a textured and a faint patch
    wall[6:24, 8:40] = noise_texture((18, 32), seed=2)
    wall[28:46, 30:60] += 0.02 * noise_texture((18, 30), seed=3)
    lf, _ = render([Layer(wall, 0.4)])
    grey = lf.views + rng.normal(0, 0.01, lf.views.shape).astype(np.float32)
    rgb = np.stack([grey, 0.9 * grey, 1.1 * grey], axis=-1)
    views = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
    write_lightfield(tmp_path / "cap", LightField(views=views, pitch_mm=0.5, focal_px=100.0))
    from_folder = reconstruct_to_folder(tmp_path / "cap", tmp_path / "grey")
    as_stored = reconstruct_to_folder(read_lightfield(tmp_path / "cap"), tmp_path / "stored")
    assert from_folder.files == as_stored.files and len(from_folder.files) > 5
    for name in from_folder.files:
        if name != "result.json":
            assert (tmp_path / "grey" / name).read_bytes() == (tmp_path / "stored" / name).read_bytes(), name
