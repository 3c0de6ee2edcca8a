"""Run one sweep task and return its result row; a failure is a row too, never an exception.

* ``simulate``: the in-process closed loop of ``hil simulate``
  (:func:`rt_controller.control.simulate.run_closed_loop`) on a plant built by the plant class
  it is handed (the emulator's :class:`plant_emulator.world.World`, from ``commands/sweep.py``;
  this package never imports the emulator). Its result depends only on the task.
* ``rig``: the emulator, vision and controller processes in lockstep, as ``hil experiment``
  runs them (:func:`rt_controller.rig.processes.run_rig`, a private bus and zenoh port each).

The row holds the measured figures (``METRICS``); :mod:`rt_controller.sweep.results` fixes
their types. ``wall_s`` is the only field that depends on the machine and the moment.
"""

from __future__ import annotations

import math
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hal.config import RigConfig, config_from_dict
from rt_controller.errors import ControllerError
from rt_controller.rig.failures import RigCancelled
from rt_controller.sweep.spec import RunTask

METRICS = (
    "J",
    "f_final_norm",
    "max_abs_tau1",
    "max_abs_tau2",
    "fallbacks",
    "dsp_faults",
    "deadline_misses",
    "ticks",
)
"""The figures of a run (NaN or 0 for a failed run)."""


class RunTimeout(ControllerError, TimeoutError):
    """The run went past ``study.timeout_s`` of wall-clock time."""


def package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hil-rhc-visual-servo")
    except PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        return "unknown"


@dataclass(frozen=True)
class Engine:
    """The task runner sent to the workers: ``Engine(World)(task) -> row``. ``plant`` builds
    the simulate engine's plant from a config (None: only the rig engine works); ``cancel``
    stops a rig run (see :func:`run_task`)."""

    plant: Callable[[RigConfig], Any] | None = None

    def __call__(self, task: RunTask, cancel: threading.Event | None = None) -> dict[str, Any]:
        return run_task(task, self.plant, cancel)


def base_row(task: RunTask, status: str = "ok", error: str = "") -> dict[str, Any]:
    """A row of ``task`` with no figures yet (NaN, 0), ``wall_s`` NaN."""
    return {
        "run_key": task.key,
        "spec_hash": task.spec_hash,
        "point": task.point,
        "rep": task.rep,
        "seed": task.seed,
        **task.axes,
        "engine": task.engine,
        "status": status,
        "error": error,
        "problems": "",
        **dict.fromkeys(METRICS[:4], math.nan),
        **dict.fromkeys(METRICS[4:], 0),
        "wall_s": math.nan,
        "version": package_version(),
    }


def run_task(
    task: RunTask,
    plant: Callable[[RigConfig], Any] | None = None,
    cancel: threading.Event | None = None,
) -> dict[str, Any]:
    """The task's row: its identity, axis values, figures, status and error. A rig run
    stopped through ``cancel`` (its processes stopped) raises :class:`RigCancelled`: it has
    no row, a resume runs it."""
    t0 = time.perf_counter()
    row = base_row(task)
    try:
        if task.engine == "simulate":
            if plant is None:
                raise ControllerError("the simulate engine was given no plant")
            row.update(simulate_run(task, plant, t0 + task.timeout_s))
        elif task.engine == "rig":
            row.update(rig_run(task, cancel))
        else:
            raise ControllerError(f"unknown engine {task.engine!r}")
    except RigCancelled:
        raise
    except Exception as exc:  # any failure of one run is recorded, the sweep goes on
        row["status"] = "failed"
        row["error"] = " ".join(f"{type(exc).__name__}: {exc}".split())[:2000]
    row["wall_s"] = time.perf_counter() - t0
    row["version"] = package_version()
    return row


# --------------------------------------------------------------------------------- simulate
class _Deadline:
    """A plant that raises :class:`RunTimeout` once the wall clock passes ``deadline``."""

    def __init__(self, plant: Any, deadline: float, timeout_s: float) -> None:
        self.plant, self.deadline, self.timeout_s = plant, deadline, timeout_s

    @property
    def t(self) -> float:
        return self.plant.t

    def measure(self) -> Any:
        return self.plant.measure()

    def hold(self, tau: Any, steps: int) -> None:
        if time.perf_counter() > self.deadline:
            raise RunTimeout(f"timed out after {self.timeout_s:g} s (study.timeout_s)")
        self.plant.hold(tau, steps)


def limit_fault(cfg: RigConfig, t: Any, q: Any, dq: Any) -> str:
    """The DSP fault the rig's emulated DSP would have raised first (position or velocity
    limit), as text, or ""; the closed loop runs on where the rig would remove torque."""
    import numpy as np

    d = cfg.dsp
    below = np.any(q < np.array(d.q_min), axis=1) | np.any(q > np.array(d.q_max), axis=1)
    fast = np.any(np.abs(dq) > np.array(d.dq_max), axis=1)
    for name, hits in (("position_limit", below), ("velocity_limit", fast)):
        idx = np.flatnonzero(hits)
        if idx.size:
            return f"{name} at t = {float(t[idx[0]]):.3f} s"
    return ""


def simulate_run(
    task: RunTask, plant: Callable[[RigConfig], Any], deadline: float
) -> dict[str, Any]:
    import numpy as np

    from rt_controller.control.controller import Controller
    from rt_controller.control.simulate import run_closed_loop

    cfg = config_from_dict(task.config, source="run config")
    ctl = cfg.controller
    result = run_closed_loop(
        _Deadline(plant(cfg), deadline, task.timeout_s),
        Controller(cfg),
        cfg,
        task.duration_s,
        predict=ctl.predict_state and ctl.predict_features,
    )
    tr = result.trace
    tau = np.abs(tr.array("tau"))
    fault = limit_fault(cfg, tr.array("t"), tr.array("q"), tr.array("dq"))
    if task.log_dir:
        write_trace(Path(task.log_dir) / f"{task.key}.parquet", tr)
    return {
        "J": result.J,
        "f_final_norm": float(np.linalg.norm(tr.f[-1])),
        "max_abs_tau1": float(tau[:, 0].max()),
        "max_abs_tau2": float(tau[:, 1].max()),
        "fallbacks": int(np.sum(tr.fallback)),
        "dsp_faults": 1 if fault else 0,
        "deadline_misses": 0,
        "ticks": len(tr.t),
        "problems": f"the DSP would fault: {fault}" if fault else "",
    }


def write_trace(path: Path, trace: Any) -> None:
    """A simulate run's per-tick trace as Parquet (``--keep-logs``; the run has no MCAP)."""
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols: dict[str, Any] = {"t": trace.array("t"), "cost": trace.array("cost")}
    for name in ("q", "dq", "f", "u", "tau"):
        arr = np.asarray(trace.array(name), dtype=float).reshape(len(trace.t), -1)
        for j in range(arr.shape[1]):
            cols[f"{name}{j + 1}"] = arr[:, j]
    cols["fallback"] = trace.array("fallback").astype(bool)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table(cols), path)


# -------------------------------------------------------------------------------------- rig
def rig_run(task: RunTask, cancel: threading.Event | None = None) -> dict[str, Any]:
    """The task on the lockstep rig processes; figures from the controller's summary and its
    MCAP log (max |tau|). ``cancel`` set: the processes are stopped, :class:`RigCancelled`."""
    import numpy as np

    from rt_controller.config_rules import config_toml
    from rt_controller.logtools.reader import read_log
    from rt_controller.rig.options import RigOptions
    from rt_controller.rig.processes import run_rig
    from rt_controller.runtime.counters import run_problems

    cfg = config_from_dict(task.config, source="run config").with_overrides(
        {"controller.clock": "lockstep"}
    )
    with tempfile.TemporaryDirectory(prefix="hil-sweep-run-") as tmp:
        cfg_file = Path(tmp) / "run.toml"
        cfg_file.write_text(config_toml(cfg, f"hil sweep run {task.key}"), encoding="utf-8")
        if task.log_dir:
            Path(task.log_dir).mkdir(parents=True, exist_ok=True)
            log = Path(task.log_dir) / f"{task.key}.mcap"
        else:
            log = Path(tmp) / "run.mcap"
        summary = run_rig(
            RigOptions(
                config=str(cfg_file),
                law=cfg.controller.law,
                duration_s=task.duration_s,
                lockstep=True,
                log=log,
                wall_timeout_s=task.timeout_s,
                cancel=cancel,
            )
        )
        tau = read_log(log, raw=False).column("tau")
    tau = np.abs(np.asarray(tau, dtype=float)).reshape(-1, 2) if tau is not None else None
    faults = summary.get("dsp_faults") or {}
    return {
        "J": _number(summary.get("J")),
        "f_final_norm": _number(summary.get("f_final_norm")),
        "max_abs_tau1": float(np.nanmax(tau[:, 0])) if tau is not None and tau.size else math.nan,
        "max_abs_tau2": float(np.nanmax(tau[:, 1])) if tau is not None and tau.size else math.nan,
        "fallbacks": int(summary.get("fallbacks", 0)),
        "dsp_faults": int(sum(int(v) for v in faults.values())),
        "deadline_misses": int(summary.get("deadline_misses", 0)),
        "ticks": int(summary.get("ticks", 0)),
        "problems": "; ".join(run_problems(summary)),
    }


def _number(value: Any) -> float:
    """A summary's figure as a float; NaN where it has none (JSON's null: a run without law
    ticks has no final features)."""
    return float(value) if isinstance(value, int | float) else math.nan
