"""The ``/controller/cycle`` record (one per tick, fields of ``cycle_schema.json``), built here
and only here: by the daemon's tick, by ``hil replay --out``, by ``hil simulate`` (its decision
fields) and by the tests that synthesise daemon logs.

Pure: no I/O, so the control layer (``simulate``) may use it.
"""

from __future__ import annotations

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
    return d.record_fields(ctl.law.name)


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
