"""Batches survive what a lab's cluster does to them (issue #13, point 9), with real `dask scheduler`
and `dask worker` processes on 127.0.0.1: a worker killed while it holds a capture (ship mode: its
views die with it) reruns that capture elsewhere; with no worker left the batch says so and stops
after --worker-timeout-s; a killed scheduler is one line and exit 2, no distributed traceback.

Every process is started in its own session and ended by its id (``tests.conftest.stop_process_group``); every wait is bounded.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import distributed
import pytest

from test_scale_batch import _start, write_benchmark_scene
from tests.conftest import stop_process_group

FLAGS = ["--method", "baseline", "--window", "5", "--step", "0.005", "--export", "none"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> list[Path]:
    """Four scenes big enough that a task runs for a few seconds under load."""
    root = tmp_path_factory.mktemp("fault_scenes")
    paths = []
    for i in range(4):
        write_benchmark_scene(root / f"scene_{i}", seed=i, size=96)
        paths.append(root / f"scene_{i}")
    return paths


class Cluster:
    """A scheduler and named workers, each its own process group."""

    def __init__(self, tmp: Path, workers: int) -> None:
        self.tmp = tmp
        dask = str(Path(sys.executable).with_name("dask"))
        scheduler_file = tmp / "scheduler.json"
        self.scheduler = _start([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                 "--scheduler-file", str(scheduler_file)], tmp / "scheduler.log", tmp)
        self.workers: list[subprocess.Popen] = []
        deadline = time.monotonic() + 60
        while not scheduler_file.is_file():
            assert self.scheduler.poll() is None, (tmp / "scheduler.log").read_text()
            assert time.monotonic() < deadline, "the scheduler did not start within 60 s"
            time.sleep(0.2)
        time.sleep(0.3)
        self.address = json.loads(scheduler_file.read_text())["address"]
        for k in range(workers):
            self.workers.append(_start([dask, "worker", self.address, "--host", "127.0.0.1", "--nworkers", "1",
                                        "--nthreads", "1", "--no-dashboard", "--name", f"w{k}",
                                        "--local-directory", str(tmp / f"w{k}")], tmp / f"w{k}.log", tmp))
        with distributed.Client(self.address, timeout=60) as client:
            client.wait_for_workers(workers, timeout=90)

    def kill_when_busy(self, *, worker: str | None, kill: subprocess.Popen, timeout_s: float = 120) -> threading.Thread:
        """In the background: once a task is processing (on ``worker`` by name, or anywhere), SIGKILL
        ``kill``'s process group."""

        def run() -> None:
            deadline = time.monotonic() + timeout_s
            with distributed.Client(self.address, timeout=30) as client:
                while time.monotonic() < deadline:
                    names = {a: w.get("name") for a, w in client.scheduler_info()["workers"].items()}
                    busy = [a for a, keys in client.processing().items()
                            if keys and (worker is None or names.get(a) == worker)]
                    if busy:
                        break
                    time.sleep(0.05)
            os.killpg(kill.pid, signal.SIGKILL)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread

    def stop(self) -> None:
        for process in reversed(self.workers):
            stop_process_group(process)
        stop_process_group(self.scheduler)


def _batch(scenes: list[Path], out: Path, address: str, *extra: str) -> list[str]:
    return ["batch", "reconstruct", *map(str, scenes), "-o", str(out), "--scheduler", address, *FLAGS, *extra]


def test_a_killed_worker_s_captures_run_again_elsewhere(tmp_path, scenes, capsys):
    from rig.main import main

    cluster = Cluster(tmp_path, workers=2)
    try:
        killer = cluster.kill_when_busy(worker="w0", kill=cluster.workers[0])
        status = main(_batch(scenes, tmp_path / "out", cluster.address))
        killer.join(timeout=10)
    finally:
        cluster.stop()
    captured = capsys.readouterr()
    assert status == 0, captured.out + captured.err
    assert "4 done, 0 already complete, 0 failed" in captured.out
    assert "its worker was lost" in captured.out and "running it again (attempt 2 of 3)" in captured.out
    assert "already forgotten" not in captured.out + captured.err
    for scene in scenes:
        assert (tmp_path / "out" / scene.name / "batch.json").is_file()


def test_no_worker_left_says_so_and_stops(tmp_path, scenes, capsys):
    from rig.main import main

    cluster = Cluster(tmp_path, workers=1)
    try:
        killer = cluster.kill_when_busy(worker="w0", kill=cluster.workers[0])
        started = time.monotonic()
        status = main(_batch(scenes, tmp_path / "out", cluster.address, "--worker-timeout-s", "3"))
        took = time.monotonic() - started
        killer.join(timeout=10)
    finally:
        cluster.stop()
    captured = capsys.readouterr()
    assert status == 1, captured.out + captured.err
    assert "no Dask worker is connected" in captured.out and "stopping; 4 capture(s) not run" in captured.out
    assert "0 done, 0 already complete, 4 failed" in captured.out
    assert took < 90, f"the batch took {took:.0f} s to give up"
    assert "Traceback" not in captured.out + captured.err


def test_a_killed_scheduler_is_one_line(tmp_path, scenes, capfd):
    from rig.main import main

    cluster = Cluster(tmp_path, workers=1)
    try:
        killer = cluster.kill_when_busy(worker=None, kill=cluster.scheduler)
        status = main(_batch(scenes, tmp_path / "out", cluster.address))
        killer.join(timeout=10)
    finally:
        cluster.stop()
    captured = capfd.readouterr()  # file descriptors: distributed's log handlers write to the real stderr
    assert status == 2, captured.out + captured.err
    errors = [line for line in captured.err.splitlines() if line.strip()]
    assert errors == [errors[-1]] and errors[-1].startswith("lfrig: error: lost the connection to the Dask scheduler")
    assert "Traceback" not in captured.out + captured.err
