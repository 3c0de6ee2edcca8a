"""The deadline-miss report of a controller log (``hil report``), cyclictest-style.

:func:`summarize` turns a :class:`~rt_controller.logtools.reader.LoadedLog` into one plain dict (the
``--json`` output); :func:`~rt_controller.logtools.report_text.render_text` prints it with rich
and :func:`~rt_controller.logtools.report_plots.write_plots` draws the PNGs.
Percentiles are numpy's default (linear interpolation); NaN/null samples are left out of every
statistic. Durations are in µs, times in s from the first tick (plant time in lockstep mode).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np

from rt_controller.logtools.canopen_timing import log_timing
from rt_controller.logtools.reader import LoadedLog
from rt_controller.runtime import diagnostics
from rt_controller.runtime.recorder import CYCLE_TOPIC
from rt_controller.sample_stats import finite, summary_stats

#: Edges (µs) of the log-scale lateness histogram; below 0 and above the last edge get buckets.
HIST_EDGES_US: tuple[float, ...] = (
    0,
    1,
    2,
    5,
    10,
    20,
    50,
    100,
    200,
    500,
    1e3,
    2e3,
    5e3,
    1e4,
    2e4,
    5e4,
    1e5,
)
TIMING_FIELDS = ("lateness_us", "cycle_us", "read_us", "solve_us", "write_us")


def numbers(col: Any) -> np.ndarray:
    """A column as floats; in a column of mixed types (a hand-edited log: text where a number
    or flag belongs) a value that is no number is NaN, unknown."""
    a = np.asarray(col)
    if a.dtype != object:
        return a.astype(float)
    return np.array(
        [float(x) if isinstance(x, (bool, int, float, np.number)) else np.nan for x in a.ravel()],
        dtype=float,
    ).reshape(a.shape)


def stats(values: np.ndarray | None) -> dict[str, float] | None:
    """min / median / p99 / max / mean of the finite samples, or None when there are none."""
    v = finite(None if values is None else numbers(values))
    if v.size == 0:
        return None
    return summary_stats(v, ("min", "median", "p99", "max", "mean"))


def histogram(values: np.ndarray | None, edges: tuple[float, ...] = HIST_EDGES_US) -> list[dict]:
    """Counts per bucket ``[lo, hi)``; ``lo`` None = below the first edge, ``hi`` None = open."""
    if values is None:
        return []
    v = numbers(values)
    v = v[np.isfinite(v)]
    bounds = [-math.inf, *edges, math.inf]
    out = []
    for lo, hi in itertools.pairwise(bounds):
        n = int(np.count_nonzero((v >= lo) & (v < hi)))
        if n or (math.isfinite(lo) and math.isfinite(hi)):
            out.append(
                {
                    "lo_us": None if math.isinf(lo) else lo,
                    "hi_us": None if math.isinf(hi) else hi,
                    "count": n,
                }
            )
    # Trim empty buckets at both ends (keep the shape compact, like cyclictest's histogram).
    while out and out[-1]["count"] == 0:
        out.pop()
    while out and out[0]["count"] == 0:
        out.pop(0)
    return out


def flags(col: np.ndarray) -> np.ndarray:
    """A per-tick flag column as bools; a tick whose record lacks the flag (NaN) is False."""
    if col.dtype == bool:
        return col
    return np.nan_to_num(numbers(col)) != 0


def _count(col: np.ndarray | None) -> int | None:
    if col is None:
        return None
    if col.dtype == bool:
        return int(np.count_nonzero(col))
    c = numbers(col)
    return int(np.count_nonzero(np.nan_to_num(c) != 0))


def time_axis(log: LoadedLog) -> tuple[np.ndarray, str]:
    """Per-tick time in s and its label: plant time if every tick has it, else monotonic."""
    sim = log.column("sim_time_s")
    if sim is not None and sim.dtype != object and sim.size and np.all(np.isfinite(sim)):
        return sim.astype(float), "plant time (s)"
    t_ns = log.column("t_ns")
    if t_ns is None or t_ns.size == 0:
        return np.arange(log.n_cycles, dtype=float), "tick"
    t = numbers(t_ns)
    return (t - t[0]) / 1e9, "time since first tick (s)"


def period_us(log: LoadedLog) -> float | None:
    """The control period: 1/rate from the config, else the median tick spacing."""
    rate = log.rate_hz
    if rate:
        return 1e6 / rate
    t_ns = log.column("t_ns")
    if t_ns is not None and t_ns.size > 1:
        return float(np.median(np.diff(numbers(t_ns)))) / 1e3
    return None


def _vector_final(col: np.ndarray | None) -> list[float] | None:
    if col is None or col.ndim != 2:
        return None
    ok = np.all(np.isfinite(col), axis=1)
    if not np.any(ok):
        return None
    return [float(x) for x in col[np.flatnonzero(ok)[-1]]]


def _stale_state(log: LoadedLog) -> int | None:
    col = log.column("state_stale")
    if col is not None:
        return _count(col)
    age = log.column("state_age_ms")
    if age is None or log.config is None:
        return None
    limit_ms = log.config.controller.state_timeout_s * 1e3
    return int(np.count_nonzero(numbers(age) > limit_ms))


def _misses(log: LoadedLog, t: np.ndarray, max_list: int) -> tuple[int | None, list[dict]]:
    miss = log.column("deadline_miss")
    if miss is None:
        return None, []
    idx = np.flatnonzero(flags(miss))
    tick, late = log.column("tick"), log.column("lateness_us")
    cyc, skip = log.column("cycle_us"), log.column("missed_periods")
    listed = []
    for i in idx[:max_list]:
        listed.append(
            {
                "tick": int(tick[i]) if tick is not None else int(i),
                "t_s": float(t[i]),
                "lateness_us": _num(late, i),
                "cycle_us": _num(cyc, i),
                "missed_periods": _int(skip, i),
            }
        )
    return int(idx.size), listed


def _int(col: np.ndarray | None, i: int) -> int | None:
    x = _num(col, i)
    return None if x is None else int(x)


def _num(col: np.ndarray | None, i: int) -> float | None:
    if col is None:
        return None
    x = float(numbers(col[i : i + 1])[0])
    return x if math.isfinite(x) else None


def summarize(log: LoadedLog, *, max_list: int = 50) -> dict[str, Any]:
    """The report of one log as a JSON-ready dict (None where a field was not recorded); the
    run's verdict is added by :func:`rt_controller.logs.info.judged_report`."""
    n = log.n_cycles
    t, t_label = time_axis(log)
    per = period_us(log)
    rate = log.rate_hz
    misses, listed = _misses(log, t, max_list)
    skipped = log.column("missed_periods")
    cost = log.column("cost")
    J = None
    if cost is not None and rate:
        J = float(np.nansum(numbers(cost)) / rate)
    f_final = _vector_final(log.column("f"))
    info = log.run_info
    out: dict[str, Any] = {
        "log": str(log.path),
        "truncated": log.truncated,
        "notes": list(log.notes),
        "law": info.get("law") or (log.config.controller.law if log.config else None),
        "clock": info.get("clock") or (log.config.controller.clock if log.config else None),
        "rate_hz": rate,
        "period_us": per,
        "start_wall_time": info.get("start_wall_time"),
        "ticks": n,
        "duration_s": float(t[-1] - t[0]) + (per or 0.0) / 1e6 if n else 0.0,
        "time_axis": t_label,
        "deadline_misses": misses,
        "miss_pct": 100.0 * misses / n if (misses is not None and n) else None,
        "missed_periods": (  # a record without the field does not say: left out
            int(np.nansum(numbers(skipped))) if skipped is not None and n else None
        ),
        "misses": listed,
        "misses_listed": len(listed),
    }
    for key in TIMING_FIELDS:
        out[key] = stats(log.column(key))
    out["lateness_histogram"] = histogram(log.column("lateness_us"))
    out["residual"] = stats(log.column("residual"))
    out["residual_final"] = _num(log.column("residual"), n - 1) if n else None
    out["iterations"] = stats(log.column("iterations"))
    out["fallbacks"] = _count(log.column("fallback"))
    out["stale_features"] = _count(log.column("f_stale"))
    valid = log.column("f_valid")
    out["invalid_features"] = None if valid is None else int(np.count_nonzero(~valid.astype(bool)))
    out["stale_state"] = _stale_state(log)
    out["outages"] = _outages(log, t, per)
    out["tau_saturated"] = _count(log.column("tau_saturated"))
    out["f_final"] = f_final
    out["f_final_norm"] = float(np.hypot(*f_final)) if f_final else None
    out["J"] = J
    out["messages"] = dict(log.topic_counts)
    out["recorder_dropped"] = _int_or_none(log.recorder_info.get("dropped"))
    out["diagnostics"] = _final_diagnostics(log)
    out["parameter_changes"] = [change_entry(r) for r in log.parameters]
    out["events"] = [_event(r) for r in log.events]
    out["canopen"] = log_timing(log)
    if out["recorder_dropped"]:
        out["notes"].append(f"the recorder dropped {out['recorder_dropped']} records")
    if n == 0:
        out["notes"].append(_no_cycles_note(log))
    return out


def log_outages(log: LoadedLog) -> dict[str, Any] | None:
    """The camera outages of a log rebuilt from its cycle records (``hil report``'s, and the
    verdict's of a log whose final ``/diagnostics`` record does not carry them)."""
    t, _ = time_axis(log)
    return _outages(log, t, period_us(log))


def _no_cycles_note(log: LoadedLog) -> str:
    """Why the log has no ticks: no cycle messages, or none of them was readable."""
    found = log.topic_counts.get(CYCLE_TOPIC, 0)
    if not found:
        return f"no {CYCLE_TOPIC} messages in the log"
    return f"none of the {found} {CYCLE_TOPIC} message(s) in the log is a readable cycle record"


def _outages(log: LoadedLog, t: np.ndarray, per_us: float | None) -> dict[str, Any] | None:
    """Camera outages from the per-tick ``f_stale``/``f_valid`` columns, with the log's own
    thresholds (``controller.outage_*``, defaults for a log without a config); None when the
    log has neither column."""
    from hal.config import ControllerConfig
    from rt_controller.runtime.counters import find_outages

    stale, valid = log.column("f_stale"), log.column("f_valid")
    if stale is None and valid is None:
        return None
    n = log.n_cycles
    bad = np.zeros(n, dtype=bool)
    if stale is not None:
        bad |= flags(stale)
    if valid is not None:  # a record without f_valid does not say it was invalid
        v = numbers(valid) if valid.dtype != bool else valid
        bad |= (v == 0) if v.dtype != bool else ~v
    ticks = log.column("tick")
    ticks = np.arange(n) if ticks is None else np.asarray(ticks)
    ctl = log.config.controller if log.config else ControllerConfig()
    warn = int(getattr(ctl, "outage_warn_periods", ControllerConfig.outage_warn_periods))
    share = float(getattr(ctl, "outage_max_share", ControllerConfig.outage_max_share))
    return find_outages(ticks, t, bad, warn, share, (per_us or 0.0) / 1e6)


def change_entry(rec: dict[str, Any]) -> dict[str, Any]:
    """One ``/controller/parameters`` record as the report lists it (a change entry that
    lacks its key, old or new value shows ``?`` there; one that is no object is left out)."""
    changes = rec.get("changes")
    items = ", ".join(
        f"{c.get('key', '?')} {c.get('old', '?')} -> {c.get('new', '?')}"
        for c in (changes if isinstance(changes, list) else [])
        if isinstance(c, dict)
    )
    return {
        "tick": rec.get("tick"),
        "accepted": bool(rec.get("accepted")),
        "unchanged": bool(rec.get("unchanged")),  # accepted, the values already in force
        "param_set": rec.get("param_set"),
        "source": rec.get("source"),
        "changes": items,
        "reason": rec.get("reason"),
    }


def _event(rec: dict[str, Any]) -> dict[str, Any]:
    """One ``/controller/events`` record (a mark, arm, disarm) as the report lists it."""
    keys = ("tick", "action", "accepted", "note", "source", "reason")
    return {k: rec.get(k) for k in keys}


def _final_diagnostics(log: LoadedLog) -> dict[str, Any] | None:
    """The counters of the run's last ``/diagnostics`` record: rejections by reason (non-zero
    ones) per receiver, the DSP's state, the controller's, the recorder's and the parameter
    service's counters (``parameters``: {} where it did not run)."""
    if not log.diagnostics:
        return None
    last = log.diagnostics[-1]
    out: dict[str, Any] = {"final": bool(last.get("final")), "level": last.get("level")}
    for name in ("can_rx", "features"):
        values = diagnostics.values_of(last, name)
        out[f"{name}_rejected"] = diagnostics.rejected(values)
        out[f"{name}_by_reason"] = {
            k: v
            for k, v in values.items()
            if k.startswith(
                ("bad_", "stale_", "future_", "foreign_", "repeated_", "counter_", "wrong_")
            )
            or k.startswith("unknown_")
            or k in ("decode_error",)
            if v
        }
    for name in ("dsp", "controller", "recorder", "parameters"):
        out[name] = diagnostics.values_of(last, name)
    return out


def _int_or_none(text: str | None) -> int | None:
    try:
        return None if text is None else int(text)
    except ValueError:
        return None
