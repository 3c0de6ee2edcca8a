"""Run a study's tasks on Dask distributed and keep each row as it comes back.

By default a :class:`distributed.LocalCluster` on 127.0.0.1: worker processes (one thread
each, as many as this process may use CPUs, or ``--workers``), scheduler and dashboard-less.
``--scheduler tcp://HOST:8786`` uses an existing cluster instead, whose workers have this
package installed::

    dask scheduler --host 10.0.0.1 --port 8786
    dask worker tcp://10.0.0.1:8786 --nthreads 1 --nworkers 4   # on every machine

A task is one run (:class:`rt_controller.sweep.spec.RunTask`, keyed by its run key); its row
never depends on the worker that runs it. Dask itself moves the tasks of a worker that dies to
the others (``distributed.scheduler.allowed-failures`` times, then the run is recorded as
failed); the store keeps one row per run key. Ctrl-C or SIGTERM cancels what is left, keeps
every finished row and writes the report of what ran; the same command resumes.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rt_controller.errors import ControllerConfigError
from rt_controller.sweep.engines import Engine, base_row, package_version
from rt_controller.sweep.results import ResultStore
from rt_controller.sweep.spec import RunTask, Spec

WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""Each worker is one thread; its BLAS too (the control law's matrices are tiny)."""
MAX_WORKERS = 256
WORKER_WAIT_S = 60.0
"""With ``--scheduler``: how long to wait for a first worker before giving up."""


def machine_workers() -> int:
    """Worker processes of a default local cluster: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class Cluster:
    """A Dask client and, for a local cluster, the cluster it owns."""

    client: Any
    local: Any = None

    @property
    def address(self) -> str:
        return str(self.client.scheduler.address)

    @property
    def workers(self) -> int:
        return len(self.client.scheduler_info().get("workers", {}))

    def close(self) -> None:
        import contextlib

        with contextlib.suppress(Exception):  # a cluster already going down on Ctrl-C
            self.client.close(timeout=10)
        if self.local is not None:
            with contextlib.suppress(Exception):
                self.local.close(timeout=10)


@contextlib.contextmanager
def _workers_ignore_sigint() -> Iterator[None]:
    """Start the local workers with SIGINT ignored (a spawned interpreter keeps an ignored
    SIGINT): Ctrl-C at a terminal signals the whole process group, and the sweep itself stops
    its workers in order instead of each one dying with a traceback."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def open_cluster(workers: int | None = None, scheduler: str | None = None) -> Cluster:
    """Connect to ``scheduler``, else start a local cluster of ``workers`` processes."""
    from distributed import Client, LocalCluster

    if scheduler is not None:
        if workers is not None:
            raise ControllerConfigError(
                "--workers sizes the local cluster; with --scheduler the cluster has its own"
            )
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise ControllerConfigError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
        try:
            client.wait_for_workers(1, timeout=WORKER_WAIT_S)
        except TimeoutError:
            client.close()
            raise ControllerConfigError(
                f"--scheduler {scheduler}: no worker joined within {WORKER_WAIT_S:g} s "
                f"(start one: dask worker {scheduler} --nthreads 1)"
            ) from None
        return Cluster(client)
    n = machine_workers() if workers is None else workers
    if not 1 <= n <= MAX_WORKERS:
        raise ControllerConfigError(f"--workers must be 1..{MAX_WORKERS}, got {n}")
    with _workers_ignore_sigint():
        local = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            worker_dashboard_address=None,
            silence_logs=logging.ERROR,
            env=WORKER_ENV,
        )
    return Cluster(Client(local), local)


@dataclass
class Outcome:
    """What one ``hil sweep`` did."""

    runs: int
    skipped: int
    ran: int = 0
    failed: int = 0
    interrupted: bool = False
    wall_s: float = 0.0
    workers: int = 0
    scheduler: str = ""
    engine: str = ""
    spec_hash: str = ""
    version: str = field(default_factory=package_version)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def failed_row(task: RunTask, error: str) -> dict[str, Any]:
    """The row of a run whose task never came back (its worker died too often)."""
    return base_row(task, "failed", error)


def run_sweep(
    spec: Spec,
    out: Path,
    *,
    engine: str | None = None,
    plant: Callable[[Any], Any] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    cluster: Cluster | None = None,
    keep_logs: bool = False,
    retry_failed: bool = False,
    progress: bool = True,
    on_row: Callable[[dict[str, Any], Cluster], None] | None = None,
) -> Outcome:
    """Run every task of ``spec`` not yet in ``out`` and keep the rows; returns the outcome.

    ``cluster``: an open cluster to use (left open); else one is opened (and closed) from
    ``workers``/``scheduler``. ``on_row`` is called after each row is kept (tests use it to
    interrupt or to kill a worker).
    """
    from rt_controller.rig.supervise import RigInterrupted, supervised

    out = Path(out)
    tasks = spec.tasks(engine, (out / "logs") if keep_logs else None)
    t0 = time.monotonic()
    with ResultStore(out, spec) as store:
        done = store.done(retry_failed)
        todo = [t for t in tasks if t.key not in done]
        result = Outcome(
            runs=len(tasks),
            skipped=len(tasks) - len(todo),
            engine=tasks[0].engine if tasks else (engine or spec.study.engine),
            spec_hash=spec.spec_hash,
        )
        if not todo:
            return result
        own = cluster is None
        try:
            with supervised():
                cl = cluster or open_cluster(workers, scheduler)
                try:
                    result.workers, result.scheduler = cl.workers, cl.address
                    _collect(cl, todo, store, result, Engine(plant), progress, on_row)
                finally:
                    if own:
                        cl.close()
        except (KeyboardInterrupt, RigInterrupted):
            result.interrupted = True
        finally:
            result.wall_s = time.monotonic() - t0
    return result


def _collect(
    cl: Cluster,
    todo: list[RunTask],
    store: ResultStore,
    result: Outcome,
    engine: Engine,
    progress: bool,
    on_row: Callable[[dict[str, Any], Cluster], None] | None,
) -> None:
    from distributed import as_completed
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from rt_controller.rig.supervise import RigInterrupted

    client = cl.client
    by_future = {}
    for task in todo:
        fut = client.submit(engine, task, key=f"hil-sweep-{task.key}", pure=False)
        by_future[fut] = task
    bar = Progress(
        TextColumn("[bold]sweep[/]"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[failed]} failed"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        disable=not progress,
        transient=False,
    )
    try:
        with bar:
            bar_task = bar.add_task("runs", total=len(todo), failed=0)
            for fut in as_completed(list(by_future)):
                task = by_future.pop(fut)
                try:
                    row = fut.result()
                except RigInterrupted:  # SIGINT/SIGTERM to this process: stop the sweep
                    raise
                except Exception as exc:  # a lost task is a failed run
                    row = failed_row(task, " ".join(f"{type(exc).__name__}: {exc}".split()))
                fut.release()
                store.add(row)
                result.ran += 1
                result.failed += row.get("status") != "ok"
                bar.update(bar_task, advance=1, failed=result.failed)
                if on_row is not None:
                    on_row(row, cl)
    finally:
        if by_future:  # interrupted: nothing left may keep running for us
            import contextlib

            with contextlib.suppress(Exception):
                client.cancel(list(by_future), force=True)
