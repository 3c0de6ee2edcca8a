"""The deadline-miss report of a controller log (``hil report``), cyclictest-style.

:func:`summarize` turns a :class:`~rt_controller.logtools.reader.LoadedLog` into one plain dict (the
``--json`` output), :func:`render_text` prints it with rich, :func:`write_plots` draws the PNGs.
Percentiles are numpy's default (linear interpolation); NaN/null samples are left out of every
statistic. Durations are in µs, times in s from the first tick (plant time in lockstep mode).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rt_controller.logtools.contact_sheet import write_contact_sheet
from rt_controller.logtools.reader import LoadedLog
from rt_controller.runtime import diagnostics
from rt_controller.runtime.recorder import CAN_RX_TOPIC, CAN_TX_TOPIC, CYCLE_TOPIC, VISION_TOPIC
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


def stats(values: np.ndarray | None) -> dict[str, float] | None:
    """min / median / p99 / max / mean of the finite samples, or None when there are none."""
    v = finite(values)
    if v.size == 0:
        return None
    return summary_stats(v, ("min", "median", "p99", "max", "mean"))


def histogram(values: np.ndarray | None, edges: tuple[float, ...] = HIST_EDGES_US) -> list[dict]:
    """Counts per bucket ``[lo, hi)``; ``lo`` None = below the first edge, ``hi`` None = open."""
    if values is None:
        return []
    v = np.asarray(values, dtype=float)
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


def _count(col: np.ndarray | None) -> int | None:
    if col is None:
        return None
    if col.dtype == bool:
        return int(np.count_nonzero(col))
    c = np.asarray(col, dtype=float)
    return int(np.count_nonzero(np.nan_to_num(c) != 0))


def time_axis(log: LoadedLog) -> tuple[np.ndarray, str]:
    """Per-tick time in s and its label: plant time if every tick has it, else monotonic."""
    sim = log.column("sim_time_s")
    if sim is not None and sim.dtype != object and sim.size and np.all(np.isfinite(sim)):
        return sim.astype(float), "plant time (s)"
    t_ns = log.column("t_ns")
    if t_ns is None or t_ns.size == 0:
        return np.arange(log.n_cycles, dtype=float), "tick"
    t = np.asarray(t_ns, dtype=float)
    return (t - t[0]) / 1e9, "time since first tick (s)"


def period_us(log: LoadedLog) -> float | None:
    """The control period: 1/rate from the config, else the median tick spacing."""
    rate = log.rate_hz
    if rate:
        return 1e6 / rate
    t_ns = log.column("t_ns")
    if t_ns is not None and t_ns.size > 1:
        return float(np.median(np.diff(np.asarray(t_ns, dtype=float)))) / 1e3
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
    return int(np.count_nonzero(np.asarray(age, dtype=float) > limit_ms))


def _misses(log: LoadedLog, t: np.ndarray, max_list: int) -> tuple[int | None, list[dict]]:
    miss = log.column("deadline_miss")
    if miss is None:
        return None, []
    idx = np.flatnonzero(np.asarray(miss, dtype=bool))
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
                "missed_periods": int(skip[i]) if skip is not None else None,
            }
        )
    return int(idx.size), listed


def _num(col: np.ndarray | None, i: int) -> float | None:
    if col is None:
        return None
    x = float(col[i])
    return x if math.isfinite(x) else None


def summarize(log: LoadedLog, *, max_list: int = 50) -> dict[str, Any]:
    """The report of one log as a JSON-ready dict (None where a field was not recorded)."""
    n = log.n_cycles
    t, t_label = time_axis(log)
    per = period_us(log)
    rate = log.rate_hz
    misses, listed = _misses(log, t, max_list)
    skipped = log.column("missed_periods")
    cost = log.column("cost")
    J = None
    if cost is not None and rate:
        J = float(np.nansum(np.asarray(cost, dtype=float)) / rate)
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
        "missed_periods": int(np.sum(skipped)) if skipped is not None and n else None,
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
    out["parameter_changes"] = [_change(r) for r in log.parameters]
    out["events"] = [_event(r) for r in log.events]
    if out["recorder_dropped"]:
        out["notes"].append(f"the recorder dropped {out['recorder_dropped']} records")
    if n == 0:
        out["notes"].append(f"no {CYCLE_TOPIC} messages in the log")
    return out


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
        bad |= np.asarray(stale, dtype=bool)
    if valid is not None:
        bad |= ~np.asarray(valid, dtype=bool)
    ticks = log.column("tick")
    ticks = np.arange(n) if ticks is None else np.asarray(ticks)
    ctl = log.config.controller if log.config else ControllerConfig()
    warn = int(getattr(ctl, "outage_warn_periods", ControllerConfig.outage_warn_periods))
    share = float(getattr(ctl, "outage_max_share", ControllerConfig.outage_max_share))
    return find_outages(ticks, t, bad, warn, share, (per_us or 0.0) / 1e6)


def _change(rec: dict[str, Any]) -> dict[str, Any]:
    """One ``/controller/parameters`` record as the report lists it."""
    items = ", ".join(f"{c['key']} {c['old']} -> {c['new']}" for c in rec.get("changes", []))
    return {
        "tick": rec.get("tick"),
        "accepted": bool(rec.get("accepted")),
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
    ones) per receiver, the DSP's state, the controller's and the recorder's counters."""
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
    for name in ("dsp", "controller", "recorder"):
        out[name] = diagnostics.values_of(last, name)
    return out


def _int_or_none(text: str | None) -> int | None:
    try:
        return None if text is None else int(text)
    except ValueError:
        return None


# ---------------------------------------------------------------------------- text output


def _fmt(x: Any, digits: int = 1) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.{digits}f}" if abs(x) < 1e6 else f"{x:.4g}"
    return str(x)


def _g(x: float | None) -> str:
    return "-" if x is None else f"{x:.6g}"


def _bucket_label(b: dict) -> str:
    lo, hi = b["lo_us"], b["hi_us"]
    if lo is None:
        return f"< {hi:g}"
    if hi is None:
        return f">= {lo:g}"
    return f"{lo:g} - {hi:g}"


def render_text(report: dict[str, Any], console: Any = None) -> None:
    """Print one report with rich (tables for timing, misses and the lateness histogram)."""
    from rich.console import Console
    from rich.table import Table

    con = console or Console()
    head = (
        f"[bold]{report['log']}[/bold]  law {report['law'] or '?'}, "
        f"{_g(report['rate_hz'])} Hz, clock {report['clock'] or '?'}, "
        f"{report['ticks']} ticks over {_fmt(report['duration_s'], 3)} s"
    )
    con.print(head)
    for note in report["notes"]:
        con.print(f"[yellow]note:[/yellow] {note}")

    timing = Table(title="Timing (µs)", title_justify="left")
    for col in ("", "min", "median", "p99", "max"):
        timing.add_column(col, justify="right" if col else "left")
    for key in TIMING_FIELDS:
        s = report.get(key)
        cells = ["-"] * 4 if s is None else [_fmt(s[k]) for k in ("min", "median", "p99", "max")]
        timing.add_row(key.removesuffix("_us"), *cells)
    con.print(timing)

    summary = Table(title="Run", title_justify="left", show_header=False)
    summary.add_column("what")
    summary.add_column("value", justify="right")
    misses = report["deadline_misses"]
    pct = report["miss_pct"]
    rows = [
        ("deadline misses", "-" if misses is None else f"{misses} ({pct:.3f} %)"),
        ("missed periods", _fmt(report["missed_periods"])),
        ("period (deadline)", f"{_fmt(report['period_us'])} µs"),
        ("fallbacks", _fmt(report["fallbacks"])),
        ("stale features", _fmt(report["stale_features"])),
        ("invalid features", _fmt(report["invalid_features"])),
        ("stale joint state", _fmt(report["stale_state"])),
        ("camera outages (longest, ticks)", _outage_counts(report.get("outages"))),
        ("tau saturated", _fmt(report["tau_saturated"])),
        ("residual median / p99 / max", _triple(report["residual"])),
        ("residual final", _g(report["residual_final"])),
        ("iterations median / max", _iters(report["iterations"])),
        ("final f (px)", _vec(report["f_final"])),
        ("final |f| (px)", _fmt(report["f_final_norm"], 3)),
        ("J", _fmt(report["J"], 6)),
        ("raw messages CAN rx / tx / vision", _raw_counts(report["messages"])),
        ("records dropped by the recorder", _fmt(report["recorder_dropped"])),
    ]
    diag = report.get("diagnostics")
    if diag is not None:
        for name, label in (("can_rx", "CAN frames rejected"), ("features", "features rejected")):
            reasons = ", ".join(f"{k} {v}" for k, v in diag[f"{name}_by_reason"].items())
            rows.append(
                (label, f"{diag[f'{name}_rejected']}" + (f" ({reasons})" if reasons else ""))
            )
        rows.append(("DSP watchdog trips", _fmt(diag["controller"].get("watchdog_trips"))))
        dsp_rejected = diag["dsp"].get("rejected_frames")
        if dsp_rejected is not None:
            rows.append(("frames the DSP rejected (saturates at 255)", _fmt(dsp_rejected)))
    else:
        rows.append(("diagnostics", "none in this log"))
    for k, v in rows:
        summary.add_row(k, v)
    con.print(summary)

    if report["misses"]:
        shown = report["misses_listed"]
        title = "Deadline misses" + (f" (first {shown} of {misses})" if shown < misses else "")
        mt = Table(title=title, title_justify="left")
        for col in ("tick", "t (s)", "lateness µs", "cycle µs", "skipped"):
            mt.add_column(col, justify="right")
        for m in report["misses"]:
            mt.add_row(
                str(m["tick"]),
                f"{m['t_s']:.3f}",
                _fmt(m["lateness_us"]),
                _fmt(m["cycle_us"]),
                _fmt(m["missed_periods"]),
            )
        con.print(mt)

    def listing(title: str, columns: tuple[str, ...], rows: list[tuple[str, ...]]) -> None:
        if rows:
            t = Table(title=title, title_justify="left")
            for col in columns:
                t.add_column(col)
            for row in rows:
                t.add_row(*row)
            con.print(t)

    def verdict(item: dict[str, Any], ok: str) -> str:
        return ok if item["accepted"] else f"refused: {item['reason']}"

    outages = report.get("outages") or {}
    listing(
        f"Camera outages (over {outages.get('warn_periods')} ticks on stale/invalid features)",
        ("from tick", "t (s)", "ticks", "s"),
        [
            (str(o["start_tick"]), f"{o['start_s']:.3f}", str(o["ticks"]), f"{o['s']:.2f}")
            for o in outages.get("listed") or []
        ],
    )
    listing(
        "Parameter changes",
        ("tick", "set", "", "changes", "source"),
        [
            (str(c["tick"]), str(c["param_set"]), verdict(c, "accepted"), c["changes"], c["source"])
            for c in report.get("parameter_changes") or []
        ],
    )
    listing(
        "Operator events (marks, arm, disarm)",
        ("tick", "action", "", "note", "source"),
        [
            (str(e["tick"]), e["action"], verdict(e, "done"), e["note"] or "", e["source"])
            for e in report.get("events") or []
        ],
    )

    hist = report["lateness_histogram"]
    if hist:
        ht = Table(title="Wake-up lateness histogram (µs)", title_justify="left")
        ht.add_column("bucket", justify="right")
        ht.add_column("count", justify="right")
        ht.add_column("")
        top = max(b["count"] for b in hist) or 1
        for b in hist:
            ht.add_row(_bucket_label(b), str(b["count"]), _bar(b["count"], top))
        con.print(ht)


def _outage_counts(outages: dict[str, Any] | None) -> str:
    """Camera outages and the longest stretch, e.g. ``2 (longest 98)``."""
    if outages is None:
        return "-"
    return f"{outages['count']} (longest {outages['longest_ticks']})"


def _bar(count: int, top: int, width: int = 40) -> str:
    """A log-scaled bar (counts span decades, as in cyclictest's histograms)."""
    if count <= 0:
        return ""
    return "█" * max(1, round(width * math.log1p(count) / math.log1p(top)))


def _raw_counts(messages: dict[str, int]) -> str:
    return " / ".join(str(messages.get(t, 0)) for t in (CAN_RX_TOPIC, CAN_TX_TOPIC, VISION_TOPIC))


def _triple(s: dict | None) -> str:
    return "-" if s is None else " / ".join(f"{s[k]:.3g}" for k in ("median", "p99", "max"))


def _iters(s: dict | None) -> str:
    return "-" if s is None else f"{s['median']:g} / {s['max']:g}"


def _vec(v: list[float] | None) -> str:
    return "-" if v is None else "(" + ", ".join(f"{x:.3f}" for x in v) + ")"


# ---------------------------------------------------------------------------- figures


@dataclass(frozen=True)
class ChangeLine:
    """A vertical line of the report's time plots: an online change or an operator event."""

    t: float
    kind: str
    """``accepted``, ``refused`` (parameter change sets) or ``event`` (a mark, arm, disarm)."""
    label: str


LINE_STYLES = {
    "accepted": {"color": "tab:green", "ls": "-", "lw": 1.2},
    "refused": {"color": "tab:red", "ls": ":", "lw": 1.2},
    "event": {"color": "tab:gray", "ls": "-.", "lw": 1.0},
}


def change_lines(log: LoadedLog) -> list[ChangeLine]:
    """Where the log's parameter changes and operator events fall on :func:`time_axis`, in
    log order (changes, then events); a record whose tick has no cycle is left out."""
    tick = log.column("tick")
    if tick is None or log.n_cycles == 0:
        return []
    t, _ = time_axis(log)
    at = {int(k): float(t[i]) for i, k in enumerate(np.asarray(tick))}
    out = []
    for rec in log.parameters:
        if int(rec.get("tick", -1)) in at:
            kind = "accepted" if rec.get("accepted") else "refused"
            out.append(ChangeLine(at[int(rec["tick"])], kind, _change(rec)["changes"]))
    for rec in log.events:
        if int(rec.get("tick", -1)) in at:
            label = rec.get("action", "") + (f": {rec['note']}" if rec.get("note") else "")
            out.append(ChangeLine(at[int(rec["tick"])], "event", label))
    return out


def _draw_lines(ax: Any, lines: list[ChangeLine]) -> None:
    """The change lines on ``ax``, one legend entry per kind."""
    named: set[str] = set()
    for ln in lines:
        name = "operator event" if ln.kind == "event" else f"parameters {ln.kind}"
        label = None if ln.kind in named else name
        named.add(ln.kind)
        ax.axvline(ln.t, label=label, **LINE_STYLES[ln.kind])


def write_plots(log: LoadedLog, outdir: str | Path, prefix: str | None = None) -> list[Path]:
    """Write the report's PNG figures into ``outdir`` (created); returns the files written.

    Figures: lateness histogram, cycle time with the deadline, solve time (and residual),
    f(t), xi(t), u(t), tau(t), and on images a contact sheet of the camera's frames around the
    target jump (:mod:`~rt_controller.logtools.contact_sheet`). Uses matplotlib's object API
    (Agg), never pyplot. The time plots
    mark the online parameter changes (:func:`change_lines`: green accepted, red dotted
    refused, grey dash-dot operator events).
    """
    from matplotlib.figure import Figure

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    stem = prefix if prefix is not None else log.path.stem
    if log.n_cycles == 0:
        return []
    t, t_label = time_axis(log)
    lines = change_lines(log)
    written: list[Path] = []

    def save(fig: Figure, name: str) -> None:
        path = out / f"{stem}_{name}.png"
        fig.savefig(path, dpi=110)
        written.append(path)

    late = log.column("lateness_us")
    if late is not None:
        fig = Figure(figsize=(8, 4), layout="constrained")
        ax = fig.add_subplot()
        v = np.asarray(late, dtype=float)
        v = v[np.isfinite(v)]
        lo = max(min(float(v.min()) if v.size else 1.0, 1.0), 0.1)
        hi = max(float(v.max()) if v.size else 10.0, lo * 10)
        bins = np.logspace(np.log10(lo), np.log10(hi * 1.01), 60)
        ax.hist(np.clip(v, lo, None), bins=bins, color="tab:blue")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"wake-up lateness (µs; values below {lo:.2g} shown at {lo:.2g})")
        ax.set_ylabel("ticks")
        ax.set_title(f"Wake-up lateness, {log.path.name}")
        save(fig, "lateness_hist")

    cyc = log.column("cycle_us")
    if cyc is not None:
        fig = Figure(figsize=(9, 4), layout="constrained")
        ax = fig.add_subplot()
        ax.plot(t, cyc, lw=0.8, label="cycle time")
        per = period_us(log)
        if per:
            ax.axhline(per, color="tab:red", ls="--", label=f"deadline (period {per:g} µs)")
        miss = log.column("deadline_miss")
        if miss is not None and np.any(miss):
            m = np.asarray(miss, dtype=bool)
            ax.plot(t[m], np.asarray(cyc, dtype=float)[m], "rx", label="deadline miss")
        c = np.asarray(cyc, dtype=float)
        c = c[np.isfinite(c) & (c > 0)]
        if c.size and max(float(c.max()), per or 0.0) > 50 * float(c.min()):
            ax.set_yscale("log")  # µs-scale cycles under a ms-scale deadline
        _draw_lines(ax, lines)
        ax.set_xlabel(t_label)
        ax.set_ylabel("µs")
        ax.set_title("Cycle time (wake-up to end of tick)")
        ax.legend(loc="best")
        save(fig, "cycle_time")

    solve = log.column("solve_us")
    if solve is not None:
        res = log.column("residual")
        fig = Figure(figsize=(9, 5), layout="constrained")
        ax = fig.add_subplot(2, 1, 1)
        ax.plot(t, solve, lw=0.8)
        s_stats = stats(solve)
        if s_stats is not None:
            ax.axhline(s_stats["p99"], color="tab:red", ls="--", lw=0.8, label="p99")
            ax.legend(loc="best")
        ax.set_ylabel("solve time (µs)")
        ax.set_title("Solver")
        ax2 = fig.add_subplot(2, 1, 2, sharex=ax)
        if res is not None:
            r = np.asarray(res, dtype=float)
            ax2.plot(t, r, lw=0.8, color="tab:orange")
            if np.any(r > 0):
                ax2.set_yscale("log")
        _draw_lines(ax2, lines)
        ax2.set_ylabel("residual")
        ax2.set_xlabel(t_label)
        save(fig, "solve_time")

    units = {"f": "px", "xi": "", "u": "N·m", "tau": "N·m"}
    for name, unit in units.items():
        col = log.column(name)
        if col is None or col.ndim != 2:
            continue
        fig = Figure(figsize=(9, 4), layout="constrained")
        ax = fig.add_subplot()
        for j in range(col.shape[1]):
            ax.plot(t, col[:, j], lw=1.0, label=f"{name}{j + 1}")
        _draw_lines(ax, lines)
        ax.set_xlabel(t_label)
        ax.set_ylabel(f"{name} ({unit})" if unit else name)
        ax.set_title(f"{name}(t)")
        ax.legend(loc="upper right")
        ax.grid(alpha=0.3)
        save(fig, name)
    sheet = out / f"{stem}_camera_jump.png"
    if write_contact_sheet(log, sheet):  # a log with the camera's frames (camera.model = image)
        written.append(sheet)
    return written
