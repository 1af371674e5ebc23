"""Where the work runs: a local Dask cluster sized to this machine, or a scheduler by address.

Sizing a local cluster for lfrig's kernels: the hot loops are numba ``parallel=True`` kernels that
hold the GIL (all but the nine-view search's are not ``nogil``), and the rest (PNG decoding, OpenCV
filters, PLY export) is mostly single-threaded. So workers are **processes** with **one task thread each**, as many as there
are cores (fewer when there are fewer captures than cores), and each worker's numba gets
``cores // workers`` threads (``NUMBA_NUM_THREADS``): on 2 cores, 2 workers x 1 numba thread for a
batch, 1 worker x 2 numba threads for a single capture. Nothing is oversubscribed and every core is
busy either with a whole capture or with a kernel's rows.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from recon.scale import ScaleError


def machine_cores() -> int:
    """Cores this process may run on (the affinity mask, else ``os.cpu_count()``)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@dataclass(frozen=True)
class LocalPlan:
    """A local cluster's shape: ``workers`` processes x 1 task thread, ``numba_threads`` each."""

    workers: int
    numba_threads: int


def plan_local(*, workers: int | None = None, tasks: int | None = None, cores: int | None = None) -> LocalPlan:
    """Workers = ``workers`` if given, else ``min(cores, tasks)``; numba threads = ``cores // workers``."""
    cores = cores or machine_cores()
    if workers is not None and workers < 1:
        raise ScaleError(f"--workers {workers}: need at least one worker")
    count = workers or max(1, min(cores, tasks or cores))
    return LocalPlan(workers=count, numba_threads=max(1, cores // count))


def limit_threads(threads: int | None) -> None:
    """Cap numba's and OpenCV's threads in this worker thread (``None``: leave them)."""
    if not threads:
        return
    import cv2
    import numba

    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    cv2.setNumThreads(int(threads))


def probe_worker() -> dict[str, Any]:
    """Run on every worker before a batch: lfrig imports there, and from where (a cluster task)."""
    import numba

    import recon
    import recon.pipeline  # noqa: F401  (fails early if the worker's lfrig is too old)

    return {"recon": os.path.dirname(recon.__file__), "numba_threads": numba.config.NUMBA_NUM_THREADS,
            "pid": os.getpid()}


@dataclass
class Connection:
    """A connected client and what the command prints about it."""

    client: Any
    local: bool
    dashboard: str | None
    workers: int
    threads: int
    task_threads: int | None  # numba/OpenCV threads a task should use; None = the worker's own setting

    def describe(self) -> str:
        where = "local cluster" if self.local else f"scheduler {self.client.scheduler.address}"
        threads = f", {self.task_threads} numba thread(s) each" if self.task_threads else ""
        return f"{where}: {self.workers} worker(s), {self.threads} task thread(s){threads}"


def _dashboard(client: Any) -> str | None:
    try:
        if "dashboard" not in client.scheduler_info().get("services", {}):
            return None
        return client.dashboard_link
    except Exception:  # noqa: BLE001 - a missing dashboard must not stop the work
        return None


@contextmanager
def connect(
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    tasks: int | None = None,
    dashboard_address: str | None = "127.0.0.1:8787",
    timeout_s: float = 60.0,
) -> Iterator[Connection]:
    """A client on ``scheduler`` (``tcp://HOST:PORT``), or on a local cluster that lives as long as
    the ``with`` block (``workers`` processes, else sized by :func:`plan_local` for ``tasks``).

    A local cluster listens on 127.0.0.1 only; its dashboard on ``dashboard_address`` (a random port
    when that one is taken; ``None`` for none), ``HOST:PORT`` as :func:`recon.cliargs.host_port`
    accepts it: every interface only when named (``0.0.0.0:PORT``), never by an empty host.

    Raises
    ------
    ScaleError
        The scheduler cannot be reached, has no worker within ``timeout_s``, or a worker cannot import
        lfrig.
    """
    if scheduler is None and dashboard_address:
        import argparse

        from recon.cliargs import host_port

        try:
            host_port(dashboard_address)
        except argparse.ArgumentTypeError as error:
            raise ScaleError(f"dashboard address {error}") from None
    from distributed import Client, LocalCluster

    quiet = _QuietDistributedLogs()
    cluster = None
    if scheduler is None:
        plan = plan_local(workers=workers, tasks=tasks)
        env = {"NUMBA_NUM_THREADS": str(plan.numba_threads), "OMP_NUM_THREADS": str(plan.numba_threads)}
        cluster = LocalCluster(
            n_workers=plan.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
            dashboard_address=dashboard_address if dashboard_address else None,
            silence_logs=logging.ERROR, env=env,
        )
        task_threads: int | None = plan.numba_threads
        try:
            client = Client(cluster)
        except BaseException:
            cluster.close()
            raise
    else:
        if workers is not None:
            raise ScaleError("--workers sizes a local cluster; with --scheduler, start that many `dask worker`s instead")
        try:
            client = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError, ValueError, TypeError) as error:  # ValueError: not an address
            raise ScaleError(
                f"cannot reach the Dask scheduler at {scheduler} ({error}); start one with "
                "`dask scheduler` and pass the address it prints (tcp://HOST:PORT)"
            ) from None
        task_threads = None
    quiet.__enter__()
    try:
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except TimeoutError:
            raise ScaleError(
                f"the scheduler at {client.scheduler.address} has no worker after {timeout_s:.0f} s; "
                f"start one with `dask worker {client.scheduler.address} --nthreads 1`"
            ) from None
        from distributed.comm.core import CommClosedError

        probes = client.run(probe_worker, on_error="return")
        # A worker that left while being probed (CommClosedError, a timeout) is not a broken install.
        broken = {addr: result for addr, result in probes.items() if isinstance(result, BaseException)
                  and not isinstance(result, (CommClosedError, OSError, TimeoutError))}
        if broken:
            addr, error = next(iter(broken.items()))
            raise ScaleError(
                f"worker {addr} cannot run lfrig ({type(error).__name__}: {error}); install lfrig in the "
                "worker's Python environment (the same version as here)"
            )
        info = client.scheduler_info()["workers"]
        yield Connection(
            client=client, local=cluster is not None, dashboard=_dashboard(client), workers=len(info),
            threads=sum(w.get("nthreads", 1) for w in info.values()), task_threads=task_threads,
        )
    finally:
        try:
            client.close(timeout=10)
        except Exception:  # noqa: BLE001 - closing a client whose scheduler is gone: nothing left to do
            pass
        if cluster is not None:
            cluster.close()
        quiet.__exit__()


class _QuietDistributedLogs:
    """While a batch runs, distributed's own log messages (a lost worker or scheduler, with their
    tracebacks) are not printed: lfrig reports what happened in its own words (the batch's notes, a
    :class:`ScaleError`). Set ``LFRIG_DASK_LOGS=1`` to see them."""

    NAMES = ("distributed", "tornado")

    def __init__(self) -> None:
        self.saved: dict[str, int] = {}

    def __enter__(self) -> "_QuietDistributedLogs":
        if not os.environ.get("LFRIG_DASK_LOGS"):
            # every logger of the family: distributed's config gives some children their own level
            known = [name for name in logging.root.manager.loggerDict
                     if any(name == n or name.startswith(n + ".") for n in self.NAMES)]
            for name in sorted(set(known) | set(self.NAMES)):
                logger = logging.getLogger(name)
                self.saved[name] = logger.level
                logger.setLevel(logging.CRITICAL + 1)
        return self

    def __exit__(self, *exc: object) -> None:
        for name, level in self.saved.items():
            logging.getLogger(name).setLevel(level)
        self.saved.clear()
