"""The baseline on the benchmark scene through the command line, as a user runs it."""

import json

import numpy as np
import pytest

from rig.main import main
from recon.lf.pfm import read_pfm

pytestmark = [pytest.mark.hci, pytest.mark.slow]


def test_reconstruct_and_evaluate_backgammon(hci_scene_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["reconstruct", str(hci_scene_dir), "-o", str(out), "--method", "baseline", "--quiet"]) == 0
    assert (out / "disparity.png").is_file()
    capsys.readouterr()
    assert main(["evaluate", str(out / "disparity.pfm"), str(hci_scene_dir / "gt_disp_lowres.pfm"), "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["badpix_0.07"] <= 25.0
    assert scores["mse_x100"] <= 45.0
    # Sign and orientation: the estimate as written is far closer to the truth than the same map
    # negated or flipped either way.
    est = read_pfm(out / "disparity.pfm")[15:-15, 15:-15]
    gt = read_pfm(hci_scene_dir / "gt_disp_lowres.pfm")[15:-15, 15:-15]
    error = np.median(np.abs(est - gt))
    assert error < 0.03
    for wrong in (-est, est[::-1], est[:, ::-1]):
        assert np.median(np.abs(wrong - gt)) > 5 * error
