"""The command's fixed costs: what ``lfrig --help`` loads, and the docs' speed table of
``bench/command_speed.py`` (its markers and format; the numbers are the script's)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

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


def test_a_process_that_ran_the_command_skips_the_final_collections():
    # An object kept alive only by a reference cycle is found by the interpreter's collections at
    # exit (its __del__ runs); after rig.main.main they leave the objects of that moment alone.
    code = ("import sys\n"
            "from rig.main import main\n"
            "if sys.argv[1] == 'ran':\n"
            "    import contextlib, io\n"
            "    with contextlib.redirect_stdout(io.StringIO()):\n"
            "        main(['--help'])\n"
            "class Cycle:\n"
            "    def __del__(self):\n"
            "        print('collected', flush=True)\n"
            "c = Cycle(); c.me = c; del c\n")
    ends = {how: subprocess.run([sys.executable, "-c", code, how], cwd=ROOT, capture_output=True, text=True,
                                check=True).stdout for how in ("ran", "not")}
    assert ends == {"ran": "", "not": "collected\n"}


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
            "    raise SystemExit('no AttributeError')\n"
            "assert 'recon.entropy.estimate' in sys.modules")
    # The estimator's modules bring numpy; numba waits for a kernel's first call (recon.jit).
    assert _loaded_by(code) == ["cv2", "numpy"]


def _bench():
    """``bench/command_speed.py`` as a module (bench/ is not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("command_speed", ROOT / "bench" / "command_speed.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_the_docs_speed_table_is_the_scripts_block():
    bench = _bench()
    block = bench.table_block(bench.DOC.read_text(encoding="utf-8"))
    assert bench.check_block(block) == []
    cases = [line.split(" | ")[0].lstrip("| ") for line in block.splitlines() if bench.ROW.match(line)]
    assert set(cases) <= set(bench.CASES) and {"help", "backgammon", "baseline"} <= set(cases)


def test_the_block_is_rewritten_in_place_and_a_hand_edit_is_caught(tmp_path):
    bench = _bench()
    report = {"date": "2026-01-02", "runs": 3, "machine": {"cpu": "CPU", "cores": 2, "memory_gib": 24.0,
                                                          "python": "3.12.1", "numba": "0.60.0"},
              "results": [{"case": "help", "command": "lfrig --help", "wall_s": 0.31, "cpu_s": 0.2, "peak_mib": 23.4,
                           "load_before": [0.5, 0, 0], "load_after": [0.7, 0, 0]}]}
    doc = tmp_path / "page.md"
    doc.write_text(f"# Page\n\nbefore\n\n{bench.BEGIN}\nold\n{bench.END}\n\nafter\n", encoding="utf-8")
    bench.update_docs(report, doc)
    text = doc.read_text(encoding="utf-8")
    assert text.startswith("# Page\n\nbefore\n\n") and text.endswith("\n\nafter\n") and "old" not in text
    block = bench.table_block(text)
    assert "| help | `lfrig --help` | 0.31 | 0.20 | 23 |" in block and bench.check_block(block) == []
    assert bench.check_block(block.replace("| 0.31 |", "| fast |")) != []  # a number written by hand as a word
    assert bench.check_block(block.replace("| wall s |", "| seconds |")) != []
    with pytest.raises(ValueError):
        bench.table_block(text.replace(bench.END, ""))


def _run_bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "bench" / "command_speed.py"), *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


def test_against_another_checkout_alternates_the_runs_and_reports_both_sides(tmp_path):
    # this checkout against itself (a tree of lfrig's sources): both sides timed, as many runs each
    report = tmp_path / "ab.json"
    done = _run_bench("--cases", "help", "--runs", "2", "--work", str(tmp_path / "work"), "--against", str(ROOT),
                      "--json", str(report))
    assert done.returncode == 0, done.stderr
    assert "wall ratio" in done.stdout
    (result,) = json.loads(report.read_text(encoding="utf-8"))["results"]
    assert result["case"] == "help" and result["against_tree"] == str(ROOT)
    for side in ("this", "against"):
        assert len(result[side]["runs"]) == 2 and result[side]["wall_s"] > 0 and result[side]["peak_mib"] > 0


def test_against_refuses_a_folder_that_is_no_checkout_and_the_docs_table(tmp_path):
    done = _run_bench("--cases", "help", "--work", str(tmp_path / "work"), "--against", str(tmp_path))
    assert done.returncode != 0 and "not a checkout of lfrig" in done.stderr
    done = _run_bench("--cases", "help", "--work", str(tmp_path / "work"), "--against", str(ROOT), "--update-docs")
    assert done.returncode != 0 and "leave out --update-docs" in done.stderr


def test_the_timeline_marks_each_part_of_a_fresh_reconstruction_in_order():
    # bench/command_timeline.py on the tiny capture with the baseline: every mark, in the order the
    # command passes them (the warm-up's readiness only after it started; the estimate after both
    # the views and the warm-up).
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "command_timeline.py"), str(ROOT / "fixtures" / "tiny_capture"),
                          "--runs", "1", "--", "--method", "baseline", "--window", "3"],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    marks = dict(line.rsplit(None, 1) for line in run.stdout.splitlines()[2:])
    marks = {name.strip(): float(value) for name, value in marks.items()}
    order = ["imports done", "command starts", "reading starts", "views read", "estimate starts", "estimate done",
             "result folder written", "main returned"]
    assert [marks[name] for name in order] == sorted(marks[name] for name in order)
    assert marks["warm-up starts"] <= marks["warm-up ready"] <= marks["estimate starts"]
    assert marks["process, from outside"] >= marks["main returned"]
