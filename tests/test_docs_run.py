"""The docs' commands run: every line of every shell block (```` ```sh ````) of README.md and
docs/*.md is executed here, so that no page can show a command that fails.

How each line runs:

- ``lfrig ...`` (or ``.venv/bin/lfrig ...``): through ``rig.main.main`` in a fresh folder holding the
  inputs the command names; ``camera preview`` and ``stage jog`` as a process (the preview is fetched
  once over HTTP, then stopped with Ctrl-C; jog gets its keys on a pseudo-terminal and is quit with q).
- ``.venv/bin/python -c ...``: in a shell, in such a folder.
- ``./run``, ``./test``, ``./setup.sh``: the CI runs them itself; here each script must exist, be
  executable, parse (``bash -n``) and run what the page says it runs, and ``./run``'s job,
  ``lfrig demo``, runs at a smaller size (the demo fixture below).
- ``dask scheduler`` and ``dask worker`` (``scale-out.md``): in a shell, kept running for the page's
  later lines (the scheduler without its dashboard, whose port may be taken), ended with the module.
- A block after a ``<!-- docs-run: skip (reason) -->`` line is not run (a synopsis); the reason is
  shown as the skip's. Nothing else is left out: a shell line of any other
  kind fails the test.

Substitutions, each keeping the command's meaning (``SUBSTITUTIONS``, ``HARDWARE``):

- grids become 3x3: ``--rows``/``--cols``/``--mosaic`` of the import examples (the fixture's grid), and
  ``capture`` gets ``--rows 3 --cols 3`` (the same code on fewer views);
- ``../shared`` is the shared data beside the checkout; ``LF_DIR`` is the tiny fixture capture
  (``fixtures/tiny_capture``, its truth ``fixtures/tiny_capture_truth.pfm``); ``CAPTURE...`` is
  ``captures/*`` holding a copy of it;
- the lab's hardware becomes devices nobody here wrote: ``grbl:///dev/ttyUSB0`` the real GRBL 1.1h
  firmware (``../shared/grbl-sim``) on a pty, ``aravis:Basler-12345678`` Aravis's simulated GenICam
  camera ``aravis:Fake_1`` (with ``Mono16`` for a ``Mono12`` it lacks), ``opencv:0`` and
  ``opencv:/dev/video0`` a video file read by OpenCV; the grid centre ``X Y Z`` is a position in the
  simulated stage's travel, a live view's ``--port`` a free one, the lab's scheduler machine
  (``192.168.10.5:8786``) 127.0.0.1 and a free port, and ``/lab/captures/*`` / ``/lab/results`` the
  tiny capture in ``captures/`` and ``results``;
- the demo session's files (``runs/demo/...``, ``boards/``, ``cam.cameramodel``, ``stage.json``,
  ``BOARD_CAPTURE``, ``SCENE_CAPTURE``, ``scene``, ``scene_rect``) come from one ``lfrig demo`` run at
  binning 4 with 6 boards and the baseline method;
- a folder an earlier command of the same page wrote (``OUT``, ``RESULT_DIR``, ``result``, ``out``) is
  that command's output (the tests run in the pages' order);
- the README's benchmark example runs with ``--method baseline``: its point is the benchmark's
  layout and scoring, not the estimator, whose scores ``tests/test_hci_entropy.py`` checks.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import select
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from glob import glob
from pathlib import Path

import cv2
import numpy as np
import pytest

from grbl_devices import FAST, Firmware
from recon.lf import read_lightfield
from recon.lf.importer import capture_order
from rig.main import main
from tests.conftest import SHARED, require_hci_scene, stop_process_group
from tests.test_rig_aravis import require_aravis

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "fixtures" / "tiny_capture"
TINY_TRUTH = ROOT / "fixtures" / "tiny_capture_truth.pfm"
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SKIP = re.compile(r"<!-- docs-run: skip \((.+)\) -->")
SETUP_SCRIPTS = {"./run": "lfrig demo", "./test": "pytest", "./setup.sh": "sync --frozen"}
#: The grid centre the pages leave to the lab (``X Y Z``), inside the simulated stage's travel.
CENTRE = "-50 -50 -10"
#: The simulated controller: the test suite's fast stage with 100 x 100 x 20 mm of travel.
TRAVEL = {**FAST, 130: 100, 131: 100, 132: 20}
SUBSTITUTIONS = [
    (r"--rows (9|17) --cols (9|17)", "--rows 3 --cols 3"),  # the fixture's grid
    (r"--mosaic 9x9", "--mosaic 3x3"),
    (r"\.\./shared/", f"{SHARED}/"),
    (r"\bLF_DIR/gt_disp_lowres\.pfm", str(TINY_TRUTH)),
    (r"\bLF_DIR\b", str(TINY)),
    (r"\bOLD_DIR\b", "old/"),
    (r"\bCAPTURE\.\.\.", "captures/*"),
    (r"--centre-mm X Y Z", f"--centre-mm {CENTRE}"),
    (r"aravis:Basler-12345678", "aravis:Fake_1"),
    (r"(aravis:Fake_1 .*)--pixel-format Mono12", r"\1--pixel-format Mono16"),  # Fake_1's deeper format
    (r"(reconstruct \S*backgammon -o \S+)$", r"\1 --method baseline"),
    (r"/lab/captures/\*", "captures/*"),
    (r"/lab/results\b", "results"),
]
#: The lab's devices, replaced by ``hardware`` (a :class:`Hardware`).
HARDWARE = [
    (r"grbl:///dev/ttyUSB0", lambda hw: hw.stage_url()),
    (r"opencv:(0|/dev/video0)\b", lambda hw: f"opencv:{hw.clip}"),
]
#: The lab's scheduler machine (``scale-out.md``): its address becomes 127.0.0.1 and a free port.
LAB_SCHEDULER = re.compile(r"192\.168\.10\.5(?::|\s+--port\s+)8786")
#: Flags whose value a command writes.
OUTPUT_FLAGS = ("-o", "--output", "--ply", "--depth", "--report", "--poses")
#: Names an earlier command of the same page writes and a later one reads.
PRODUCED_NAMES = ("OUT", "RESULT_DIR", "result", "out")


@dataclass(frozen=True)
class Line:
    page: str
    number: int
    text: str
    skip: str | None  # the block's skip reason

    @property
    def id(self) -> str:
        return f"{self.page}:{self.number}"


def shell_blocks(page: Path) -> list[tuple[int, list[tuple[int, str]], str | None]]:
    """``(line of the fence, [(line, command)], skip reason)`` of each ``sh`` block: comments dropped,
    continued lines joined."""
    blocks, lines = [], page.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        if lines[i].strip() == "```sh":
            before = next((lines[k] for k in range(i - 1, -1, -1) if lines[k].strip()), "")
            skip = SKIP.search(before)
            commands, j = [], i + 1
            while not lines[j].startswith("```"):
                start, command = j, lines[j].strip()
                while command.endswith("\\"):
                    j += 1
                    command = command[:-1] + " " + lines[j].strip()
                command = re.split(r"\s+#\s", " " + command + " ", maxsplit=1)[0].strip()
                if command:
                    commands.append((start + 1, command))
                j += 1
            blocks.append((i + 1, commands, skip.group(1) if skip else None))
            i = j
        i += 1
    return blocks


def documented_lines() -> list[Line]:
    return [Line(page.name, number, text, skip) for page in PAGES
            for _, commands, skip in shell_blocks(page) for number, text in commands]


LINES = documented_lines()


def test_every_command_block_is_a_shell_block():
    """A fenced block of commands without the ``sh`` tag would escape this test."""
    untagged = []
    for page in PAGES:
        fenced = None
        for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            if line.startswith("```"):
                fenced = line.strip() if fenced is None else None
                continue
            if fenced == "```" and re.match(r"(\.venv/bin/|\./|lfrig )", line.strip()):
                untagged.append(f"{page.name}:{n}: {line.strip()}")
    assert untagged == []
    assert len(LINES) >= 70 and {line.page for line in LINES} >= {"README.md", "user-guide.md", "rig.md"}


# --------------------------------------------------------------------------------------------------
# Inputs


def write_views(folder: Path, name_of, views: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for u in range(views.shape[0]):
        for v in range(views.shape[1]):
            assert cv2.imwrite(str(folder / name_of(u, v)), views[u, v][:, :, ::-1])


def write_import_source(command: str, views: np.ndarray, *, cwd: Path) -> None:
    """The views an ``import`` command reads, in the layout its flags describe."""
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


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    """One ``lfrig demo`` (``./run``'s job) at a smaller size: boards, camera model, stage, captures. Its
    ``--json`` report is ``summary.json``; on stderr, each step's lines and a progress bar for each of its
    long parts."""
    out = tmp_path_factory.mktemp("demo") / "demo"
    printed, progress = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(progress):
        assert main(["demo", "-o", str(out), "--binning", "4", "--boards", "6", "--method", "baseline", "--json"]) == 0
    assert json.loads(printed.getvalue()) == json.loads((out / "summary.json").read_text(encoding="utf-8"))
    shown = progress.getvalue()
    assert "[6/6]" in shown and all(f"{bar} [" in shown for bar in ("rendering boards", "finding corners", "capture",
                                                                     "rectify", "baseline")), shown
    return out


#: Input name -> what it is in the demo's folder.
FROM_DEMO = {"runs": ".", "boards": "boards", "cam.cameramodel": "camera.cameramodel", "stage.json": "stage.json",
             "BOARD_CAPTURE": "stage_capture", "board_capture": "stage_capture", "SCENE_CAPTURE": "capture",
             "scene": "capture", "scene_rect": "rectified"}
PRODUCED: dict[tuple[str, str], Path] = {}  # (page, name) -> a copy of what an earlier command wrote


def output_positions(words: list[str]) -> set[int]:
    """Where ``words`` name what the command writes: flags' values, and ``capture``'s folder."""
    flagged = {k + 1 for k, w in enumerate(words[:-1]) if w in OUTPUT_FLAGS}
    return flagged | ({1} if words[0] == "capture" else set())


def written(words: list[str]) -> list[str]:
    """What the command must have written (a dry run writes nothing)."""
    return [] if "--dry-run" in words else [words[k] for k in sorted(output_positions(words))]


def read(words: list[str]) -> list[str]:
    outputs = output_positions(words)
    return [w for k, w in enumerate(words) if k not in outputs and not w.startswith("-")]


def prepare(line: Line, command: str, words: list[str], *, cwd: Path, request) -> None:
    """Put in ``cwd`` the inputs ``words`` read."""
    if command.startswith("import"):
        write_import_source(command, read_lightfield(TINY).views, cwd=cwd)
    if "backgammon" in command:
        require_hci_scene()
    for word in read(words):
        head = word.split("/")[0]
        if head in FROM_DEMO and not (cwd / head).exists():
            source = request.getfixturevalue("demo") / FROM_DEMO[head]
            target = cwd / ("runs/demo" if head == "runs" else head)
            (shutil.copytree if source.is_dir() else shutil.copy)(source, target)
        elif head == "captures":
            shutil.copytree(TINY, cwd / "captures" / TINY.name)
        elif head in PRODUCED_NAMES:
            made = PRODUCED.get((line.page, head))
            if made is None:
                pytest.skip(f"{head} is written by an earlier command of {line.page}: run the whole page")
            shutil.copytree(made, cwd / head)


def expand(words: list[str], *, cwd: Path) -> list[str]:
    """The shell's globbing, relative to ``cwd``."""
    out = []
    for word in words:
        found = sorted(glob(word, root_dir=cwd)) if any(c in word for c in "*?[") else []
        out += found or [word]
    return out


# --------------------------------------------------------------------------------------------------
# Hardware


class Hardware:
    """The stand-ins for the lab's devices, made when a line needs them."""

    def __init__(self, request, folder: Path) -> None:
        self.request, self.folder = request, folder
        self.firmware: Firmware | None = None
        self.clip = folder / "camera.avi"  # a video read by OpenCV, like a V4L2 device
        writer = cv2.VideoWriter(str(self.clip), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
        ramp = np.tile(np.linspace(20, 230, 64, dtype=np.uint8), (48, 1))
        for k in range(6000):  # two minutes of a live view: 10 frames/s, each after 4 dropped (--drop-frames)
            writer.write(np.dstack([np.roll(ramp, k, axis=1)] * 3))
        writer.release()

    def stage_url(self) -> str:
        if self.firmware is None:
            self.firmware = Firmware(self.request.getfixturevalue("firmware_exe"), self.folder / "grbl",
                                     settings=TRAVEL)
        return self.firmware.url

    def close(self) -> None:
        if self.firmware is not None:
            self.firmware.close()


@pytest.fixture(scope="module")
def hardware(request, tmp_path_factory):
    made = Hardware(request, tmp_path_factory.mktemp("hardware"))
    yield made
    made.close()


class Cluster:
    """The lab's Dask scheduler and worker of ``scale-out.md``, started as the page says on 127.0.0.1 and
    a free port (each in its own process group, ended with the module)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.processes: list[subprocess.Popen] = []

    def address(self, command: str) -> str:
        """``command`` with the lab's scheduler address replaced by this one's."""
        return LAB_SCHEDULER.sub(lambda m: f"127.0.0.1{':' if ':' in m.group(0) else ' --port '}{self.port}",
                                 command)

    def start(self, command: str) -> None:
        """Run a ``dask scheduler`` or ``dask worker`` line in a shell (``$(nproc)`` and all), with the
        environment's ``dask`` first on PATH; wait until the scheduler takes connections."""
        name = "scheduler" if " scheduler " in f" {command} " else "worker"
        if name == "scheduler":
            command += " --no-dashboard"  # the page's dashboard port may be taken on a shared machine
        elif not self.processes:
            pytest.skip("the worker joins the scheduler an earlier line starts: run the whole page")
        env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}", "PYTHONPATH": str(ROOT)}
        with open(self.folder / f"{name}.log", "wb") as log:
            self.processes.append(subprocess.Popen(["bash", "-c", command], cwd=self.folder, env=env, stdout=log,
                                                   stderr=subprocess.STDOUT, start_new_session=True))
        deadline = time.monotonic() + 60
        while name == "scheduler":
            assert self.processes[-1].poll() is None, (self.folder / "scheduler.log").read_text()
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port), timeout=1):
                break
            assert time.monotonic() < deadline, "the scheduler took no connection within 60 s"
            time.sleep(0.2)
        assert self.processes[-1].poll() is None, (self.folder / f"{name}.log").read_text()

    def close(self) -> None:
        for process in reversed(self.processes):
            stop_process_group(process)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    made = Cluster(tmp_path_factory.mktemp("cluster"))
    yield made
    made.close()


def substitute(command: str, hardware: Hardware) -> str:
    for pattern, replacement in SUBSTITUTIONS:
        command = re.sub(pattern, replacement, command)
    for pattern, device in HARDWARE:
        if re.search(pattern, command):
            command = re.sub(pattern, device(hardware), command)
    if command.startswith("capture") and "--rows" not in command:
        command += " --rows 3 --cols 3"  # the same code on fewer views
    if "aravis:" in command:
        require_aravis()
    return command


# --------------------------------------------------------------------------------------------------
# Running


def lfrig_process(words: list[str], *, cwd: Path, **kwargs) -> subprocess.Popen:
    """``lfrig WORDS`` as a process; Ctrl-C (SIGINT) reaches it as from a terminal, also when the tests were
    started in the background by a shell, which leaves SIGINT ignored in its children."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "rig.main", *words], cwd=cwd, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL), **kwargs)


def run_preview(words: list[str], *, cwd: Path) -> None:
    """Serve the live view on a free port, fetch the page and a frame's readout, stop with Ctrl-C."""
    words = [w for k, w in enumerate(words) if w != "--port" and (k == 0 or words[k - 1] != "--port")]
    with open(cwd / "stderr.txt", "w") as err:
        proc = lfrig_process([*words, "--port", "0"], cwd=cwd, stdout=subprocess.PIPE, stderr=err, text=True)
    try:
        ready = proc.stdout.readline()
        url = re.search(r"(http://\S+)", ready)
        assert url, f"no address printed: {ready!r} {(cwd / 'stderr.txt').read_text()}"
        with urllib.request.urlopen(url.group(1), timeout=60) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=120) == 130, (cwd / "stderr.txt").read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def run_jog(words: list[str], *, cwd: Path) -> None:
    """Jog on a pseudo-terminal: wait for the key help, quit with q."""
    master, slave = os.openpty()
    proc = lfrig_process(words, cwd=cwd, stdin=slave, stdout=slave, stderr=slave)
    output, deadline, quit_sent = b"", time.monotonic() + 90, False
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            if select.select([master], [], [], 0.1)[0]:
                try:
                    output += os.read(master, 65536)
                except OSError:
                    break
            if not quit_sent and b"q: quit" in output:
                os.write(master, b"q")
                quit_sent = True
        assert quit_sent, f"jog showed no key help: {output[-800:]!r}"
        assert proc.wait(timeout=30) == 0, output[-800:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("line", LINES, ids=lambda line: line.id)
def test_documented_line_runs(line, tmp_path, tmp_path_factory, hardware, request, monkeypatch, capsys):
    if line.skip:
        pytest.skip(line.skip)
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    if line.text.split()[0] in SETUP_SCRIPTS:
        check_setup_script(line.text, request)
        return
    python = re.match(r"\.venv/bin/python (-c .*)", line.text)
    if python:
        (cwd / "cam.cameramodel").write_bytes((request.getfixturevalue("demo") / "camera.cameramodel").read_bytes())
        done = subprocess.run(f"{shlex.quote(sys.executable)} {python.group(1)}", shell=True, cwd=cwd,
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0 and done.stdout.strip(), done.stderr[-2000:]
        return
    dask = re.match(r"(?:\S+=\S+\s+)*dask (scheduler|worker)\b", line.text)
    if dask:
        request.getfixturevalue("cluster").start(request.getfixturevalue("cluster").address(line.text))
        return
    lfrig = re.match(r"(?:\.venv/bin/)?lfrig(?:\s+(.*))?$", line.text)
    assert lfrig, f"{line.id}: no way to run {line.text!r}: make it an lfrig command or mark its block " \
                  "<!-- docs-run: skip (reason) -->"
    command = substitute(lfrig.group(1) or "", hardware)
    if LAB_SCHEDULER.search(command):
        if not request.getfixturevalue("cluster").processes:
            pytest.skip("the scheduler is started by an earlier line of the page: run the whole page")
        command = request.getfixturevalue("cluster").address(command)
    words = shlex.split(command)
    prepare(line, command, words, cwd=cwd, request=request)
    words = expand(words, cwd=cwd)
    if words[:2] == ["camera", "preview"]:
        run_preview(words, cwd=cwd)
        return
    if words[:2] == ["stage", "jog"]:
        run_jog(words, cwd=cwd)
        return
    try:
        status = main(words)
    except SystemExit as stop:  # --help
        status = stop.code
    shown = capsys.readouterr()
    err = shown.err
    assert status == 0, f"lfrig {command}: exit {status}\n{err}"
    if "--scheduler" in words:  # the work went to the page's worker through its scheduler
        assert re.search(r"scheduler tcp://127\.0\.0\.1:\d+: 1 worker\(s\)", shown.out + err), shown.out + err
    outputs = written(words)
    assert all((cwd / p).exists() for p in outputs), f"lfrig {command}: missing one of {outputs}"
    if "--dry-run" in words:
        assert not (cwd / words[1]).exists(), f"lfrig {command}: a dry run wrote {words[1]}"
    for name in outputs:
        head = name.split("/")[0]
        if head in PRODUCED_NAMES:
            kept = tmp_path_factory.mktemp("produced") / head
            shutil.copytree(cwd / head, kept)
            PRODUCED[(line.page, head)] = kept


def check_setup_script(text: str, request) -> None:
    """``./run``, ``./test``, ``./setup.sh``: present, executable, parsed by bash, running what the
    pages say; ``./run``'s job runs (the demo fixture) and leaves its report and model."""
    script = ROOT / text.split()[0]
    assert script.is_file() and os.access(script, os.X_OK), f"{script} is missing or not executable"
    done = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert SETUP_SCRIPTS[text.split()[0]] in script.read_text(encoding="utf-8")
    if text.split()[0] != "./setup.sh":
        assert "./setup.sh" in script.read_text(encoding="utf-8"), f"{script} does not set up first"
    if text.split()[0] == "./run":
        demo = request.getfixturevalue("demo")
        assert (demo / "report" / "index.html").is_file() and (demo / "model_mesh.ply").is_file()
