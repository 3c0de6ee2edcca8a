"""The ``/controller/cycle`` record (one per tick, fields of ``cycle_schema.json``), built here
and only here: by the daemon's tick, by ``hil replay --out``, by ``hil simulate`` (its decision
fields) and by the tests that synthesise daemon logs.

Pure: no I/O, so the control layer (``simulate``) may use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rt_controller.control.controller import Controller, Decision

TIMING_FIELDS = (
    "lateness_us",
    "read_us",
    "solve_us",
    "law_us",
    "write_us",
    "cycle_us",
    "e2e_us",
)
"""Loop-timing fields of a cycle record (zero in a replayed log)."""


def vec2(a: Any) -> list[float]:
    """A 2-vector as the JSON list the record stores."""
    return [float(a[0]), float(a[1])]


@dataclass(frozen=True)
class Timing:
    """Where one tick's time went (µs); all zero for offline producers."""

    lateness_us: float = 0.0
    read_us: float = 0.0
    solve_us: float = 0.0
    law_us: float = 0.0
    """Of ``solve_us``, the law's own solve: the C/GMRES update for RHC (what ``hil bench
    solver`` times alone); 0 for the closed-form laws and ticks where no law ran."""
    write_us: float = 0.0
    cycle_us: float = 0.0
    e2e_us: float = 0.0
    deadline_miss: bool = False
    missed_periods: int = 0


def decision_fields(ctl: Controller, d: Decision) -> dict[str, Any]:
    """The output fields of one tick (the state acted on, u, xi, tau, law, solver report, cost,
    V) from the per-tick rule's :class:`Decision`; zeros / NaN when the law did not run."""
    cmd = d.command
    if cmd is None:
        law, (cost, V) = None, (math.nan, math.nan)
    else:
        law, (cost, V) = cmd.law, ctl.costs(cmd)
    return {
        "q_pred": vec2(d.state[0]) if d.state is not None else [math.nan, math.nan],
        "dq_pred": vec2(d.state[1]) if d.state is not None else [math.nan, math.nan],
        "f_pred": vec2(d.features) if d.features is not None else [math.nan, math.nan],
        "xi": [0.0, 0.0] if cmd is None else vec2(cmd.measurement.xi),
        "u": [0.0, 0.0] if law is None else vec2(law.u),
        "tau": vec2(d.tau),
        "tau_saturated": False if cmd is None else bool(cmd.saturated),
        "law": d.mode if cmd is None else ctl.law.name,
        "residual": 0.0 if law is None else float(law.residual),
        "iterations": 0 if law is None else int(law.iterations),
        "fallback": False if law is None else bool(law.fallback),
        "cost": float(cost),
        "V": float(V),
    }


def cycle_record(
    *,
    tick: int,
    t_ns: int,
    sim_time_s: float,
    timing: Timing,
    q: Any,
    dq: Any,
    f: Any,
    f_age_ms: float,
    state_age_ms: float,
    f_valid: bool,
    f_stale: bool,
    state_stale: bool,
    decision: dict[str, Any],
    predict_ms: float = 0.0,
    f_predict_ms: float = 0.0,
    param_set: int = 0,
) -> dict[str, Any]:
    """One cycle record, fields in the order of ``cycle_schema.json``; ``decision`` comes from
    :func:`decision_fields`; ``predict_ms`` and ``f_predict_ms`` are the ages of the state and
    of the features the tick compensated; ``param_set`` the online parameter set in force
    (:mod:`rt_controller.calibration.parameters`)."""
    return {
        "tick": tick,
        "t_ns": t_ns,
        "sim_time_s": sim_time_s,
        "lateness_us": timing.lateness_us,
        "read_us": timing.read_us,
        "solve_us": timing.solve_us,
        "law_us": timing.law_us,
        "write_us": timing.write_us,
        "cycle_us": timing.cycle_us,
        "e2e_us": timing.e2e_us,
        "deadline_miss": timing.deadline_miss,
        "missed_periods": timing.missed_periods,
        "q": vec2(q),
        "dq": vec2(dq),
        "f": vec2(f),
        "f_age_ms": f_age_ms,
        "state_age_ms": state_age_ms,
        "predict_ms": predict_ms,
        "f_predict_ms": f_predict_ms,
        "f_valid": f_valid,
        "f_stale": f_stale,
        "state_stale": state_stale,
        **decision,
        "param_set": param_set,
    }
