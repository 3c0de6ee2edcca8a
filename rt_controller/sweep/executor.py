"""Run a study's tasks on Dask distributed and keep each row as it comes back.

By default a :class:`distributed.LocalCluster` on 127.0.0.1: worker processes (one thread
each, as many as this process may use CPUs, or ``--workers``), scheduler and dashboard-less.
``--scheduler tcp://HOST:8786`` uses an existing cluster instead, whose workers have this
package installed::

    dask scheduler --host 10.0.0.1 --port 8786
    dask worker tcp://10.0.0.1:8786 --nthreads 1 --nworkers 4   # on every machine

The one mechanism of ``hil sweep`` and ``hil experiment``: :func:`open_cluster`
(:mod:`.cluster`) makes the cluster, :class:`Tasks` puts tasks on it and takes each back as it
finishes, and a stop request (:func:`request_stop`) reaches the tasks that are running
(:func:`watch_stop`). A scheduler that goes away ends the sweep (:class:`ClusterLost`): the
runs it never ran are no rows. A sweep task is one run (:class:`rt_controller.sweep.spec.RunTask`,
keyed by its run key); its row never depends on the worker that runs it. Dask itself moves the
tasks of a worker that dies to the others (``distributed.scheduler.allowed-failures`` times,
then the run is recorded as failed); the store keeps one row per run key. Ctrl-C or SIGTERM
cancels what is left (a running rig run stops its processes, waited for), keeps every finished
row and writes the report of what ran; the same command resumes.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import CancelledError
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rt_controller.sweep.cluster import Cluster, open_cluster
from rt_controller.sweep.cluster import machine_workers as machine_workers  # re-exported
from rt_controller.sweep.engines import Engine, base_row, package_version
from rt_controller.sweep.results import ResultStore
from rt_controller.sweep.spec import RunTask, Spec

NO_WORKER_S = 30.0
"""How long the cluster may have no worker before :meth:`Tasks.next` says so (again every
ten times as long): Dask keeps the tasks and waits for a worker silently."""


class Tasks:
    """Tasks on a cluster's workers, taken back one by one as they finish.

    A task whose worker dies is run again elsewhere by Dask itself
    (``distributed.scheduler.allowed-failures`` times); after that, or when the task raised,
    its exception is what :meth:`next` hands back. Leaving the ``with`` block cancels the
    tasks still queued (a running task stops only if it watches a stop request, see
    :func:`watch_stop`).
    """

    def __init__(
        self,
        cluster: Cluster,
        prefix: str,
        *,
        no_worker_s: float = NO_WORKER_S,
        say: Callable[[str], None] | None = None,
    ) -> None:
        from distributed import as_completed

        self.client, self.prefix, self.address = cluster.client, prefix, cluster.address
        self.no_worker_s, self.say = no_worker_s, say or _stderr
        self._items: dict[Any, Any] = {}
        self._done = as_completed()

    def submit(self, item: Any, fn: Callable[..., Any], *args: Any, key: str) -> None:
        """Run ``fn(*args)`` as the task ``PREFIX-KEY``; ``item`` comes back with its result."""
        fut = self.client.submit(fn, *args, key=f"{self.prefix}-{key}", pure=False)
        self._items[fut] = item
        self._done.add(fut)

    def __len__(self) -> int:
        return len(self._items)

    def in_flight(self) -> list[Any]:
        """The items of the tasks submitted and not yet taken back, in submission order."""
        return list(self._items.values())

    def next(self) -> tuple[Any, Any, Exception | None]:
        """The next task to finish: (item, result, None), or (item, None, its exception)."""
        from rt_controller.rig.supervise import RigInterrupted

        self._wait_ready()
        fut = next(self._done)
        item = self._items.pop(fut)
        try:
            result, error = fut.result(), None
        except RigInterrupted:  # SIGINT/SIGTERM to this process while it waited
            self._items[fut] = item
            raise
        except Exception as exc:  # the task raised, or its worker died too often
            result, error = None, exc
        fut.release()
        return item, result, error

    def _wait_ready(self) -> None:
        """Wait for a task to finish, saying so when the cluster has had no worker for
        ``no_worker_s`` (its only worker died): the tasks wait, the sweep does not end."""
        since = checked = time.monotonic()
        said = -math.inf
        check_s = min(1.0, self.no_worker_s / 4)
        while self._items and not self._done.has_ready():
            now = time.monotonic()
            if now - checked >= check_s:
                checked = now
                since = since if self._no_worker() else now
            if now - since >= self.no_worker_s and now - said >= 10 * self.no_worker_s:
                said = now
                self.say(
                    f"no worker in the cluster at {self.address} for {round(now - since, 1):g} s; "
                    "waiting (Ctrl-C keeps the finished rows)"
                )
            time.sleep(0.1)  # as as_completed itself polls

    def _no_worker(self) -> bool:
        """Whether the scheduler answers and has no worker (an unanswered query: unknown)."""
        try:
            return not self.client.scheduler_info(n_workers=1).get("workers")
        except Exception:  # a scheduler going down: not this message's business
            return False

    def drop_queued(self) -> None:
        """Cancel and forget the tasks no worker has started (a stop waits for the rest)."""
        try:
            started = {k for keys in self.client.processing().values() for k in keys}
        except Exception:  # a cluster going down: nothing is waited for
            started = set()
        queued = [f for f in self._items if f.key not in started]
        self._done.clear()
        self._items = {f: i for f, i in self._items.items() if f.key in started}
        self._done.update(self._items)
        with contextlib.suppress(Exception):
            self.client.cancel(queued, force=True)

    def cancel(self) -> None:
        """Cancel the tasks not taken back yet."""
        if self._items:
            with contextlib.suppress(Exception):  # a cluster already going down on Ctrl-C
                self.client.cancel(list(self._items), force=True)

    def __enter__(self) -> Tasks:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.cancel()


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


def stop_name(prefix: str) -> str:
    """A fresh name for a stop request (:func:`request_stop`, :func:`watch_stop`)."""
    return f"{prefix}-stop-{uuid.uuid4().hex}"


def request_stop(cluster: Cluster, name: str) -> None:
    """Tell the running tasks that watch ``name`` to stop (Dask never interrupts a task)."""
    from distributed import Event

    with contextlib.suppress(Exception):  # a cluster already going down
        Event(name, client=cluster.client).set()


@contextlib.contextmanager
def watch_stop(name: str | None, poll_s: float = 0.25) -> Iterator[threading.Event]:
    """Inside a task: a :class:`threading.Event` that is set once the client has called
    :func:`request_stop` with ``name`` (None: one that is never set)."""
    stop = threading.Event()
    if name is None:
        yield stop
        return
    from distributed import Event

    event = Event(name)
    if event.client is None:  # not in a task: nobody can ask
        yield stop
        return
    with contextlib.suppress(Exception):  # asked already (a task that starts after the stop)
        if event.is_set():
            stop.set()
    ended = threading.Event()

    def watch() -> None:
        while not ended.is_set():
            try:
                if event.wait(timeout=poll_s):
                    stop.set()
                    return
            except Exception:  # the scheduler went away: nobody can ask any more
                return

    watcher = threading.Thread(target=watch, name="hil-stop-watch", daemon=True)
    watcher.start()
    try:
        yield stop
    finally:
        ended.set()
        watcher.join(timeout=5 * poll_s)


@dataclass
class Outcome:
    """What one ``hil sweep`` did."""

    runs: int
    skipped: int
    ran: int = 0
    failed: int = 0
    kept_failed: list[str] = field(default_factory=list)
    """Failed runs of an earlier sweep in the folder, skipped (``point P rep R``)."""
    interrupted: bool = False
    wall_s: float = 0.0
    workers: int = 0
    scheduler: str = ""
    engine: str = ""
    spec_hash: str = ""
    version: str = field(default_factory=package_version)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


class ClusterLost(ConnectionError):
    """The cluster cancelled the tasks (its scheduler went away): they are no runs' rows."""


def stoppable_run(engine: Engine, task: RunTask, stop: str) -> dict[str, Any] | None:
    """In a task: ``engine(task)``, cancelled by the stop request ``stop`` (rig processes)."""
    from rt_controller.rig.failures import RigCancelled

    with watch_stop(stop) as cancel, contextlib.suppress(RigCancelled):  # no row: None
        return None if cancel.is_set() else engine(task, cancel)


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
    tasks: list[RunTask] | None = None,
    no_worker_s: float = NO_WORKER_S,
) -> Outcome:
    """Run every task of ``spec`` not yet in ``out`` and keep the rows; returns the outcome.

    ``cluster``: an open cluster to use (left open); else one is opened (and closed) from
    ``workers``/``scheduler``. ``on_row`` is called after each row is kept (tests use it to
    interrupt or to kill a worker). ``tasks``: ``spec.tasks(engine, log folder)`` expanded
    already (``hil sweep`` validates them before it touches ``out``), else expanded here.
    ``no_worker_s``: after so long without a worker, a line on stderr (:class:`Tasks`).
    """
    from rt_controller.rig.supervise import RigInterrupted, supervised

    out = Path(out)
    if tasks is None:
        tasks = spec.tasks(engine, (out / "logs") if keep_logs else None)
    t0 = time.monotonic()
    run_engine = tasks[0].engine if tasks else (engine or spec.study.engine)
    with ResultStore(out, spec, run_engine) as store:
        done = store.done(retry_failed)
        todo = [t for t in tasks if t.key not in done]
        result = Outcome(
            runs=len(tasks),
            skipped=len(tasks) - len(todo),
            engine=run_engine,
            spec_hash=spec.spec_hash,
            kept_failed=_kept_failed(store, tasks, done),
        )
        if not todo:
            return result
        own = cluster is None
        try:
            with supervised():
                cl = cluster or open_cluster(
                    workers, scheduler, worker_env=_target_env(out, scheduler, progress)
                )
                try:
                    result.workers, result.scheduler = cl.workers, cl.address
                    run = Engine(plant)
                    _collect(cl, todo, store, result, run, progress, on_row, no_worker_s)
                finally:
                    if own:
                        cl.close()
        except (KeyboardInterrupt, RigInterrupted):
            result.interrupted = True
        finally:
            result.wall_s = time.monotonic() - t0
    return result


def _kept_failed(store: ResultStore, tasks: list[RunTask], done: set[str]) -> list[str]:
    """The skipped runs whose kept row failed: the study is not all good without them."""
    rows = [store.rows[t.key] for t in tasks if t.key in done]
    return [f"point {r.get('point')} rep {r.get('rep')}" for r in rows if r.get("status") != "ok"]


def _target_env(out: Path, scheduler: str | None, progress: bool) -> dict[str, str]:
    """The local workers' compile target: the sweep's first run's (:mod:`.target`)."""
    from rt_controller.sweep.target import worker_env

    def say(line: str) -> None:
        if progress:
            print(f"hil sweep: {line}", file=sys.stderr)

    if scheduler is not None:  # the cluster's workers compile for their own hosts
        return {}
    return worker_env(out, say)


def _collect(
    cl: Cluster,
    todo: list[RunTask],
    store: ResultStore,
    result: Outcome,
    engine: Engine,
    progress: bool,
    on_row: Callable[[dict[str, Any], Cluster], None] | None,
    no_worker_s: float = NO_WORKER_S,
) -> None:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

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

    def say(line: str) -> None:
        print(f"hil sweep: {line}", file=sys.stderr)

    def keep(row: dict[str, Any]) -> None:
        store.add(row)
        result.ran += 1
        result.failed += row.get("status") != "ok"

    tasks = Tasks(cl, "hil-sweep", no_worker_s=no_worker_s, say=say)
    stop = stop_name("hil-sweep") if todo[0].engine == "rig" else None  # rigs: stoppable
    with tasks, bar:  # interrupted: nothing left keeps running for us
        try:
            for task in todo:
                call = (engine, task) if stop is None else (stoppable_run, engine, task, stop)
                tasks.submit(task, *call, key=task.key)
            bar_task = bar.add_task("runs", total=len(todo), failed=0)
            while tasks:
                task, row, exc = tasks.next()
                if isinstance(exc, CancelledError):  # not by us: the scheduler went away
                    logging.getLogger("distributed.client").setLevel(logging.CRITICAL)
                    raise ClusterLost(
                        f"the Dask cluster at {cl.address} went away after {result.ran} "
                        f"run(s); the finished rows are kept in {store.out}: the same "
                        "command resumes"
                    )
                if exc is not None:  # a lost task is a failed run
                    row = failed_row(task, " ".join(f"{type(exc).__name__}: {exc}".split()))
                keep(row)
                bar.update(bar_task, advance=1, failed=result.failed)
                if on_row is not None:
                    on_row(row, cl)
        finally:
            if stop is not None and len(tasks):  # stopped: the running rigs stop, waited for
                request_stop(cl, stop)
                tasks.drop_queued()
                while tasks:
                    _, row, _ = tasks.next()
                    if row is not None:  # a run that ended before the stop reached it
                        keep(row)
