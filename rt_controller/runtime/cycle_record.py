"""The ``/controller/cycle`` record (one per tick, fields of ``cycle_schema.json``), built here
and only here: by the daemon's tick, by ``hil replay --out`` and by the tests that synthesise
daemon logs.

Pure: no I/O. The decision part of the record is ``Controller.record_fields``, from the
rule's declared outputs (:data:`rt_controller.control.state.OUTPUTS`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rt_controller.control.state import OUTPUTS

if TYPE_CHECKING:
    from rt_controller.control.controller import Controller, Decision


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


TIMING_FIELDS = tuple(f.name for f in fields(Timing) if f.name.endswith("_us"))
"""Loop-timing fields of a cycle record (zero in a replayed log)."""


SCHEMA_FILE = Path(__file__).with_name("cycle_schema.json")
"""The JSON Schema of the record; its decision part is generated (:func:`decision_schema`)."""


def cycle_schema() -> dict[str, Any]:
    """The JSON Schema of ``/controller/cycle`` (:data:`SCHEMA_FILE`)."""
    return json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))


def _property(record: str, doc: str) -> dict[str, Any]:
    if record == "vector":
        kind = {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2}
    else:
        kind = {"type": "string" if record == "law" else record}
    return {**kind, "description": doc}


def decision_schema() -> dict[str, dict[str, Any]]:
    """The decision part of the record's JSON Schema properties, in order, from the one
    declaration of the rule's outputs (:data:`rt_controller.control.state.OUTPUTS`)."""
    return {
        "law" if f.record == "law" else f.name: _property(f.record, f.doc)
        for f in OUTPUTS
        if f.record
    }


def schema_with_decision(schema: dict[str, Any]) -> dict[str, Any]:
    """``schema`` with its decision properties replaced by :func:`decision_schema` (in place,
    after ``state_stale``, before ``param_set``)."""
    decision = decision_schema()
    props: dict[str, Any] = {}
    for key, value in schema["properties"].items():
        if key == "param_set":
            props.update(decision)
        if key not in decision:
            props[key] = value
    return {**schema, "properties": props}


def write_schema(path: Path = SCHEMA_FILE) -> bool:
    """Regenerate the decision part of ``cycle_schema.json``; whether the file changed.
    (``python -m rt_controller.runtime.cycle_record`` after changing the rule's outputs.)"""
    old = path.read_text(encoding="utf-8")
    new = json.dumps(schema_with_decision(json.loads(old)), indent=2, ensure_ascii=False) + "\n"
    if new != old:
        path.write_text(new, encoding="utf-8")
    return new != old


def decision_fields(ctl: Controller, d: Decision) -> dict[str, Any]:
    """The output fields of one tick (the state acted on, u, xi, tau, law, solver report, cost,
    V) from the per-tick rule's :class:`Decision`; zeros / NaN when the law did not run."""
    return d.record_fields(ctl.law)


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
    drives: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One cycle record, fields in the order of ``cycle_schema.json``; ``decision`` comes from
    :func:`decision_fields`; ``predict_ms`` and ``f_predict_ms`` are the ages of the state and
    of the features the tick compensated; ``param_set`` the online parameter set in force
    (:mod:`rt_controller.calibration.parameters`); ``drives``: the hardware profile's per-joint
    drive fields (``drive_*``, the cia402 profile's), after the rest."""
    return {
        "tick": tick,
        "t_ns": t_ns,
        "sim_time_s": sim_time_s,
        **vars(timing),  # its fields, in their order
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
        **(drives or {}),
    }


if __name__ == "__main__":
    print(f"{SCHEMA_FILE}: {'rewritten' if write_schema() else 'up to date'}")
