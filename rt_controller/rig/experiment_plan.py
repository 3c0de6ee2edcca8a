"""The outcome of each run of a plan (:func:`rt_controller.rig.experiment.execute_batch`: runs
sharing one set of rig processes) from what :func:`~rt_controller.rig.processes.run_rig_plan`
handed back: the summaries of the runs that ended and why the rest did not."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from hal.errors import HalError
from rt_controller.errors import ControllerError
from rt_controller.rig.failures import RigProcessDied


def record_plan(
    batch: list[Any],
    summaries: list[dict[str, Any]],
    error: BaseException | None,
    can: str | None,
    finish: Callable[[Any, dict[str, Any]], None],
    cancelled: bool = False,
) -> None:
    """Record each run of ``batch`` (its :class:`~rt_controller.rig.experiment.RunResult`):
    one with a summary as it ended (``finish``, :func:`~rt_controller.rig.experiment.finish`,
    handed in: this module imports none of ``experiment``); one without, ``pending`` when the
    plan was ``cancelled``, else ``failed`` with ``error``.

    When a process the runs share died (:class:`RigProcessDied`: the emulator, vision or the
    controller), the run it cut short failed (its summary says how) and the runs after it
    never started: they stay ``pending`` (not run), their error saying which process died in
    which run, instead of failures of their own.
    """
    text = None if error is None else f"{type(error).__name__}: {error}"
    died = error if isinstance(error, RigProcessDied) else None
    last = summaries[-1] if summaries else {}
    during = last.get("run") if last.get("ended_by") else None  # the run the death cut short
    by_name = {s.get("run"): s for s in summaries}
    for run in batch:
        summary = by_name.get(run.spec.name)
        if summary is None and cancelled:  # not run
            run.status, run.summary = "pending", {}
            continue
        run.can = can
        if summary is None:
            run.wall_s = None
            if died is not None and during is not None:
                run.status, run.summary = "pending", {}
                run.error = f"not run: the {died.end.name} ended in run {during} ({died.end.how})"
            else:
                run.status, run.error = "failed", text or "the controller printed no summary"
                during = run.spec.name if died is not None else None
            continue
        try:
            finish(run, summary)
        except (ControllerError, HalError, OSError) as exc:  # an unreadable log
            run.status, run.error = "failed", f"{type(exc).__name__}: {exc}"
        wall = summary.get("wall_s")
        run.wall_s = float(wall) if isinstance(wall, int | float) else None
