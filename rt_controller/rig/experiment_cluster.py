"""``hil experiment``'s runs as Dask tasks on the executor of ``hil sweep``, with a progress
bar and a line a run on the console; it gives up after :data:`MAX_CONSECUTIVE_FAILURES` failed
runs in a row."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.console import Console

    from rt_controller.rig.experiment import RunResult, Settings
    from rt_controller.sweep.executor import Cluster

MAX_CONSECUTIVE_FAILURES = 3


def sweep(cl: Cluster, runs: dict[str, RunResult], settings: Settings, console: Console) -> None:
    """Run every pending run as Dask tasks on ``cl``, a cluster of the executor of ``hil
    sweep`` (:mod:`rt_controller.sweep.executor`), one task per batch
    (:func:`~rt_controller.rig.experiment.batches`), at most as many at a time as the cluster
    has workers (one for runs that may not run at once), with a progress bar on stderr.

    The local cluster's workers are threads of this process (``--jobs`` of them): a task only
    supervises its rig's processes, which stay children of ``hil experiment``. A stop request
    (:class:`~rt_controller.rig.supervise.RigInterrupted`, main thread only) asks the running
    tasks to stop their rigs (their runs stay pending) and waits for them before this returns.
    """
    import uuid

    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from rt_controller.rig.experiment import EXPERIMENTS, batches, run_batch
    from rt_controller.rig.supervise import signals_deferred
    from rt_controller.sweep.executor import Tasks, request_stop, stop_name

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    local = settings.scheduler is None
    prefix = f"hil-experiment-{uuid.uuid4().hex[:12]}"  # unique on a shared cluster
    stop = stop_name(prefix)
    jobs = settings.effective_jobs() if local else cl.workers if settings.parallel() else 1
    queue = batches(list(runs.values()), settings, jobs)
    failed_in_a_row = 0
    name = "all" if settings.experiments == EXPERIMENTS else " ".join(settings.experiments)
    with (
        Progress(*columns, console=console, transient=False) as progress,
        Tasks(cl, prefix) as tasks,
    ):
        task = progress.add_task("runs", total=len(runs))
        try:
            while queue or len(tasks):
                while queue and len(tasks) < jobs and failed_in_a_row < MAX_CONSECUTIVE_FAILURES:
                    batch = queue.pop(0)
                    tasks.submit(batch, run_batch, batch, settings, stop, key=batch[0].spec.name)
                if not len(tasks):
                    break
                labels = ", ".join(
                    b[0].spec.label + (f" (+{len(b) - 1} on its processes)" if len(b) > 1 else "")
                    for b in tasks.in_flight()
                )
                progress.update(task, description=labels)
                for run in _take(tasks, runs):
                    progress.advance(task)
                    failed_in_a_row = _report_run(progress.console, run, failed_in_a_row, name)
        finally:
            if len(tasks):  # stopped: the running tasks stop their rigs; wait for them
                with signals_deferred(deliver=False):  # a second stop signal: no more to do
                    request_stop(cl, stop)
                    while len(tasks):
                        _take(tasks, runs)


def _take(tasks: Any, runs: dict[str, RunResult]) -> list[RunResult]:
    """The runs of the next batch to finish, recorded in ``runs``; a batch whose task never
    came back (it raised, or its worker died too often) has failed runs."""
    batch, done, exc = tasks.next()
    if exc is not None:
        error = " ".join(f"{type(exc).__name__}: {exc}".split())
        for run in batch:
            run.status, run.error = "failed", error
        done = batch
    for run in done:  # a worker's copy of the run: its outcome goes into the planned one
        planned = runs[run.spec.name]
        if planned is not run:
            vars(planned).update(vars(run))
    return [runs[r.spec.name] for r in done]


def _report_run(console: Console, run: RunResult, failed_in_a_row: int, experiment: str) -> int:
    """One finished run's line; the count of failures in a row after it (at the limit, the
    line that ``experiment`` gives up)."""
    if run.status == "ok":
        console.print(
            f"{run.spec.label}: J = {run.J:.4f}, |f_final| = "
            f"{run.summary.get('f_final_norm', float('nan')):.3g} px ({_took(run)})"
        )
        return 0
    if run.status == "pending":  # not run: no failure of its own
        if run.error:
            console.print(f"[yellow]{run.spec.label}: {run.error}[/]", highlight=False)
        return failed_in_a_row
    console.print(f"[red]{run.spec.label}: FAILED[/] ({_took(run)})")
    failed_in_a_row += 1
    if failed_in_a_row == MAX_CONSECUTIVE_FAILURES:
        console.print(
            f"[red]{failed_in_a_row} failures in a row: giving up on hil experiment {experiment}[/]"
        )
    return failed_in_a_row


def _took(run: RunResult) -> str:
    return "—" if run.wall_s is None else f"{run.wall_s:.1f} s"
