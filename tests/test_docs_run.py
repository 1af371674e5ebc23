"""The docs' commands run: every ``lfrig`` line of the shell blocks of the pages listed in ``RUN`` is
executed, each in a fresh folder holding the inputs it names (made from the tiny fixture capture),
so that a page cannot show a command that fails.

Substitutions, each keeping the command's meaning (``SUBSTITUTIONS``): grids of 9x9 or 17x17 views
become the fixture's 3x3 (``--rows``, ``--cols``, ``--mosaic``); ``../shared`` is the shared data beside
the checkout; ``LF_DIR`` is the tiny capture and ``RESULT_DIR`` one reconstruction of it, shared by the
export commands. Blocks of other pages (hardware, a cluster, the lab's own paths) are checked for
commands and flags by ``tests/test_docs.py``; covering them here is open work.
"""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.lf import read_lightfield
from recon.lf.importer import capture_order
from rig.main import main
from tests.conftest import SHARED, require_hci_scene

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "fixtures" / "tiny_capture"
#: Pages whose every shell block is run here.
RUN = ("capture-format.md", "depth-and-export.md")
SUBSTITUTIONS = [
    (r"--rows (9|17) --cols (9|17)", "--rows 3 --cols 3"),  # the fixture's grid
    (r"--mosaic 9x9", "--mosaic 3x3"),
    (r"\.\./shared/", f"{SHARED}/"),
    (r"\bLF_DIR\b", str(TINY)),
]


def shell_commands(page: Path) -> list[tuple[int, str]]:
    """``(line, command after 'lfrig')`` of the ``sh`` blocks, comments dropped, continuations joined."""
    found, fenced = [], False
    lines = page.read_text(encoding="utf-8").splitlines()
    for i, line in enumerate(lines):
        if line.startswith("```"):
            fenced = line.strip() == "```sh" if not fenced else False
            continue
        if fenced and (m := re.match(r"(?:\.venv/bin/)?lfrig\s+(.*)", line.strip())):
            command = m.group(1)
            j = i
            while command.rstrip().endswith("\\"):
                j += 1
                command = command.rstrip()[:-1] + " " + lines[j].strip()
            found.append((i + 1, re.split(r"\s+#", command)[0].strip()))
    return found


def write_views(folder: Path, name_of, views: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for u in range(views.shape[0]):
        for v in range(views.shape[1]):
            assert cv2.imwrite(str(folder / name_of(u, v)), views[u, v][:, :, ::-1])


def make_inputs(command: str, views: np.ndarray, *, cwd: Path) -> None:
    """The files the command reads, in the layout its flags describe."""
    if command.startswith("import old/"):
        if "'view_{u}_{v}.png'" in command:
            write_views(cwd / "old", lambda u, v: f"view_{u}_{v}.png", views)
        elif "'img_{v:02d}-{u:02d}.tif'" in command:
            write_views(cwd / "old", lambda u, v: f"img_{v + 1:02d}-{u + 1:02d}.tif", views)
        else:
            order = "raster" if "raster" in command else "serpentine"
            named = "frame_{i:04d}.png" if "frame_" in command else "img{i}.png"
            for i, (u, v) in enumerate(capture_order(3, 3, order=order)):
                write_views(cwd / "old", lambda *_: named.format(i=i), views[u:u + 1, v:v + 1])
    elif command.startswith("import stanford/"):
        write_views(cwd / "stanford", lambda u, v: f"out_{u:02d}_{v:02d}_{-780.13 + u:.6f}_{-3355.33 + v:.6f}_.png", views)
    elif command.startswith("import views.png"):
        rows, cols, h, w = views.shape[:4]
        cv2.imwrite(str(cwd / "views.png"), views.transpose(0, 2, 1, 3, 4).reshape(rows * h, cols * w, 3)[:, :, ::-1])
    elif command.startswith("import lf.h5"):
        import h5py

        with h5py.File(cwd / "lf.h5", "w") as f:
            f.create_dataset("LF", data=views)
            f.attrs.update({"dH": 0.5, "focalLength": 1000.0, "shift": 0.0})
    elif "backgammon" in command:
        require_hci_scene()


def documented(pages=RUN):
    for name in pages:
        for line, command in shell_commands(ROOT / "docs" / name):
            yield pytest.param(command, id=f"{name}:{line}")


@pytest.fixture(scope="module")
def result_dir(tmp_path_factory) -> Path:
    """One reconstruction of the tiny capture, shared by the export commands (as in the docs' order)."""
    out = tmp_path_factory.mktemp("docs") / "RESULT_DIR"
    assert main(["reconstruct", str(TINY), "-o", str(out), "--quiet"]) == 0
    return out


def test_the_pages_have_commands():
    assert len(list(documented())) >= 15


@pytest.mark.parametrize("command", list(documented()))
def test_documented_command_runs(command, tmp_path, result_dir, monkeypatch, capsys):
    for pattern, replacement in SUBSTITUTIONS:
        command = re.sub(pattern, replacement, command)
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    make_inputs(command, read_lightfield(TINY).views, cwd=cwd)
    words = shlex.split(command)
    if "RESULT_DIR" in words:
        shutil.copytree(result_dir, cwd / "RESULT_DIR")  # export writes beside it: each command its own copy
    status = main(words)
    err = capsys.readouterr().err
    assert status == 0, f"lfrig {command}: exit {status}\n{err}"
    outputs = [words[k + 1] for k, w in enumerate(words[:-1]) if w in ("-o", "--ply", "--depth", "--report", "--poses")]
    assert outputs and all((cwd / p).exists() for p in outputs), f"lfrig {command}: missing one of {outputs}"
