"""Batches on Dask: one task per capture, failures reported without stopping the others, reruns that
skip complete captures, the same results as one by one, and a real `dask scheduler` + `dask worker`."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import distributed  # a declared dependency: if it is missing these tests must fail, not skip
import numpy as np
import pytest

from recon.lf.imageio import write_png
from recon.lf.params import write_parameters
from recon.lf.pfm import read_pfm, write_pfm
from recon.pipeline import reconstruct_to_folder
from recon.scale import ScaleError
from recon.scale.batch import (
    MARKER,
    SUMMARY,
    BatchRequest,
    check_complete,
    format_summary,
    input_fingerprint,
    plan_jobs,
    prepare_batch,
    run_batch,
)
from recon.scale.cluster import plan_local
from recon.synthetic import occluding_square_scene
from tests.conftest import stop_process_group
from recon.lf.capture import parameters_for

ROOT = Path(__file__).resolve().parents[1]
TINY_CAPTURE = ROOT / "fixtures" / "tiny_capture"
OPTIONS = {"window": 5, "step": 0.05}  # what `--method baseline --window 5 --step 0.05` gives
FLAGS = ["--method", "baseline", "--window", "5", "--step", "0.05"]
OUTPUTS = ("disparity.pfm", "disparity.png", "centre_view.png", "result.json", "mesh.ply")


def write_benchmark_scene(path: Path, *, seed: int, size: int = 40) -> None:
    """A 5x5 grey light field in the benchmark layout, with parameters.cfg and its true disparity."""
    lf, truth = occluding_square_scene(size, seed=seed, grid=(5, 5))
    path.mkdir(parents=True)
    rows, cols = lf.grid_shape
    for u in range(rows):
        for v in range(cols):
            write_png(path / f"input_Cam{u * cols + v:03d}.png", np.round(lf.views[u, v] * 255).astype(np.uint8))
    write_parameters(path / "parameters.cfg", parameters_for(
        grid=(rows, cols), image_shape=lf.image_shape, pitch_mm=0.5, focal_px=1000.0,
        disparity_range=lf.disparity_range))
    write_pfm(path / "gt_disp_lowres.pfm", truth)


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict[str, Path]:
    """Two benchmark scenes with truth, the tiny capture (capture layout, no truth), a broken one."""
    root = tmp_path_factory.mktemp("captures")
    write_benchmark_scene(root / "scene_a", seed=1)
    write_benchmark_scene(root / "scene_b", seed=2)
    shutil.copytree(TINY_CAPTURE, root / "tiny_capture")
    broken = root / "broken"
    broken.mkdir()
    (broken / "input_Cam000.png").write_bytes(b"this is not a PNG")
    (broken / "parameters.cfg").write_text("[lfrig]\nfocal_px = 100\n\n[extrinsics]\nbaseline_mm = 1\n")  # a camera
    return {p.name: p for p in sorted(root.iterdir())}


@pytest.fixture(scope="module")
def client():
    """An in-process cluster (threads, inproc transport: no ports, fast to start)."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        yield c


@pytest.fixture(scope="module")
def one_by_one(captures, tmp_path_factory) -> dict[str, Path]:
    """Each good capture reconstructed alone by `lfrig reconstruct --ply`."""
    from rig.main import main

    root = tmp_path_factory.mktemp("one_by_one")
    out = {}
    for name in ("scene_a", "scene_b", "tiny_capture"):
        assert main(["reconstruct", str(captures[name]), "-o", str(root / name), *FLAGS, "--quiet",
                     "--ply", str(root / name / "mesh.ply")]) == 0
        out[name] = root / name
    return out


def test_pipeline_writes_what_lfrig_reconstruct_writes(tmp_path, captures, one_by_one):
    folder = reconstruct_to_folder(captures["scene_a"], tmp_path / "a", method="baseline", options=OPTIONS,
                                   ply=tmp_path / "a" / "mesh.ply")
    assert sorted(folder.files) == sorted(p.name for p in one_by_one["scene_a"].iterdir() if p.suffix != ".ply" and not p.name.startswith("."))
    assert_same_result(tmp_path / "a", one_by_one["scene_a"])
    assert folder.export.points > 0


def assert_same_result(folder: Path, reference: Path) -> None:
    np.testing.assert_array_equal(read_pfm(folder / "disparity.pfm"), read_pfm(reference / "disparity.pfm"))
    mine, theirs = (json.loads((f / "result.json").read_text()) for f in (folder, reference))
    mine.pop("seconds"), theirs.pop("seconds")
    made, made_there = mine.pop("provenance"), theirs.pop("provenance")  # when, how and by which command differ
    assert made["input"] == made_there["input"] and made["input"]["kind"] in ("capture", "benchmark")
    assert mine == theirs
    ply, ply_there = ((f / "mesh.ply").read_bytes() for f in (folder, reference))
    assert ply[ply.index(b"end_header\n"):] == ply_there[ply_there.index(b"end_header\n"):]


def mtimes(folder: Path) -> dict[str, int]:
    return {name: (folder / name).stat().st_mtime_ns for name in OUTPUTS + (MARKER,)}


# --------------------------------------------------------------------------------------------------


def test_local_plan_uses_processes_per_core_and_splits_numba_threads():
    assert plan_local(cores=2, tasks=5) == plan_local(cores=2) == plan_local(cores=2, workers=2)
    assert plan_local(cores=2, tasks=5).workers == 2 and plan_local(cores=2, tasks=5).numba_threads == 1
    assert plan_local(cores=2, tasks=1).workers == 1 and plan_local(cores=2, tasks=1).numba_threads == 2
    assert plan_local(cores=8, workers=3).numba_threads == 2
    with pytest.raises(ScaleError, match="at least one worker"):
        plan_local(workers=0)


def test_captures_with_the_same_folder_name_are_refused(tmp_path, captures):
    twin = tmp_path / "elsewhere" / "scene_a"
    shutil.copytree(captures["scene_a"], twin)
    with pytest.raises(ScaleError, match="same folder name 'scene_a'"):
        plan_jobs([captures["scene_a"], twin], tmp_path / "out")
    with pytest.raises(ScaleError, match="not a folder"):
        plan_jobs([tmp_path / "missing"], tmp_path / "out")


def test_batch_reports_the_failure_runs_the_rest_and_a_rerun_skips_finished_work(tmp_path, captures, client,
                                                                                 one_by_one):
    out = tmp_path / "out"
    request = BatchRequest(method="baseline", options=OPTIONS, export="mesh")
    seen = []
    outcomes = run_batch(client, prepare_batch(list(captures.values()), out, request=request),
                         on_outcome=lambda o, done, total: seen.append((o.name, o.status, done, total)))
    status = {o.name: o for o in outcomes}
    assert [o.name for o in outcomes] == list(captures)  # in the order given
    assert status["broken"].status == "failed"
    assert "input_Cam000.png" in status["broken"].error and "not a readable image" in status["broken"].error
    for name in ("scene_a", "scene_b", "tiny_capture"):
        assert status[name].status == "ok", status[name].error
        assert_same_result(out / name, one_by_one[name])
        assert (out / name / MARKER).is_file()
    assert status["scene_a"].scores["badpix_0.07"] >= 0 and status["tiny_capture"].scores is None
    assert sorted(s[2] for s in seen) == [1, 2, 3, 4] and {s[3] for s in seen} == {4}
    summary = json.loads((out / SUMMARY).read_text())
    assert [c["status"] for c in summary["captures"]] == [status[n].status for n in captures]
    table = format_summary(outcomes)
    assert "3 done, 0 already complete, 1 failed" in table and "FAILED broken" in table

    before = {name: mtimes(out / name) for name in ("scene_a", "scene_b", "tiny_capture")}
    plan = prepare_batch(list(captures.values()), out, request=request)
    assert [job.name for job, _ in plan.todo] == ["broken"]  # only the failure is tried again
    again = {o.name: o for o in run_batch(client, plan)}
    assert again["broken"].status == "failed"
    for name in before:
        assert again[name].status == "skipped"
        assert again[name].scores == status[name].scores and again[name].seconds == status[name].seconds
        assert mtimes(out / name) == before[name]  # not a byte rewritten

    # a damaged output makes its capture incomplete: only that one is redone
    pfm = out / "scene_b" / "disparity.pfm"
    pfm.write_bytes(pfm.read_bytes()[:-100])
    plan = prepare_batch([captures["scene_a"], captures["scene_b"]], out, request=request)
    assert [job.name for job, _ in plan.todo] == ["scene_b"]
    assert not (out / "scene_b" / MARKER).exists()  # reads as incomplete until the redo finishes
    redone = {o.name: o.status for o in run_batch(client, plan)}
    assert redone == {"scene_a": "skipped", "scene_b": "ok"}
    assert_same_result(out / "scene_b", one_by_one["scene_b"])


def test_complete_means_same_request_same_input_and_intact_outputs(tmp_path, captures, one_by_one):
    """:func:`check_complete` on a folder marked by hand from the one-by-one results."""
    from recon.scale.batch import Outcome, write_marker

    source = tmp_path / "scene_a"
    shutil.copytree(captures["scene_a"], source)
    request = BatchRequest(method="baseline", options=OPTIONS, export="mesh")
    job = plan_jobs([source], tmp_path / "out")[0]
    shutil.copytree(one_by_one["scene_a"], job.out_dir)
    assert check_complete(job, request, input_fingerprint(source)) == (None, "not done yet")
    write_marker(job, request, input_fingerprint(source), Outcome(job.name, "", "", "ok", seconds=1.0), OUTPUTS)
    marker, why = check_complete(job, request, input_fingerprint(source))
    assert marker is not None and why == ""

    other = BatchRequest(method="baseline", options={**OPTIONS, "window": 7}, export="mesh")
    assert check_complete(job, other, input_fingerprint(source))[1] == "made with other options"
    assert check_complete(job, BatchRequest(options=OPTIONS, export="points"), input_fingerprint(source))[0] is None

    view = source / "input_Cam012.png"
    os.utime(view, ns=(view.stat().st_atime_ns, view.stat().st_mtime_ns + 10**9))  # re-captured view
    assert check_complete(job, request, input_fingerprint(source))[1] == "the light-field files changed since"

    fingerprint = input_fingerprint(source)
    write_marker(job, request, fingerprint, Outcome(job.name, "", "", "ok"), OUTPUTS)
    ply = job.out_dir / "mesh.ply"
    data = bytearray(ply.read_bytes())
    data[-1] ^= 0xFF  # same size, other content
    ply.write_bytes(bytes(data))
    assert "changed or is truncated" in check_complete(job, request, fingerprint)[1]
    ply.unlink()
    assert "is missing" in check_complete(job, request, fingerprint)[1]
    (job.out_dir / MARKER).write_text("{ not json")
    assert "unreadable" in check_complete(job, request, fingerprint)[1]


def test_ship_mode_sends_views_and_gets_files_back(tmp_path, captures, client, one_by_one):
    out = tmp_path / "out"
    request = BatchRequest(method="baseline", options=OPTIONS, export="mesh")
    outcomes = run_batch(client, prepare_batch([captures["tiny_capture"], captures["broken"]], out, request=request),
                         transfer="ship")
    assert [o.status for o in outcomes] == ["ok", "failed"]
    assert str(captures["broken"]) in outcomes[1].error  # the user's folder, not the worker's copy
    assert_same_result(out / "tiny_capture", one_by_one["tiny_capture"])


class _Unreachable:
    """The client, except that its first ``failures`` scatters raise what distributed raises when the
    scheduler still lists a worker that was killed a moment ago: a bare ``OSError`` after the connect
    timeout (seen in a fault test, after 30 s)."""

    def __init__(self, client, failures: int) -> None:
        self._client, self.failures, self.calls = client, failures, 0

    def __getattr__(self, name):
        return getattr(self._client, name)

    def scatter(self, *args, **kwargs):
        self.calls += 1
        if self.calls <= self.failures:
            raise OSError("Timed out trying to connect to tcp://127.0.0.1:37899 after 30 s")
        return self._client.scatter(*args, **kwargs)


def test_ship_mode_sends_again_when_a_worker_cannot_be_reached_and_gives_up_after_three(tmp_path, captures, client,
                                                                                        one_by_one):
    request = BatchRequest(method="baseline", options=OPTIONS, export="mesh")
    notes: list[str] = []
    flaky = _Unreachable(client, failures=1)
    outcomes = run_batch(flaky, prepare_batch([captures["tiny_capture"]], tmp_path / "once", request=request),
                         transfer="ship", on_note=notes.append)
    assert [o.status for o in outcomes] == ["ok"] and flaky.calls == 2
    assert notes == ["tiny_capture: sending it failed (OSError); trying again (attempt 2 of 3)"]
    assert_same_result(tmp_path / "once" / "tiny_capture", one_by_one["tiny_capture"])

    notes.clear()
    dead = _Unreachable(client, failures=10**6)
    outcomes = run_batch(dead, prepare_batch([captures["tiny_capture"], captures["scene_a"]], tmp_path / "never",
                                             request=request), transfer="ship", on_note=notes.append)
    assert [o.status for o in outcomes] == ["failed", "failed"] and dead.calls == 6  # three sends each, then stop
    assert "sending it to a worker failed 3 times (OSError: Timed out trying to connect" in outcomes[0].error
    assert not (tmp_path / "never" / "tiny_capture" / MARKER).exists()


def test_tiled_batch_equals_untiled(tmp_path, captures, client, one_by_one):
    out = tmp_path / "out"
    request = BatchRequest(method="baseline", options=OPTIONS, export=None, tile=16)
    (outcome,) = run_batch(client, prepare_batch([captures["scene_a"]], out, request=request))
    assert outcome.status == "ok", outcome.error
    np.testing.assert_allclose(read_pfm(out / "scene_a" / "disparity.pfm"),
                               read_pfm(one_by_one["scene_a"] / "disparity.pfm"), rtol=0, atol=1e-6)
    tiling = json.loads((out / "scene_a" / "result.json").read_text())["tiling"]
    assert tiling["tiles"] == 9 and tiling["exact"] is True
    assert not (out / "scene_a" / "mesh.ply").exists()


def test_cli_on_its_own_local_cluster(tmp_path, captures, one_by_one, capsys):
    from rig.main import main

    out = tmp_path / "out"
    args = ["batch", "reconstruct", str(captures["scene_a"]), str(captures["tiny_capture"]), "-o", str(out),
            "--workers", "1", *FLAGS, "--dashboard-address", "127.0.0.1:0"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "local cluster: 1 worker(s)" in printed and "dashboard: http://127.0.0.1:" in printed
    assert "[2/2]" in printed and "2 done, 0 already complete, 0 failed" in printed
    for name in ("scene_a", "tiny_capture"):
        assert_same_result(out / name, one_by_one[name])
    assert main(args) == 0  # everything complete: no cluster is started at all
    printed = capsys.readouterr().out
    assert "local cluster" not in printed and "0 done, 2 already complete, 0 failed" in printed


# --------------------------------------------------------------------------------------------------
# a scheduler and a worker started by hand, as on lab machines
# --------------------------------------------------------------------------------------------------


def _start(args: list[str], log: Path, cwd: Path) -> subprocess.Popen:
    env = dict(os.environ, NUMBA_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    with open(log, "wb") as f:
        return subprocess.Popen(args, stdout=f, stderr=subprocess.STDOUT, cwd=cwd, env=env, start_new_session=True)


def test_batch_through_a_dask_scheduler_and_worker_started_by_hand(tmp_path, captures, one_by_one, capsys):
    from rig.main import main

    dask = str(Path(sys.executable).with_name("dask"))
    scheduler_file = tmp_path / "scheduler.json"
    processes = []
    try:
        processes.append(_start([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                 "--scheduler-file", str(scheduler_file)], tmp_path / "scheduler.log", tmp_path))
        deadline = time.monotonic() + 60
        while not scheduler_file.is_file():
            assert processes[0].poll() is None, (tmp_path / "scheduler.log").read_text()
            assert time.monotonic() < deadline, "the scheduler did not start within 60 s"
            time.sleep(0.2)
        time.sleep(0.2)  # the file is written in one go, but give it a moment
        address = json.loads(scheduler_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        processes.append(_start([dask, "worker", address, "--host", "127.0.0.1", "--nworkers", "1", "--nthreads", "1",
                                 "--no-dashboard", "--local-directory", str(tmp_path / "worker")],
                                tmp_path / "worker.log", tmp_path))
        out = tmp_path / "out"
        status = main(["batch", "reconstruct", str(captures["scene_a"]), str(captures["scene_b"]),
                       str(captures["broken"]), "-o", str(out), "--scheduler", address, *FLAGS])
        printed = capsys.readouterr().out
    finally:
        for process in reversed(processes):
            stop_process_group(process)
    assert status == 1, printed  # one capture failed ...
    assert f"scheduler {address}: 1 worker(s)" in printed and "data: ship" in printed
    assert "2 done, 0 already complete, 1 failed" in printed and "FAILED broken" in printed
    for name in ("scene_a", "scene_b"):  # ... and the others are as if run one by one
        assert_same_result(out / name, one_by_one[name])


def test_a_capture_without_camera_is_refused_before_any_work_when_a_ply_is_asked_for(tmp_path, captures, capsys):
    """Issue 23: the batch ran the estimate, then failed on the export with a flag it does not have."""
    from rig.main import main

    bare = tmp_path / "bare"
    shutil.copytree(captures["scene_b"], bare)
    (bare / "parameters.cfg").unlink()
    out = tmp_path / "out"
    assert main(["batch", "reconstruct", str(captures["scene_a"]), str(bare), "-o", str(out), *FLAGS]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bare has no focal_px or pitch_mm" in err and "--export none" in err
    assert not out.exists() or not any(out.rglob("disparity.pfm"))  # nothing was estimated
    plan = prepare_batch([bare], out, request=BatchRequest(method="baseline", options=OPTIONS, export=None))
    assert [job.name for job, _ in plan.todo] == ["bare"]  # disparity only: nothing to refuse
