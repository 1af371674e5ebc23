"""The committed fixtures still read, and still match what their script renders."""

import importlib.util
from pathlib import Path

import numpy as np

from rig.main import main
from recon.lf import read_lightfield
from recon.lf.pfm import read_pfm

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def load_generator():
    spec = importlib.util.spec_from_file_location("make_fixtures", FIXTURES / "make_fixtures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_capture_reads_and_matches_its_generator():
    lf = read_lightfield(FIXTURES / "tiny_capture")
    fresh, truth = load_generator().tiny_capture()
    np.testing.assert_array_equal(lf.views, fresh.views)
    np.testing.assert_array_equal(read_pfm(FIXTURES / "tiny_capture_truth.pfm"), truth)
    assert lf.grid_shape == (3, 3) and lf.pitch_mm == 0.5 and lf.focal_px == 1000.0


def test_info_on_a_capture(capsys):
    assert main(["info", str(FIXTURES / "tiny_capture")]) == 0
    out = capsys.readouterr().out
    assert "lfrig-capture layout" in out and "3 x 3 views" in out and "32 x 32 px, RGB, 8-bit" in out
