"""Benchmark of the C/GMRES update on the paper scenario closed loop (``hil bench solver``).

The solver runs in closed loop with a plant: by default the nominal model's eq. (12) integrated
by RK4 at ``rates.physics_hz`` with u held over each control period (the target jump is
ignored); the scenario restarts every :data:`EPISODE_S` seconds with a cold solver, so the
updates cover the transient and not only the rest state. Each update is timed with
``time.perf_counter_ns`` around :meth:`CGMRESSolver.update` (the compiled tick and its Python
wrapper); the first tick of an episode is the Newton-GMRES initial solve and is reported
apart (``init_us``). What compiling buys (the plain-NumPy reference solver, a test oracle, on
the same loop) is a test-side benchmark: ``python -m tests.support.bench_reference``.

``profile`` splits a continuation tick into its parts: F evaluations per tick (each one forward and
one backward sweep), the time of one evaluation (``sweep_us``, compiled loop), hence the time in
sweeps; the rest of the compiled tick (``gmres_us``: Arnoldi, preconditioner, least squares,
projections); and the Python wrapper around it (``wrapper_us``: :meth:`CGMRESSolver.update` minus
the bare compiled call). The parts are measured by replaying up to :data:`PROFILE_TICKS` recorded
ticks back to back (warm caches), so they add up to less than ``solve_us`` of the closed loop.

``paced`` replays :data:`PACED_TICKS` recorded ticks once per control period, the core left
idle (sleeping) in between as the live daemon leaves it: caches, TLB and branch predictors go
cold, and the same update takes several times its back-to-back time. It is the isolated figure
to hold against the live daemon.

``decide`` (:mod:`rt_controller.rig.bench_decide`) times the whole per-tick rule as the daemon
runs it, one compiled call, for rhc and ioc: closed loop, warm and paced, with its code size
and working set; it is the figure to hold the live daemon's ``law_us`` against (``hil bench
loop``).
"""

from __future__ import annotations

import gc
import os
import platform
import time
from collections.abc import Callable
from typing import Any, Protocol

import numba
import numpy as np

from hal.config import RigConfig
from rt_controller.control.model import NominalModel
from rt_controller.control.model_kernels import prepare
from rt_controller.control.rhc import dynamics
from rt_controller.control.rhc.kernel import rhc_tick, sweep_probe
from rt_controller.control.rhc.problem import pack_params
from rt_controller.control.rhc.solver import CGMRESSolver, SolveReport, pack_state
from rt_controller.control.state import ST
from rt_controller.rig.bench_decide import bench_decide
from rt_controller.sample_stats import summary_stats

PlantStep = Callable[
    [np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]
]
"""(q, dq, f, u) -> (q, dq, f) one control period later, the input u of eq. (11) held."""

EPISODE_S = 6.0
"""Length of one run of the paper scenario before it restarts."""
SWEEP_STEPS = (5, 20, 50)
PROFILE_TICKS = 400
"""Continuation ticks recorded (evenly spread over the run) and replayed for the profile."""
PACED_TICKS = 100
"""Recorded ticks replayed one per control period for ``paced`` (2 s at 50 Hz)."""


def nominal_plant_step(model: NominalModel, cfg: RigConfig) -> PlantStep:
    """Eq. (12) of the nominal model (the solver's own, :func:`~rt_controller.control.rhc.
    dynamics.rhs`) by RK4 at ``rates.physics_hz``, u held over the period."""
    h = 1.0 / cfg.rates.physics_hz
    substeps = cfg.rates.substeps
    P, _ = pack_params(model, cfg)

    def rhs(s: np.ndarray, u: np.ndarray) -> np.ndarray:
        out = np.empty(6)
        dynamics.rhs(P, s, u, out)
        return out

    def step(q: np.ndarray, dq: np.ndarray, f: np.ndarray, u: np.ndarray):
        s = pack_state(q, prepare(P, q, dq, f)[0], f)
        for _ in range(substeps):
            k1 = rhs(s, u)
            k2 = rhs(s + 0.5 * h * k1, u)
            k3 = rhs(s + 0.5 * h * k2, u)
            k4 = rhs(s + h * k3, u)
            s = s + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return s[0:2], rhs(s, u)[0:2], s[4:6]

    return step


def _stats(us: np.ndarray) -> dict[str, float]:
    return summary_stats(us)


class UpdatingSolver(Protocol):
    """What :func:`run_updates` drives: :class:`CGMRESSolver`, or the NumPy reference of the
    tests, which has its interface."""

    @property
    def last_fevals(self) -> int: ...

    def reset(self) -> None: ...

    def update(self, x: np.ndarray, t: float) -> SolveReport: ...


def run_updates(
    solver: UpdatingSolver,
    model: NominalModel,
    cfg: RigConfig,
    plant_step: PlantStep,
    updates: int,
) -> dict[str, Any]:
    """Closed loop of ``updates`` ticks; per-tick time (ns), residual, iterations, F evaluations,
    flags, and (compiled solver) ``snapshots``: (state vector before the tick, x, t) of up to
    :data:`PROFILE_TICKS` continuation ticks for :func:`_profile`."""
    s = cfg.scenario
    period = 1.0 / cfg.rates.control_hz
    episode = max(1, round(EPISODE_S * cfg.rates.control_hz))
    ns = np.zeros(updates, dtype=np.int64)
    res = np.zeros(updates)
    its = np.zeros(updates, dtype=np.int64)
    fev = np.zeros(updates, dtype=np.int64)
    init = np.zeros(updates, dtype=bool)
    bad = np.zeros(updates, dtype=bool)
    umax = np.asarray(cfg.rhc.u_max, dtype=float)
    P, _ = pack_params(model, cfg)
    x = np.zeros(6)
    q = dq = f = np.zeros(2)
    compiled = isinstance(solver, CGMRESSolver)
    every = max(1, updates // PROFILE_TICKS)
    snapshots = []
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for k in range(updates):
            if k % episode == 0:
                q = np.array(s.q0, dtype=float)
                dq = np.array(s.dq0, dtype=float)
                f = np.array(s.f0, dtype=float)
                solver.reset()
            xi, _ = prepare(P, q, dq, f)
            pack_state(q, xi, f, x)
            t = (k % episode) * period
            if compiled and k % every == 0 and not solver.needs_init:
                snapshots.append((solver.st.copy(), x.copy(), t))
            start = time.perf_counter_ns()
            rep = solver.update(x, t)
            ns[k] = time.perf_counter_ns() - start
            res[k], its[k], init[k], bad[k] = (
                rep.residual,
                rep.iterations,
                rep.initialised,
                not rep.ok,
            )
            fev[k] = solver.last_fevals
            u = rep.u if rep.ok else np.clip(-2.0 * model.R @ xi, -umax, umax)
            q, dq, f = plant_step(q, dq, f, u)
    finally:
        if gc_was_enabled:
            gc.enable()
    return {
        "ns": ns,
        "residual": res,
        "iterations": its,
        "fevals": fev,
        "init": init,
        "fallback": bad,
        "snapshots": snapshots,
    }


def _profile(solver: CGMRESSolver, run: dict[str, Any]) -> dict[str, Any]:
    """Per-part split of a continuation tick from replays of the recorded ticks (see module)."""
    snaps = run["snapshots"]
    cont = ~run["init"]
    fevals = run["fevals"][cont]
    out: dict[str, Any] = {
        "fevals_per_tick": float(np.median(fevals)) if fevals.size else 0.0,
        "fevals_mean": float(np.mean(fevals)) if fevals.size else 0.0,
        "replayed_ticks": len(snaps),
    }
    if not snaps:
        return out
    st, P, iP, work = solver.st, solver.P, solver.iP, solver.work
    wrapped = np.zeros(len(snaps))
    bare = np.zeros(len(snaps))
    sweep = np.zeros(len(snaps))
    reps = 20
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        snap, x, t = snaps[0]  # one untimed sweep: a first call's cold caches are no sweep's cost
        st[:] = snap
        st[ST.X : ST.X + 6] = x
        st[ST.T] = t
        sweep_probe(P, iP, st, work, 1)
        for i, (snap, x, t) in enumerate(snaps):
            st[:] = snap
            solver.needs_init = False
            start = time.perf_counter_ns()
            solver.update(x, t)
            wrapped[i] = time.perf_counter_ns() - start
            st[:] = snap
            st[ST.X : ST.X + 6] = x
            st[ST.T] = t
            st[ST.INIT] = 0.0
            st[ST.MODEL_XDOT] = 1.0
            start = time.perf_counter_ns()
            rhc_tick(P, iP, st, work)
            bare[i] = time.perf_counter_ns() - start
            st[:] = snap
            st[ST.X : ST.X + 6] = x
            st[ST.T] = t
            start = time.perf_counter_ns()
            sweep_probe(P, iP, st, work, reps)
            sweep[i] = (time.perf_counter_ns() - start) / reps
    finally:
        if gc_was_enabled:
            gc.enable()
        solver.reset()
    sweep_us = float(np.median(sweep)) / 1e3
    bare_us = float(np.median(bare)) / 1e3
    sweeps_us = out["fevals_mean"] * sweep_us
    out.update(
        {
            "sweep_us": sweep_us,
            "update_us": float(np.median(wrapped)) / 1e3,
            "kernel_us": bare_us,
            "sweeps_us": sweeps_us,
            "gmres_us": bare_us - sweeps_us,
            "wrapper_us": float(np.median(wrapped - bare)) / 1e3,
        }
    )
    return out


def _paced(solver: CGMRESSolver, run: dict[str, Any], period_s: float) -> dict[str, Any]:
    """Replay up to :data:`PACED_TICKS` recorded ticks, sleeping one control period before
    each (see module): the update time with the core idle in between."""
    snaps = run["snapshots"][:PACED_TICKS]
    ns = np.zeros(len(snaps), dtype=np.int64)
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for i, (snap, x, t) in enumerate(snaps):
            solver.st[:] = snap
            solver.needs_init = False
            time.sleep(period_s)
            start = time.perf_counter_ns()
            solver.update(x, t)
            ns[i] = time.perf_counter_ns() - start
    finally:
        if gc_was_enabled:
            gc.enable()
        solver.reset()
    return {"period_s": period_s, "ticks": len(snaps), "solve_us": _stats(ns / 1e3)}


def summary(cfg: RigConfig, run: dict[str, Any]) -> dict[str, Any]:
    cont = ~run["init"]
    us = run["ns"] / 1e3
    return {
        "N": cfg.rhc.steps,
        "kmax": cfg.rhc.kmax,
        "horizon": cfg.rhc.horizon,
        "updates": int(us.size),
        "solve_us": _stats(us[cont]),
        "init_us": {**_stats(us[~cont]), "count": int(np.sum(~cont))},
        "residual_median": float(np.median(run["residual"])),
        "residual_max": float(np.max(run["residual"])),
        "iterations_median": float(np.median(run["iterations"][cont])) if cont.any() else 0.0,
        "fevals_median": float(np.median(run["fevals"][cont])) if cont.any() else 0.0,
        "fallbacks": int(np.sum(run["fallback"])),
    }


def bench_one(
    cfg: RigConfig,
    updates: int = 2000,
    *,
    plant_step: PlantStep | None = None,
    paced: bool = False,
) -> dict[str, Any]:
    """The compiled solver for the configuration as given; with ``paced``, the
    update at the control rate too (``paced``, see module)."""
    model = NominalModel.from_config(cfg)
    step = plant_step if plant_step is not None else nominal_plant_step(model, cfg)
    solver = CGMRESSolver(model, cfg)
    solver.warm_up()
    run = run_updates(solver, model, cfg, step, updates)
    out = summary(cfg, run)
    out["profile"] = _profile(solver, run)
    if paced:
        out["paced"] = _paced(solver, run, 1.0 / cfg.rates.control_hz)
        out["decide"] = {
            law: bench_decide(cfg.with_overrides({"controller.law": law}), updates, step, EPISODE_S)
            for law in ("rhc", "ioc")
        }
    return out


def bench_solver(
    cfg: RigConfig,
    updates: int = 2000,
    *,
    plant_step: PlantStep | None = None,
    sweep: tuple[int, ...] = SWEEP_STEPS,
) -> dict[str, Any]:
    """JSON-ready benchmark: the configured N and kmax, then a sweep over N (same kmax, T).

    ``plant_step`` replaces the default nominal-model plant (e.g. with the emulator).
    """
    out = bench_one(cfg, updates, plant_step=plant_step, paced=True)
    out["sweep"] = [
        bench_one(
            cfg.with_overrides({"rhc.steps": n}),
            updates,
            plant_step=plant_step,
        )
        for n in sweep
    ]
    load1, load5, load15 = os.getloadavg()
    out["plant"] = "custom" if plant_step is not None else "nominal-rk4"
    out["machine"] = {
        "load": {"1min": load1, "5min": load5, "15min": load15},
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "platform": platform.platform(),
    }
    return out
