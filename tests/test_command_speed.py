"""The command's fixed costs: what ``lfrig --help`` loads, and the docs' speed table of
``bench/command_speed.py`` (its markers and format; the numbers are the script's)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Modules that only the work itself needs: a command's parser and its --help load none of them.
HEAVY = ("numba", "llvmlite", "numpy", "scipy", "cv2", "open3d", "dask", "distributed", "mrcal", "matplotlib")


def _loaded_by(code: str) -> list[str]:
    """The top-level packages of :data:`HEAVY` in ``sys.modules`` after ``code`` runs in a fresh interpreter."""
    probe = (f"import sys\n{code}\n"
             f"import json; print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))))")
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_help_loads_no_numba_numpy_or_opencv():
    code = ("from rig.main import main\n"
            "import contextlib, io\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    assert main(['--help']) == 0\n"
            "    assert main(['reconstruct', '--help']) == 0\n"
            "    assert main(['export', '--help']) == 0")
    assert _loaded_by(code) == []


def test_the_package_names_still_load_on_use():
    """``recon.lf`` and ``recon.entropy`` keep their names; the modules behind them load when used."""
    code = ("import recon.lf, recon.entropy\n"
            "assert 'numba' not in sys.modules and 'cv2' not in sys.modules\n"
            "from recon.lf import LightField, read_lightfield, read_ground_truth, write_lightfield\n"
            "from recon.entropy import estimate_disparity, write_outputs, EntropyResult, DEFAULTS\n"
            "assert recon.entropy.estimate_disparity is estimate_disparity\n"
            "try:\n"
            "    recon.lf.no_such_name\n"
            "except AttributeError:\n"
            "    pass\n"
            "else:\n"
            "    raise SystemExit('no AttributeError')")
    assert "numba" in _loaded_by(code)
