"""``lfrig reconstruct`` end to end on the committed tiny capture."""

import json
from pathlib import Path

import numpy as np

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
