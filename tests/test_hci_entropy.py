"""The matching-entropy method on the benchmark scene through the command line: the issue's targets."""

import json

import numpy as np
import pytest

from rig.main import main
from recon.evaluate import score
from recon.lf.pfm import read_pfm

pytestmark = [pytest.mark.hci, pytest.mark.slow]


def test_entropy_on_backgammon_meets_the_targets_and_beats_the_baseline(hci_scene_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["reconstruct", str(hci_scene_dir), "-o", str(out), "--quiet"]) == 0  # entropy is the default
    record = json.loads((out / "result.json").read_text())
    assert record["method"] == "entropy"
    gt = read_pfm(hci_scene_dir / "gt_disp_lowres.pfm")
    scores = score(read_pfm(out / "disparity.pfm"), gt)
    assert scores["badpix_0.07"] <= 10.0
    assert scores["mse_x100"] <= 10.0
    # What the method explains itself with is there, and the region map uses all four types.
    for name in ("regions.png", "regions.npy", "window_size.npy", "window_shape.npy",
                 "initial_disparity.pfm", "refined_disparity.pfm"):
        assert (out / name).is_file(), name
    labels = np.load(out / "regions.npy")
    assert set(np.unique(labels)) == {0, 1, 2, 3}
