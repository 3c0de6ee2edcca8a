"""The paper's experiments (Section V) on the rig: Fig. 3, Fig. 4 and Table I.

Each experiment is a list of :class:`RunSpec` (law, horizon, camera noise, noise seed). A run is
one :func:`rt_controller.rig.processes.run_rig` call — emulator, vision and controller as separate
processes, lockstep unless asked for real time — with its own configuration file written next to
its MCAP log, so ``hil up --config ... --law ...`` repeats it exactly. This module plans and
runs them; :mod:`rt_controller.rig.experiment_report` turns the results into one JSON-ready dict,
PNG figures and a ``report.md`` (:func:`rt_controller.rig.experiment_report.write_outputs`).

Identical specs are run once (``all`` shares Fig. 3's and Fig. 4's RHC T = 0.02 s run). Batches
(:func:`batches`) go as tasks (:func:`run_batch`) on ``hil sweep``'s Dask executor.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hal.bus import process_spec
from hal.config import RigConfig, image_noise_error, load_config
from hal.errors import HalError
from rt_controller.config_rules import apply_overrides, config_toml
from rt_controller.errors import ControllerConfigError, ControllerError
from rt_controller.rig.failures import RigCancelled
from rt_controller.rig.options import RigOptions, local_rig, private_default_bus
from rt_controller.rig.processes import run_rig, run_rig_plan
from rt_controller.rig.supervise import RigInterrupted

EXPERIMENTS = ("fig3", "fig4", "table1")
FIG3_LAWS = ("rhc", "ioc", "pbc")
FIG3_HORIZON_S = 0.02
HORIZONS_S = (0.02, 0.1, 1.0)
TABLE1_DEFAULT_NOISE_PX = 0.5
"""``table1``'s pixel noise on the analytic camera when neither ``--noise`` nor the config sets
one (repetitions must differ). The rendering camera's repetitions differ by its sensor's noise."""
STEADY_FROM_S = 4.0
"""The paper compares the steady state "after t = 4 s"; J over [4 s, end) is reported too."""

Runner = Callable[[RigOptions], dict[str, Any]]


@dataclass(frozen=True)
class RunSpec:
    """One rig run: the law, the RHC horizon (None for PBC/IOC), camera noise and its seed."""

    law: str
    horizon_s: float | None
    noise_px: float
    seed: int
    rep: int | None = None
    """Repetition index for ``table1`` runs (their name always carries the seed)."""

    @property
    def name(self) -> str:
        """File-name-safe identity, e.g. ``rhc-T0.02``, ``rhc-T0.1-seed3`` or (pixel noise on
        the analytic camera) ``rhc-T0.1-noise0.5-seed3``."""
        out = self.law if self.horizon_s is None else f"{self.law}-T{fmt_t(self.horizon_s)}"
        if self.noise_px > 0:
            out += f"-noise{self.noise_px:g}"
        if self.noise_px > 0 or self.rep is not None:
            out += f"-seed{self.seed}"
        return out

    @property
    def label(self) -> str:
        """Human label: ``RHC T = 0.1 s, seed 3`` or ``RHC T = 0.1 s, noise 0.5 px, seed 3``."""
        out = self.law.upper() + (
            "" if self.horizon_s is None else f" T = {fmt_t(self.horizon_s)} s"
        )
        if self.noise_px > 0:
            out += f", noise {self.noise_px:g} px"
        if self.noise_px > 0 or self.rep is not None:
            out += f", seed {self.seed}"
        return out


@dataclass
class Settings:
    """What ``hil experiment`` was asked to do."""

    experiments: tuple[str, ...]
    out: Path
    reps: int = 5
    duration_s: float = 10.0
    noise_px: float | None = None
    """``--noise``: overrides camera.noise_px for every experiment when set."""
    realtime: bool = False
    config: str | None = None
    can: str | None = None
    jobs: int | None = None
    """Rigs run at once (``--jobs``, the workers of the local Dask cluster); None:
    :func:`default_jobs`."""
    scheduler: str | None = None
    """``--scheduler``: run the batches on this existing Dask cluster, not a local one."""
    fresh_processes: bool = False
    """``--fresh-processes``: start the rig anew for every lockstep run instead of running
    the runs that share an emulator configuration on one set of processes (:func:`batches`)."""
    profile: str | None = None
    """``--profile``: the hardware profile of every run (``hardware.profile``); None: the
    config's (:meth:`hardware_profile`)."""
    sets: dict[str, Any] = field(default_factory=dict)
    """``--set``: keys changed for every run."""

    def base_config(self) -> RigConfig:
        """The config file (else the embedded one) with the ``--set`` keys."""
        return apply_overrides(load_config(self.config), sets=self.sets, from_command_line=True)

    def validate(self) -> None:
        """Raise :class:`ControllerConfigError` naming the bad option."""
        process_spec(self.can or self.base_config().transport.can)  # before any run
        local_rig(self.config)
        bad = [e for e in self.experiments if e not in EXPERIMENTS]
        if bad or not self.experiments:
            raise ControllerConfigError(f"unknown experiment(s) {bad}; known: {EXPERIMENTS}")
        if self.reps < 1:
            raise ControllerConfigError(f"--reps must be at least 1, got {self.reps}")
        if not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise ControllerConfigError(f"--duration must be positive, got {self.duration_s}")
        if self.noise_px is not None and not (self.noise_px >= 0 and math.isfinite(self.noise_px)):
            raise ControllerConfigError(f"--noise must be non-negative, got {self.noise_px}")
        if self.jobs is not None and self.jobs > 1:
            if self.jobs > MAX_JOBS:
                raise ControllerConfigError(f"--jobs must be at most {MAX_JOBS}, got {self.jobs}")
            if self.realtime:
                raise ControllerConfigError(
                    "--jobs above 1 needs lockstep runs: real-time runs at once would share "
                    "the CPU, and their timing is part of the result"
                )
            if not self.private_buses():
                raise ControllerConfigError(
                    f"--jobs above 1 needs a private bus per run; {self.shared_bus()} is one "
                    "bus that all runs would share"
                )
        elif self.jobs is not None and self.jobs < 1:
            raise ControllerConfigError(f"--jobs must be at least 1, got {self.jobs}")
        if self.scheduler is not None and self.jobs is not None:
            raise ControllerConfigError(
                "--jobs sizes the local cluster; with --scheduler the cluster has its own"
            )

    def shared_bus(self) -> str:
        """The bus every run would use when runs cannot get private ones."""
        from hal.bus import resolve_spec

        cfg = self.base_config()
        return self.can or str(
            resolve_spec(None if cfg.transport.can == "auto" else cfg.transport.can)
        )

    def private_buses(self) -> bool:
        """Whether each run gets a bus of its own (the automatic host-local ``udp_multicast``
        bus, see :func:`bus_for_run`); ``--can`` or a SocketCAN interface is one shared bus."""
        return self.can is None and private_default_bus(self.config) is not None

    def parallel(self) -> bool:
        """Whether runs may run at once: lockstep runs, each on a private bus."""
        return not self.realtime and self.private_buses()

    def effective_jobs(self) -> int:
        """``jobs``, else :func:`default_jobs`."""
        return self.jobs if self.jobs is not None else default_jobs(self)

    @property
    def clock(self) -> str:
        return "realtime" if self.realtime else "lockstep"

    def hardware_profile(self) -> str:
        """The hardware profile every run uses: ``--profile``, else the config's."""
        return self.profile or self.base_config().hardware.profile

    def shares_processes(self) -> bool:
        """Whether lockstep runs may share one set of processes as a plan
        (``hil controller --plan``): the plan resets the emulated DSP's scenario, which only
        the ``dsp`` profile has; ``cia402`` runs start the rig anew for every run."""
        return not (self.realtime or self.fresh_processes) and self.hardware_profile() == "dsp"


@dataclass
class RunResult:
    """A planned run and, once run, its outcome."""

    spec: RunSpec
    config: RigConfig
    config_file: Path
    log: Path
    status: str = "pending"
    """pending (not run; ``error`` says why when known) | ok | failed"""
    can: str | None = None
    """The CAN bus spec the run used (see :func:`bus_for_run`)."""
    summary: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    wall_s: float | None = None
    J_steady: float | None = None
    """J over t >= STEADY_FROM_S (from the log), None if the run is shorter."""

    @property
    def J(self) -> float | None:
        j = self.summary.get("J")
        return float(j) if isinstance(j, int | float) and math.isfinite(j) else None


MAX_JOBS = 16


def default_jobs(settings: Settings) -> int:
    """Lockstep runs on private buses: one rig per CPU (a lockstep period passes from process
    to process, so one rig keeps about one core busy; results do not depend on it, a lockstep
    run is deterministic); otherwise 1."""
    if not settings.parallel():
        return 1
    return max(1, min(os.cpu_count() or 1, MAX_JOBS))


def fmt_t(horizon_s: float) -> str:
    """A horizon as the paper writes it: 0.02, 0.1, 1.0."""
    text = f"{horizon_s:g}"
    return text if "." in text or "e" in text else f"{text}.0"


# ------------------------------------------------------------------------------------- plan
def table1_noise(settings: Settings, base: RigConfig) -> float:
    """``--noise``, else the config's camera noise, else on the analytic camera 0.5 px when
    that is 0 (the rendering camera: 0, its sensor's noise makes the repetitions differ)."""
    if settings.noise_px is not None:
        return settings.noise_px
    if base.camera.noise_px > 0 or base.camera.model == "image":
        return base.camera.noise_px
    return TABLE1_DEFAULT_NOISE_PX


def plan(settings: Settings, base: RigConfig) -> dict[str, list[RunSpec]]:
    """The runs of each requested experiment, in order. :class:`ControllerConfigError` for a
    pixel noise the configured camera cannot apply (:func:`~hal.config.image_noise_error`)."""
    fig_noise = base.camera.noise_px if settings.noise_px is None else settings.noise_px
    problem = image_noise_error(base.with_overrides({"camera.noise_px": fig_noise}))
    if problem is not None:
        where = "--noise" if settings.noise_px else "the config"
        raise ControllerConfigError(f"{where}: {problem}")
    seed = base.camera.seed
    out: dict[str, list[RunSpec]] = {}
    for exp in EXPERIMENTS:
        if exp not in settings.experiments:
            continue
        if exp == "fig3":
            out[exp] = [
                RunSpec(law, FIG3_HORIZON_S if law == "rhc" else None, fig_noise, seed)
                for law in FIG3_LAWS
            ]
        elif exp == "fig4":
            out[exp] = [RunSpec("rhc", h, fig_noise, seed) for h in HORIZONS_S]
        else:
            noise = table1_noise(settings, base)
            out[exp] = [
                RunSpec("rhc", h, noise, rep, rep=rep)
                for h in HORIZONS_S
                for rep in range(settings.reps)
            ]
    return out


def run_config(settings: Settings, spec: RunSpec) -> RigConfig:
    """The run's configuration, built by the same rules as ``hil controller --horizon T``.

    When only the horizon is given, N = max(rhc.steps, ceil(T / 0.05)) (T = 1.0 s -> N = 20).
    """
    cfg = apply_overrides(
        settings.base_config(),
        law=spec.law,
        horizon=spec.horizon_s,
        profile=settings.profile,
    )
    return cfg.with_overrides(
        {
            "camera.noise_px": spec.noise_px,
            "camera.seed": spec.seed,
            "controller.clock": settings.clock,
        }
    )


def prepare(settings: Settings) -> tuple[dict[str, list[RunSpec]], dict[str, RunResult]]:
    """Plan the runs, write each run's config file; (plan, unique runs by name in run order)."""
    base = settings.base_config()
    runs_by_exp = plan(settings, base)
    (settings.out / "configs").mkdir(parents=True, exist_ok=True)
    (settings.out / "logs").mkdir(parents=True, exist_ok=True)
    runs: dict[str, RunResult] = {}
    for specs in runs_by_exp.values():
        for spec in specs:
            if spec.name in runs:
                continue
            cfg = run_config(settings, spec)
            cfg_file = settings.out / "configs" / f"{spec.name}.toml"
            cfg_file.write_text(config_toml(cfg), encoding="utf-8")
            if load_config(cfg_file) != cfg:  # pragma: no cover - guards config_toml
                raise ControllerError(f"{cfg_file}: the written config does not read back")
            log = settings.out / "logs" / f"{spec.name}.mcap"
            runs[spec.name] = RunResult(spec, cfg, cfg_file, log)
    return runs_by_exp, runs


# -------------------------------------------------------------------------------------- run
def execute(
    run: RunResult,
    settings: Settings,
    runner: Runner | None = None,
    cancel: threading.Event | None = None,
) -> RunResult:
    """Run one spec through the rig (``runner``, default :func:`run_rig`).

    A failure is recorded on the result (status ``failed`` and the error), not raised. A run
    stopped through ``cancel`` stays ``pending`` (not run), as one cut short by a signal.
    """
    t0 = time.monotonic()
    try:
        run.can = bus_for_run(settings, run)
        opts = RigOptions(
            config=str(run.config_file),
            law=run.spec.law,
            duration_s=settings.duration_s,
            lockstep=not settings.realtime,
            can=run.can,
            log=run.log,
            cancel=cancel,
        )
        finish(run, (runner or run_rig)(opts))
    except RigInterrupted:
        raise  # the whole sweep stops; the caller writes up what ran
    except RigCancelled:
        run.status, run.summary = "pending", {}
    except (ControllerError, HalError, OSError) as exc:
        run.status, run.error = "failed", f"{type(exc).__name__}: {exc}"
    finally:
        run.wall_s = time.monotonic() - t0
    return run


def finish(run: RunResult, summary: dict[str, Any]) -> None:
    """Record a finished run's summary: ``ok``, or ``failed`` when it was not clean."""
    run.summary = summary
    problems = summary.get("problems") or []
    if problems:
        run.status, run.error = "failed", f"run not clean: {'; '.join(problems)}"
    elif run.J is None:  # nothing to tabulate
        run.status, run.error = "failed", f"the controller reported no finite J: {summary.get('J')}"
    else:
        run.status = "ok"
    if "error" not in (summary.get("log_contents") or {}):  # a run cut short before its log
        run.J_steady = steady_cost(run.log)


def batches(
    runs: list[RunResult], settings: Settings, jobs: int | None = None
) -> list[list[RunResult]]:
    """The runs grouped for one set of rig processes each, in run order.

    Lockstep runs whose configurations agree in all that the emulator and vision processes
    read (:func:`rt_controller.runtime.plan.world_of`: everything but the controller's own
    sections) share one set: the controller runs them as a plan, resetting the emulated DSP's
    scenario between them, which starts each exactly as fresh processes would. While there are
    fewer batches than rigs may run at once (``jobs``, default ``settings.effective_jobs()``),
    the largest is split in two. Real-time runs, all runs with ``fresh_processes`` and
    runs of the ``cia402`` profile (:meth:`Settings.shares_processes`) are batches of one.
    """
    if not settings.shares_processes():
        return [[r] for r in runs]
    from rt_controller.runtime.plan import world_of

    groups: dict[str, list[RunResult]] = {}
    for run in runs:
        groups.setdefault(json.dumps(world_of(run.config), sort_keys=True), []).append(run)
    out = list(groups.values())
    while len(out) < (settings.effective_jobs() if jobs is None else jobs):
        big = max(out, key=len)
        if len(big) < 2:
            break
        i, half = out.index(big), (len(big) + 1) // 2
        out[i : i + 1] = [big[:half], big[half:]]
    return out


def execute_batch(
    batch: list[RunResult], settings: Settings, cancel: threading.Event | None = None
) -> list[RunResult]:
    """Run a batch (:func:`batches`): one run through :func:`execute`, more as a plan on one
    set of processes (:func:`~rt_controller.rig.processes.run_rig_plan`). Failures are
    recorded on the runs (:func:`~rt_controller.rig.experiment_plan.record_plan`); runs stopped
    through ``cancel``, or after a shared process died, stay ``pending`` (not run)."""
    if len(batch) == 1:
        return [execute(batch[0], settings, None, cancel)]
    t0 = time.monotonic()
    can = bus_for_run(settings, batch[0])
    plan_file = settings.out / "plans" / f"{batch[0].spec.name}.json"
    plan_file.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "runs": [
            {
                "name": r.spec.name,
                "config": str(r.config_file),
                "law": r.spec.law,
                "duration_s": settings.duration_s,
                "log": str(r.log),
            }
            for r in batch
        ]
    }
    plan_file.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    opts = RigOptions(
        config=str(batch[0].config_file),
        duration_s=settings.duration_s * len(batch),
        lockstep=True,
        can=can,
        plan=plan_file,
        cancel=cancel,
    )
    from rt_controller.rig.experiment_plan import record_plan

    summaries: list[dict[str, Any]] = []
    error: BaseException | None = None
    cancelled = False
    try:
        summaries, error = run_rig_plan(opts, len(batch))
    except RigInterrupted:
        raise
    except RigCancelled as exc:  # the runs that ended before keep their results
        summaries, cancelled = list(exc.summaries), True
    except (ControllerError, HalError, OSError) as exc:
        error = exc
    record_plan(batch, summaries, error, can, finish, cancelled)  # after a death: not run
    if batch[0].wall_s is not None:  # the first run carries the processes' start-up
        batch[0].wall_s += max(0.0, time.monotonic() - t0 - sum(r.wall_s or 0 for r in batch))
    return batch


def run_batch(batch: list[RunResult], settings: Settings, stop: str | None) -> list[RunResult]:
    """A batch as one task on the sweep's Dask executor: :func:`execute_batch`, stopped (its
    runs left pending) when the experiment requests ``stop``
    (:func:`rt_controller.sweep.executor.request_stop`). The runs' config files and logs are
    under ``settings.out``, which the worker must see at the same path."""
    from rt_controller.sweep.executor import watch_stop

    missing = [r.config_file for r in batch if not r.config_file.is_file()]
    if missing:
        import socket

        error = (
            f"the worker on {socket.gethostname()} cannot read {missing[0]}: the experiment's "
            "--out must be a folder the workers share"
        )
        for run in batch:
            run.status, run.error = "failed", error
        return batch
    with watch_stop(stop) as cancel:
        if cancel.is_set():  # the experiment stopped before this batch started: not run
            return batch
        return execute_batch(batch, settings, cancel)


def bus_for_run(settings: Settings, run: RunResult) -> str:
    """The bus the run will use, named so that results.json and the rerun commands record it.

    ``--can``, else :func:`~rt_controller.rig.options.private_default_bus` (the automatic
    host-local ``udp_multicast`` bus becomes a private port, as every rig gets), else the
    config's bus as resolved (SocketCAN cannot be isolated and is used as it is). It is passed
    to the rig explicitly, so the recorded private port is the one the processes use.
    """
    from hal.bus import resolve_spec

    if settings.can:
        return settings.can
    private = private_default_bus(str(run.config_file))
    return private or str(resolve_spec(run.config.transport.can))


def steady_cost(log: Path, from_s: float = STEADY_FROM_S) -> float | None:
    """Sum of the stage cost over t >= from_s, divided by the rate; None if the run is shorter."""
    from rt_controller.logtools.reader import read_log

    data = read_log(log, raw=False)
    t, cost, rate = data.column("sim_time_s"), data.column("cost"), data.rate_hz
    if t is None or cost is None or not rate or t.size == 0 or float(np.nanmax(t)) < from_s:
        return None
    mask = np.asarray(t, dtype=float) >= from_s - 1e-9
    return float(np.nansum(np.asarray(cost, dtype=float)[mask]) / rate)
