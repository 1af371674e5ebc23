"""Property-based mutation tests of every loader and of the command line's argument checking (#13).

A seeded mutation fuzzer (hypothesis, ``derandomize=True``: the same examples on every run, no
example database) damages valid files the way disks, editors and half-finished writes do (flipped,
inserted, deleted and truncated bytes; JSON values replaced by NaN, huge, negative, wrongly typed or
missing ones; INI values replaced by junk) and feeds them to each loader: ``manifest.jsonl`` and the
views of a capture, ``parameters.cfg``, PFM, ``result.json``, ``stage.json``, mrcal camera models,
PNG images, depth maps (PNG with its scale, PFM, NPY). Argument vectors are drawn from each command's flags with good and bad values.

The properties:

- a loader returns or raises :class:`recon.errors.LfrigError` (or a subclass), nothing else;
- ``lfrig`` exits 0, or prints exactly one line starting ``lfrig: error:`` and exits 2 (expensive
  work is replaced by a stand-in that only records that validation let the values through);
- nothing is written outside the example's own folder, and nothing is read outside it apart from
  Python, the installed packages and the system (an audit hook watches every ``open``).

Bounded for CI: the whole file runs in well under a minute on a loaded 2-core machine.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import random
import shutil
import sys
import tempfile
import threading
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon.errors import LfrigError

ROOT = Path(__file__).resolve().parents[1]
TINY_CAPTURE = ROOT / "fixtures" / "tiny_capture"
TRUTH = ROOT / "fixtures" / "tiny_capture_truth.pfm"

FUZZ = settings(derandomize=True, database=None, deadline=None, max_examples=60,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                       HealthCheck.data_too_large])

# --------------------------------------------------------------------------------------------------
# nothing read or written outside the example's folder: an audit hook on every open


class FileAudit:
    """Records every file opened (and removed, renamed, made) while :attr:`active`."""

    def __init__(self) -> None:
        self.active = False
        self.events: list[tuple[str, str, bool]] = []  # (event, path, writes)
        #: Opens of a path that was a symbolic link at the time, without O_NOFOLLOW: (path, writes).
        self.followed: list[tuple[str, bool]] = []

    def hook(self, event: str, args: tuple) -> None:
        if not self.active:
            return
        if event == "open":
            path, mode, flags = args
            if isinstance(path, int):
                return
            writes = bool((mode and any(c in mode for c in "wax+"))
                          or (flags or 0) & (os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC))
            path = os.fsdecode(path)
            if (flags or 0) & os.O_NOFOLLOW:
                # cannot follow a link at its last component (a link there fails with ELOOP): judge
                # where it is, not where a link of that name leads
                path = os.path.join(os.path.realpath(os.path.dirname(os.path.abspath(path))), os.path.basename(path))
                self.events.append(("open-nofollow", path, writes))
                return
            if os.path.islink(path):
                self.followed.append((path, writes))
            self.events.append((event, path, writes))
        elif event in ("os.remove", "os.rename", "os.mkdir", "os.rmdir", "shutil.rmtree", "os.truncate"):
            path = args[0]
            if not isinstance(path, int):
                self.events.append((event, os.fsdecode(path), True))

    @contextlib.contextmanager
    def watch(self):
        self.events.clear()
        self.followed.clear()
        self.active = True
        try:
            yield self
        finally:
            self.active = False

    def outside(self, folder: Path) -> list[tuple[str, str, bool]]:
        """Events outside ``folder``: any write; reads other than Python's, the packages' and the system's."""
        allowed_reads = tuple(str(Path(p).resolve()) for p in {sys.prefix, sys.base_prefix, sys.exec_prefix}) + (
            str(ROOT / "recon"), str(ROOT / "rig"), str(ROOT / "calib"), "/usr", "/lib", "/etc", "/proc", "/sys",
            "/dev/null", "/dev/urandom", "/dev/shm")
        compiled_caches = tuple(str(ROOT / package) + os.sep for package in ("recon", "rig", "calib"))
        bad = []
        for event, path, writes in self.events:
            if event == "open-nofollow":
                resolved = path
            else:
                resolved = str(Path(os.path.abspath(path)).resolve()) if path else path
            if resolved.startswith(str(folder.resolve()) + os.sep) or resolved == str(folder.resolve()):
                continue
            if not writes and resolved.startswith(allowed_reads):
                continue
            if resolved.startswith(compiled_caches) and "__pycache__" in Path(resolved).parts:
                continue  # lfrig's own bytecode and numba's cache (numba probes it with a temporary file)
            bad.append((event, path, writes))
        return bad


AUDIT = FileAudit()
sys.addaudithook(AUDIT.hook)


def fresh_folder(base: Path) -> Path:
    return Path(tempfile.mkdtemp(dir=base))


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def call_loader(folder: Path, load) -> object:
    """Run ``load()``: it returns or raises LfrigError, touching nothing outside ``folder``."""
    with AUDIT.watch():
        try:
            result = load()
        except LfrigError as error:
            assert str(error) and "\n" not in str(error).strip(), repr(error)
            result = error
    outside = AUDIT.outside(folder)
    assert not outside, f"touched outside {folder}: {outside[:5]}"
    return result


# --------------------------------------------------------------------------------------------------
# mutations

INTERESTING = [None, True, False, 0, -1, 1, 3, 100000, 2**63, -(2**63), 1e308, -1e308, float("nan"),
               float("inf"), float("-inf"), -0.0, 1e-300, 0.5, "", "x", "0.5", "\udcff", [], [0], [1, 2, 3],
               [[1], [2, 3]], {}, {"rows": 3}]
TOKENS = ["nan", "inf", "-inf", "-1", "0", "0.0", "1e308", "1e-308", "100000", "-100000", "abc", "", "3",
          "0.5", "1e3", "0x10", "\u00ff", "[x]", "= =", "9" * 400]


def byte_mutation(rng: random.Random, data: bytes) -> bytes:
    """1-4 of: flip a byte, overwrite a run, insert bytes, delete a range, truncate, duplicate a range."""
    out = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.choice(["flip", "overwrite", "insert", "delete", "truncate", "duplicate"])
        n = len(out)
        at = rng.randint(0, max(0, n - 1))
        if op == "flip" and n:
            out[at] ^= rng.randint(1, 255)
        elif op == "overwrite":
            chunk = rng.randbytes(rng.randint(1, 16))
            out[at:at + len(chunk)] = chunk
        elif op == "insert":
            out[at:at] = rng.randbytes(rng.randint(1, 16))
        elif op == "delete":
            del out[at:at + rng.randint(1, 64)]
        elif op == "truncate":
            del out[at:]
        elif op == "duplicate":
            out[at:at] = out[at:at + rng.randint(1, 64)]
    return bytes(out)


def _paths(value, prefix=()):
    yield prefix
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _paths(item, prefix + (key,))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _paths(item, prefix + (i,))


def json_mutation(rng: random.Random, value):
    """Replace, delete or wrap the value at a random place in a JSON document (1-3 times)."""
    value = json.loads(json.dumps(value))
    for _ in range(rng.randint(1, 3)):
        paths = [p for p in _paths(value) if p]
        if not paths:
            return rng.choice(INTERESTING)
        path = rng.choice(paths)
        parent = value
        for key in path[:-1]:
            parent = parent[key]
        key = path[-1]
        op = rng.choice(["replace", "replace", "delete", "wrap"])
        if op == "replace":
            parent[key] = rng.choice(INTERESTING)
        elif op == "delete":
            del parent[key]
        else:
            parent[key] = [parent[key]]
    return value


def dump_json(value) -> bytes:
    return json.dumps(value).encode("utf-8", "surrogatepass")


def ini_mutation(rng: random.Random, text: str) -> bytes:
    """Replace values by junk, delete lines, add section headers or junk lines (1-3 times)."""
    lines = text.splitlines()
    for _ in range(rng.randint(1, 3)):
        values = [i for i, line in enumerate(lines) if "=" in line]
        op = rng.choice(["value", "value", "value", "delete", "section", "garbage"])
        if op == "value" and values:
            i = rng.choice(values)
            lines[i] = lines[i].split("=")[0] + "= " + rng.choice(TOKENS)
        elif op == "delete" and lines:
            del lines[rng.randint(0, len(lines) - 1)]
        elif op == "section":
            lines.insert(rng.randint(0, len(lines)), rng.choice(["[extrinsics]", "[lfrig]", "[", "[]"]))
        else:
            lines.insert(rng.randint(0, len(lines)), rng.choice(TOKENS))
    return "\n".join(lines).encode("utf-8", "surrogateescape")


def rng_of(data) -> random.Random:
    """A seeded generator for one example: hypothesis draws the seed (derandomized: the same seeds on
    every run), the mutations use it. Reproduce a failure with ``random.Random(seed)``."""
    return random.Random(data.draw(st.integers(0, 2**32 - 1), label="seed"))


# --------------------------------------------------------------------------------------------------
# the loaders


def copy_capture(base: Path) -> tuple[Path, Path]:
    folder = fresh_folder(base)
    shutil.copytree(TINY_CAPTURE, folder / "cap")
    return folder, folder / "cap"


@FUZZ
@given(data=st.data())
def test_manifest_mutations(base, data):
    from recon.lf import read_lightfield

    folder, cap = copy_capture(base)
    lines = (cap / "manifest.jsonl").read_text().splitlines()
    rng = rng_of(data)
    if rng.random() < 0.7:
        i = rng.randint(0, len(lines) - 1)
        lines[i] = dump_json(json_mutation(rng, json.loads(lines[i]))).decode("utf-8", "surrogateescape")
        raw = ("\n".join(lines) + "\n").encode("utf-8", "surrogateescape")
    else:
        raw = byte_mutation(rng, (cap / "manifest.jsonl").read_bytes())
    (cap / "manifest.jsonl").write_bytes(raw)
    call_loader(folder, lambda: read_lightfield(cap))


@settings(FUZZ, max_examples=200)
@given(data=st.data())
def test_parameters_mutations(base, data):
    from recon.lf import read_lightfield

    folder, cap = copy_capture(base)
    text = (cap / "parameters.cfg").read_text()
    rng = rng_of(data)
    raw = ini_mutation(rng, text) if rng.random() < 0.85 else byte_mutation(rng, text.encode())
    (cap / "parameters.cfg").write_bytes(raw)
    # as a capture, and as a benchmark folder with the same views and parameters
    bench = folder / "bench"
    bench.mkdir()
    for i, view in enumerate(sorted((cap / "views").iterdir())):
        shutil.copy(view, bench / f"input_Cam{i:03d}.png")
    shutil.copy(cap / "parameters.cfg", bench / "parameters.cfg")
    for source in (cap, bench):
        lf = call_loader(folder, lambda: read_lightfield(source))
        if not isinstance(lf, LfrigError):
            for name in ("pitch_mm", "focal_px"):
                value = getattr(lf, name)
                assert value is None or (math.isfinite(value) and value > 0), (name, value)
            assert math.isfinite(lf.disparity_offset)


@FUZZ
@given(data=st.data())
def test_pfm_mutations(base, data):
    from recon.lf.pfm import read_pfm

    folder = fresh_folder(base)
    original = TRUTH.read_bytes()
    rng = rng_of(data)
    if rng.random() < 0.5:
        header = original[:40].split(b"\n")[:3]
        body = original[len(b"\n".join(header)) + 1:]
        tokens = b" ".join(header).split()
        tokens[rng.randint(0, len(tokens) - 1)] = rng.choice(TOKENS).encode("utf-8", "surrogateescape")
        raw = b"\n".join([tokens[0], b" ".join(tokens[1:3]), b" ".join(tokens[3:])]) + b"\n" + body
    else:
        raw = byte_mutation(rng, original)
    (folder / "x.pfm").write_bytes(raw)
    call_loader(folder, lambda: read_pfm(folder / "x.pfm"))


def write_result_folder(folder: Path) -> dict:
    from recon.lf.imageio import write_png
    from recon.lf.pfm import write_pfm

    result = folder / "res"
    result.mkdir()
    write_pfm(result / "disparity.pfm", np.zeros((16, 16), np.float32))
    write_png(result / "centre_view.png", np.zeros((16, 16, 3), np.uint8))
    write_png(result / "mask.png", np.full((16, 16), 255, np.uint8))
    record = {"method": "baseline", "options": {"window": 3}, "source": None, "image": [16, 16], "grid": [3, 3],
              "focal_px": 1000.0, "pitch_mm": 0.5, "disparity_offset": 0.0, "principal_point_px": [7.5, 7.5],
              "disparity_png_range": [-1.0, 1.0], "seconds": 0.1, "mask": "mask.png"}
    return record


@FUZZ
@given(data=st.data())
def test_result_json_mutations(base, data):
    from recon.result import read_result

    folder = fresh_folder(base)
    record = write_result_folder(folder)
    rng = rng_of(data)
    raw = dump_json(json_mutation(rng, record)) if rng.random() < 0.7 else byte_mutation(rng, dump_json(record))
    (folder / "res" / "result.json").write_bytes(raw)
    result = call_loader(folder, lambda: read_result(folder / "res"))
    if not isinstance(result, LfrigError):
        call_loader(folder, lambda: result.camera())


def stage_record() -> dict:
    from calib import stage

    return {"format": stage.FORMAT, "version": stage.VERSION, "grid": [9, 9], "pitch_mm": 0.5,
            "step_u_mm": [0.0, 0.5, 0.0], "step_v_mm": [0.5, 0.0, 0.0], "r_cam_board": [0.0, 0.0, 0.0],
            "t_cam_board_mm": [0.0, 0.0, 1000.0], "rms_px": 0.1, "max_px": 0.3, "n_views": 81, "n_corners": 100,
            "n_outliers": 0, "skipped": [], "per_view_rms_px": {"u00_v00": 0.1}, "lensmodel": "LENSMODEL_PINHOLE",
            "intrinsics": [1000.0, 1000.0, 15.5, 15.5]}


@FUZZ
@given(data=st.data())
def test_stage_json_mutations(base, data):
    from calib.stage import StageCalibration

    folder = fresh_folder(base)
    rng = rng_of(data)
    raw = (dump_json(json_mutation(rng, stage_record())) if rng.random() < 0.7
           else byte_mutation(rng, dump_json(stage_record())))
    (folder / "stage.json").write_bytes(raw)
    stage = call_loader(folder, lambda: StageCalibration.load(folder / "stage.json"))
    if not isinstance(stage, LfrigError):
        assert stage.pitch_u_mm > 0 and stage.pitch_v_mm > 0 and math.isfinite(stage.tilt_deg)


@pytest.fixture(scope="module")
def model_text(tmp_path_factory) -> str:
    import mrcal

    path = tmp_path_factory.mktemp("model") / "cam.cameramodel"
    mrcal.cameramodel(intrinsics=("LENSMODEL_OPENCV4", np.array([1000.0, 1000.0, 15.5, 15.5, 0, 0, 0, 0])),
                      imagersize=np.array([32, 32]), extrinsics_rt_fromref=np.zeros(6)).write(str(path))
    return path.read_text()


@settings(FUZZ, max_examples=150)
@given(data=st.data())
def test_camera_model_mutations(base, model_text, data):
    from calib.stage import load_model

    folder = fresh_folder(base)
    rng = rng_of(data)
    if rng.random() < 0.6:
        import re

        numbers = list(re.finditer(r"-?\d+(\.\d+)?(e-?\d+)?", model_text))
        match = rng.choice(numbers)
        raw = (model_text[:match.start()] + rng.choice(["0", "-1", "nan", "inf", "1e308", "-0", "'x'", "[]"])
               + model_text[match.end():]).encode()
    else:
        raw = byte_mutation(rng, model_text.encode())
    (folder / "cam.cameramodel").write_bytes(raw)
    model = call_loader(folder, lambda: load_model(folder / "cam.cameramodel"))
    if not isinstance(model, LfrigError):
        _, intrinsics = model.intrinsics()
        assert np.isfinite(intrinsics).all() and intrinsics[0] > 0 and intrinsics[1] > 0


@FUZZ
@given(data=st.data())
def test_png_view_mutations(base, data, capfd):
    from recon.lf import read_lightfield

    folder, cap = copy_capture(base)
    views = sorted((cap / "views").iterdir())
    rng = rng_of(data)
    view = rng.choice(views)
    view.write_bytes(byte_mutation(rng, view.read_bytes()))
    capfd.readouterr()
    call_loader(folder, lambda: read_lightfield(cap))
    # lfrig's errors only: nothing printed by libpng or OpenCV on the way
    assert capfd.readouterr().err == ""


@settings(FUZZ, max_examples=90)
@given(data=st.data())
def test_depth_map_mutations(base, data, capfd):
    from recon.depth import read_depth, write_depth

    folder = fresh_folder(base)
    rng = rng_of(data)
    suffix = rng.choice([".png", ".pfm", ".npy"])
    path = folder / f"depth{suffix}"
    depth = np.full((8, 8), 1000.0)
    depth[2:5, 3:6] = np.nan
    write_depth(path, depth)
    target = path
    if suffix == ".png" and rng.random() < 0.4:  # the sidecar holds the scale too
        target = path.with_name(path.name + ".json")
        if rng.random() < 0.5:
            path.write_bytes(path.read_bytes().replace(b"tEXt", b"teXt"))  # only the sidecar is left
    if target.suffix == ".json" and rng.random() < 0.7:
        target.write_bytes(dump_json(json_mutation(rng, json.loads(target.read_text()))))
    else:
        target.write_bytes(byte_mutation(rng, target.read_bytes()))
    capfd.readouterr()
    call_loader(folder, lambda: read_depth(path))
    assert capfd.readouterr().err == ""


def test_a_manifest_cannot_make_lfrig_read_outside_the_capture(base):
    """A journal whose ``file`` points outside the capture (point 5 of #13) reads nothing there."""
    from recon.lf import read_lightfield

    folder, cap = copy_capture(base)
    outside = fresh_folder(base)
    shutil.copy(cap / "views" / "u00_v00.png", outside / "x.png")
    lines = (cap / "manifest.jsonl").read_text().splitlines()
    record = json.loads(lines[1])
    record["file"] = os.path.relpath(outside / "x.png", cap)
    lines[1] = json.dumps(record)
    (cap / "manifest.jsonl").write_text("\n".join(lines) + "\n")
    call_loader(folder, lambda: read_lightfield(cap))


# --------------------------------------------------------------------------------------------------
# the command line's argument checking


class Reached(Exception):
    """Raised by the stand-ins for expensive work: validation let the arguments through."""


@pytest.fixture(scope="module")
def cli_world(tmp_path_factory):
    """Inputs for the argument fuzzer: a capture, a result folder, PFMs, a file and a folder."""
    from rig.main import main

    root = tmp_path_factory.mktemp("cli")
    shutil.copytree(TINY_CAPTURE, root / "cap")
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(["reconstruct", str(root / "cap"), "-o", str(root / "res"), "--method", "baseline",
                     "--window", "3", "--step", "0.1", "--quiet"]) == 0
    shutil.copy(TRUTH, root / "truth.pfm")
    (root / "afile").write_text("not a folder")
    (root / "emptydir").mkdir()
    return root


PATHS = ["{root}/cap", "{root}/res", "{root}/truth.pfm", "{root}/afile", "{root}/emptydir", "{root}/missing",
         "{root}/out", "{root}/out/x.ply", "{root}/res/disparity.pfm", "", "{root}/afile/below"]
NUMBERS = ["0", "1", "-1", "0.5", "-0.5", "3", "9", "1e-9", "1e9", "100000", "nan", "inf", "-inf", "abc", "",
           "0x10", "2.5e-3", "9" * 40]


def flag(name: str, count: int = 1, values=NUMBERS) -> tuple[str, int, list[str]]:
    return (name, count, values)


COMMANDS = {
    "info": (["{root}/cap"], [flag("--json", 0)]),
    "evaluate": (["{root}/res/disparity.pfm", "{root}/truth.pfm"], [flag("--border"), flag("--json", 0)]),
    "reconstruct": (["{root}/cap", "-o", "{root}/out"], [
        flag("--method", values=["baseline", "entropy", "nope"]), flag("--step"), flag("--window"),
        flag("--disparity-range", 2), flag("--ply", values=PATHS), flag("--points", 0), flag("--quiet", 0),
        flag("--window-sizes", 2), flag("--initial-step"), flag("-o", values=PATHS)]),
    "export": (["{root}/res"], [
        flag("--ply", values=PATHS), flag("--points", 0), flag("--mesh", 0), flag("--ascii", 0), flag("--max-jump"),
        flag("--depth", values=PATHS + ["{root}/out/d.png", "{root}/out/d.xyz"]), flag("--focal-px"),
        flag("--pitch-mm"), flag("--disparity-offset"), flag("--poisson", 0), flag("--poses", values=PATHS),
        flag("--report", values=PATHS)]),
    "capture": (["{root}/out/c"], [
        flag("--dry-run", 0), flag("--rows"), flag("--cols"), flag("--pitch-mm"), flag("--centre-mm", 3),
        flag("--row-axis", values=["+y", "-x", "z", "q", ""]), flag("--backlash-mm"), flag("--settle-s"),
        flag("--feed-mm-min"), flag("--tolerance-mm"), flag("--limits-mm", 6), flag("--binning"), flag("--noise"),
        flag("--supersample"), flag("--roi", 4), flag("--stage", values=["fake", "fake?fault=nope", "grbl://", "x"]),
        flag("--camera", values=["fake", "opencv:", "zzz"]), flag("--quiet", 0)]),
    "stage": (["status"], [flag("--stage", values=["fake", "fake?clock=nope", "grbl://"]), flag("--baud")]),
    "batch": (["reconstruct", "{root}/cap", "-o", "{root}/out/b"], [
        flag("--workers"), flag("--tile"), flag("--halo"), flag("--step"), flag("--scheduler", values=["garbage", ""]),
        flag("--worker-timeout-s"), flag("--transfer", values=["ship", "shared", "x"]),
        flag("--export", values=["mesh", "none", "x"]), flag("--method", values=["baseline", "x"]),
        flag("--dashboard-address", values=["nonsense:::", ":8787", "127.0.0.1:0", "[::1]:99999", "", "0.0.0.0:0"])]),
    "import": (["{root}/cap/views", "-o", "{root}/out/imp"], [
        flag("--pattern", values=["u{{u:02d}}_v{{v:02d}}.png", "u{{u:0999999999d}}_v{{v}}.png", "{{i}}", "{{x}}",
                                  "a/{{u}}{{v}}", ""]),  # braces doubled: argv is str.format-ted with {root}
        flag("--order", values=["raster", "serpentine", "x"]), flag("--rows"), flag("--cols"), flag("--index-base"),
        flag("--pitch-mm"), flag("--focal-px"), flag("--principal-point-px", 2), flag("--disparity-range", 2),
        flag("--quiet", 0)]),
    "calibrate": (["intrinsics", "{root}/res/centre_view.png", "-o", "{root}/out/cam.cameramodel"], [
        flag("--board", values=["9x6", "0x0", "1x1", "x", "10000x3", "9X6"]), flag("--square-mm"),
        flag("--marker-mm"), flag("--focal-px"), flag("--working-distance-mm"), flag("--quiet", 0)]),
    "rectify": (["{root}/cap", "--model", "{root}/afile", "--stage", "{root}/afile"], [
        flag("-o", values=PATHS), flag("--focal-px"), flag("--no-crop", 0)]),
    "demo": ([], [flag("-o", values=PATHS), flag("--binning"), flag("--boards"), flag("--noise"),
                  flag("--method", values=["baseline", "entropy", "x"])]),
}


def random_argv(rng: random.Random) -> list[str]:
    """A command with its positional arguments and up to four flags with good or bad values."""
    command = rng.choice(sorted(COMMANDS))
    positional, flags = COMMANDS[command]
    argv = [command, *positional]
    if command == "calibrate":
        argv += ["--board", "9x6", "--square-mm", "8"]
    if command == "rectify":
        argv += ["-o", "{root}/out/rect"]
    for _ in range(rng.randint(0, 4)):
        name, count, values = rng.choice(flags)
        argv += [name, *(rng.choice(values) for _ in range(count))]
    if rng.random() < 0.2:  # a stray word or flag, or a missing value
        argv.insert(rng.randint(0, len(argv)), rng.choice(["--nope", "extra", "-o"]))
    return argv


@pytest.fixture
def stand_ins(monkeypatch):
    """Expensive work is replaced by stand-ins that raise :class:`Reached` (validation passed)."""
    import calib.intrinsics
    import calib.rectify
    import calib.stage
    import recon.pipeline
    import recon.scale.cluster
    import rig.demo
    import rig.session

    def reached(*args, **kwargs):
        raise Reached()

    for module, name in [(recon.pipeline, "run_in_process"), (rig.session, "run_capture"), (rig.demo, "run_demo"),
                         (calib.intrinsics, "calibrate_intrinsics_from_images"), (calib.rectify, "rectify_capture"),
                         (calib.stage, "calibrate_stage_from_capture"), (recon.scale.cluster, "connect")]:
        monkeypatch.setattr(module, name, reached)


@settings(FUZZ, max_examples=150)
@given(data=st.data())
def test_cli_argument_vectors(cli_world, stand_ins, data):
    from rig.main import main

    root = cli_world
    argv = [a.format(root=root) for a in random_argv(rng_of(data))]
    shutil.rmtree(root / "out", ignore_errors=True)
    out, err = io.StringIO(), io.StringIO()
    reached = False
    with AUDIT.watch(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = main(argv)
        except Reached:
            reached, status = True, None
        for thread in threading.enumerate():  # the method's warm-up: its files belong to this command
            if thread.name.startswith("lfrig-warm-"):
                thread.join()
    lines = [line for line in err.getvalue().splitlines() if line.strip()]
    assert "Traceback" not in err.getvalue(), (argv, err.getvalue())
    if not reached:
        if argv[0] == "batch":
            assert status in (0, 1, 2), (argv, status)
        else:
            assert status in (0, 2), (argv, status, err.getvalue())
        if status == 2:
            assert len(lines) == 1 and lines[0].startswith("lfrig: error:"), (argv, err.getvalue())
    outside = AUDIT.outside(root)
    assert not outside, (argv, outside[:5])


# --------------------------------------------------------------------------------------------------
# issue #22: hostile files, sizes and sources


def _valid_result_json() -> dict:
    return {"method": "baseline", "options": {"window": 3, "disparity_range": [-1.0, 1.5]}, "source": None,
            "image": [16, 16], "grid": [3, 3], "focal_px": 1000.0, "pitch_mm": 0.5, "disparity_offset": 0.0,
            "principal_point_px": [7.5, 7.5], "disparity_png_range": [-1.0, 1.0], "seconds": 0.1,
            "scores": {"mse_x100": 1.0}}


@settings(FUZZ, max_examples=120)
@given(data=st.data())
def test_result_json_field_types(base, data):
    """Every field of result.json replaced by any JSON value: read_result and what export and the
    report ask of it (the searched range, the camera) raise LfrigError or work."""
    from recon.result import read_result

    folder = fresh_folder(base)
    write_result_folder(folder)
    rng = rng_of(data)
    record = _valid_result_json()
    for _ in range(rng.randint(1, 3)):
        key = rng.choice(sorted(record))
        record[key] = rng.choice(INTERESTING + [[1.0, 2.0], {"disparity_range": "x"}, {"disparity_range": [1e308, -1e308]}])
    (folder / "res" / "result.json").write_bytes(dump_json(record))

    def load():
        result = read_result(folder / "res")
        result.search_range
        result.record.camera
        return result.camera()

    call_loader(folder, load)


def _regions_npy() -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.tile(np.arange(4, dtype=np.uint8), (16, 4)))
    return buffer.getvalue()


@FUZZ
@given(data=st.data())
def test_regions_npy_mutations(base, data):
    """A damaged regions.npy (or window_size.npy): the report's loader raises LfrigError or reads it."""
    from recon.errors import ExportError
    from recon.lf.imageio import read_npy

    folder = fresh_folder(base)
    rng = rng_of(data)
    raw = _regions_npy()
    if rng.random() < 0.5:  # the header's dict: shape, dtype, order replaced by junk
        header_end = raw.index(b"\n") + 1
        header = raw[10:header_end].decode("latin-1")
        for key in ("'descr': '|u1'", "'shape': (16, 16)", "'fortran_order': False"):
            if rng.random() < 0.5:
                junk = rng.choice(["'descr': '|O'", "'descr': '<f8'", "'shape': (100000, 100000)", "'shape': (-1, 4)",
                                   "'shape': ()", "'fortran_order': 7", "'descr': 'nope'", "'shape': (2**62, 4)"])
                header = header.replace(key, junk)
        raw = raw[:10] + header.encode("latin-1") + raw[header_end:]
    else:
        raw = byte_mutation(rng, raw)
    (folder / "regions.npy").write_bytes(raw)
    call_loader(folder, lambda: read_npy(folder / "regions.npy", error=ExportError))


def _sparse(path: Path, size: int = 8 << 30, head: bytes = b"") -> None:
    path.write_bytes(head)
    os.truncate(path, size)


#: Loaders of every file a command reads whole, with the file's place in a copy of the tiny capture
#: or a result folder: each must refuse an 8 GiB sparse file (or read only the header's bytes).
OVERSIZED = ["view", "manifest", "parameters", "disparity", "confidence", "result_json", "depth_npy",
             "depth_png", "stage_json", "camera_model", "benchmark_view", "import_source"]


@pytest.mark.parametrize("what", OVERSIZED)
def test_oversized_and_sparse_files(base, what):
    """An 8 GiB sparse file (or a header claiming a huge image) where lfrig reads a file: an
    LfrigError naming it, or a read of only the bytes the header describes; never 8 GiB in memory."""
    from calib.stage import StageCalibration, load_model
    from recon.depth import read_depth
    from recon.lf import read_lightfield
    from recon.lf.importer import import_views
    from recon.result import read_result

    folder, cap = copy_capture(base)
    record = write_result_folder(folder)
    (folder / "res" / "result.json").write_text(json.dumps(record))
    huge_png = (b"\x89PNG\r\n\x1a\n" + (13).to_bytes(4, "big") + b"IHDR" + (40000).to_bytes(4, "big")
                + (30000).to_bytes(4, "big") + bytes([8, 0, 0, 0, 0]))
    huge_png += zlib.crc32(huge_png[12:]).to_bytes(4, "big")
    cases = {
        "view": (cap / "views" / "u01_v01.png", b"", lambda: read_lightfield(cap, verify=False)),
        "manifest": (cap / "manifest.jsonl", b"", lambda: read_lightfield(cap)),
        "parameters": (cap / "parameters.cfg", b"[extrinsics]\n", lambda: read_lightfield(cap, verify=False)),
        "disparity": (folder / "res" / "disparity.pfm", b"Pf\n16 16\n-1.0\n", lambda: read_result(folder / "res")),
        "confidence": (folder / "res" / "confidence.pfm", b"Pf\n99999 99999\n-1.0\n", lambda: read_result(folder / "res")),
        "result_json": (folder / "res" / "result.json", b"{", lambda: read_result(folder / "res")),
        "depth_npy": (folder / "d.npy", b"", lambda: read_depth(folder / "d.npy")),
        "depth_png": (folder / "d.png", huge_png, lambda: read_depth(folder / "d.png")),
        "stage_json": (folder / "stage.json", b"", lambda: StageCalibration.load(folder / "stage.json")),
        "camera_model": (folder / "cam.cameramodel", b"", lambda: load_model(folder / "cam.cameramodel")),
    }
    if what == "benchmark_view":
        bench = folder / "bench"
        bench.mkdir()
        for i, view in enumerate(sorted((cap / "views").iterdir())):
            shutil.copy(view, bench / f"input_Cam{i:03d}.png")
        (bench / "input_Cam004.png").write_bytes(huge_png + b"\0\0\0\0IEND\xaeB`\x82")
        load = lambda: read_lightfield(bench)  # noqa: E731
    elif what == "import_source":
        src = folder / "src"
        shutil.copytree(cap / "views", src)
        _sparse(src / "u01_v01.png")
        load = lambda: import_views(src, folder / "imported", pattern="u{u:02d}_v{v:02d}.png", rows=3,  # noqa: E731
                                    cols=3, pitch_mm=0.5)
    else:
        path, head, load = cases[what]
        _sparse(path, head=head)
    import resource

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    call_loader(folder, load)
    grown_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert grown_kib < 512 * 1024, f"{what}: memory grew by {grown_kib // 1024} MiB"


HOSTILE_ENTRIES = ["link_out", "link_in", "link_dir_out", "padded_twin", "fifo", "folder_named_like_a_view",
                   "not_an_image", "huge_header", "sparse", "empty", "dangling_link", "hidden_temporary"]


@settings(FUZZ, max_examples=60)
@given(data=st.data())
def test_hostile_import_sources(base, data):
    """A source folder with links out of it, padded twins, FIFOs, folders named like views, damaged
    and oversized files: import_views raises LfrigError or makes a capture every reader accepts,
    reads nothing outside the example's folder and writes nothing outside the target's folder."""
    from recon.lf import read_lightfield
    from recon.lf.importer import import_views

    folder, cap = copy_capture(base)
    rng = rng_of(data)
    src = folder / "src"
    shutil.copytree(cap / "views", src)
    outside = fresh_folder(base)  # the user's other files: never read, never written
    secret = outside / "secret.png"
    shutil.copy(cap / "views" / "u00_v00.png", secret)
    names = sorted(p.name for p in src.iterdir())
    for _ in range(rng.randint(1, 3)):
        kind = rng.choice(HOSTILE_ENTRIES)
        name = rng.choice(names)
        path = src / name
        if path.exists() or path.is_symlink():
            path.unlink() if not path.is_dir() or path.is_symlink() else shutil.rmtree(path)
        if kind == "link_out":
            path.symlink_to(secret)
        elif kind == "link_in":
            path.symlink_to(src / rng.choice(names))
        elif kind == "link_dir_out":
            path.symlink_to(outside)
        elif kind == "padded_twin":
            shutil.copy(cap / "views" / name, path)
            u, v = int(name[1:3]), int(name[5:7])
            shutil.copy(cap / "views" / name, src / f"u{u:03d}_v{v:02d}.png")
        elif kind == "fifo":
            os.mkfifo(path)
        elif kind == "folder_named_like_a_view":
            path.mkdir()
        elif kind == "not_an_image":
            path.write_bytes(b"hello")
        elif kind == "huge_header":
            path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
        elif kind == "sparse":
            _sparse(path)
        elif kind == "empty":
            path.write_bytes(b"")
        elif kind == "dangling_link":
            path.symlink_to(outside / "missing.png")
        else:
            shutil.copy(cap / "views" / name, src / f".{name[:-4]}.{rng.randint(1, 99999)}.tmp.png")
    mode = rng.choice(["pattern", "order"])
    target = folder / "imported"

    def load():
        if mode == "pattern":
            return import_views(src, target, pattern="u{u:02d}_v{v:02d}.png", rows=3, cols=3, pitch_mm=0.5)
        return import_views(src, target, order="raster", rows=3, cols=3, pitch_mm=0.5)

    secret_before = secret.read_bytes()
    result = call_loader(folder, load)
    assert secret.read_bytes() == secret_before
    assert not AUDIT.followed or all(Path(p).resolve().is_relative_to(src.resolve()) for p, _ in AUDIT.followed), \
        AUDIT.followed
    if not isinstance(result, LfrigError):
        call_loader(folder, lambda: read_lightfield(target))
    else:
        assert not target.exists() and not any(".import-" in p.name for p in folder.iterdir())


def test_no_command_follows_a_link_it_did_not_create(cli_world, base):
    """Links planted where commands write (the lock, the temporary names of atomic writes of the
    result folder, a PLY, depth maps and the import) lead to a file outside every folder given: each
    command refuses or writes around them; the file stays as it was and no open went through a
    planted link. (A capture's views/ and journal: tests/test_hostile.py.)"""
    from recon.lf.imageio import temporary_name
    from rig.main import main

    victim_folder = fresh_folder(base)
    victim = victim_folder / "victim.txt"
    world = fresh_folder(base)
    shutil.copytree(cli_world / "cap", world / "cap")
    shutil.copytree(cli_world / "res", world / "res")
    out = world / "out"
    out.mkdir()
    planted = [out / ".lfrig.lock", world / "res" / ".lfrig.lock"]
    for name in ("disparity.pfm", "result.json", "disparity.png", "centre_view.png"):
        planted.append(temporary_name(out / name))
    for name in ("m.ply", "d.png", "d.png.json", "d.npy"):
        planted.append(temporary_name(world / name))
    planted.append(world / f".imp.import-{os.getpid()}.tmp")
    commands = [
        ["reconstruct", str(world / "cap"), "-o", str(out), "--method", "baseline", "--window", "3", "--step", "0.1",
         "--quiet"],
        ["export", str(world / "res"), "--ply", str(world / "m.ply"), "--points", "--depth", str(world / "d.png"),
         "--depth", str(world / "d.npy"), "--keep-all"],
        ["import", str(world / "cap" / "views"), "-o", str(world / "imp"), "--pattern", "u{u:02d}_v{v:02d}.png",
         "--rows", "3", "--cols", "3", "--pitch-mm", "0.5", "--quiet"],
    ]
    for argv in commands:
        victim.write_text("precious\n")
        for link in planted:
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(victim)
        with AUDIT.watch(), contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
            try:
                status = main(argv)
            except Reached:
                status = None
        assert status in (0, 1, 2, None), (argv, err.getvalue())
        assert "Traceback" not in err.getvalue(), (argv, err.getvalue())
        assert victim.read_text() == "precious\n", argv
        assert victim_folder.exists() and sorted(p.name for p in victim_folder.iterdir()) == ["victim.txt"], argv
        followed = [(p, w) for p, w in AUDIT.followed if Path(p) in planted]
        assert not followed, (argv, followed)
