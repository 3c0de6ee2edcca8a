"""The text of ``hil report``: one report dict
(:func:`~rt_controller.logtools.deadline_report.summarize`) printed with rich: timing, misses,
the lateness histogram, online changes, outages."""

from __future__ import annotations

import math
from typing import Any

from rich.markup import escape

from rt_controller.logtools.deadline_report import TIMING_FIELDS
from rt_controller.runtime.recorder import CAN_RX_TOPIC, CAN_TX_TOPIC, VISION_TOPIC

PARAMETER_COUNTS = ("accepted", "refused", "unauthenticated", "failed", "unchanged", "oversized")
"""The counters of the ``/diagnostics`` record's ``parameters`` component the report shows
(:data:`RARE_COUNTS` only where the record has them)."""
RARE_COUNTS = ("failed", "unchanged", "oversized")
"""Counters the record holds only when not 0: a request the controller failed on, a set to the
values in force, a mark's note beyond its limit."""


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
        f"[bold]{escape(report['log'])}[/bold]  law {escape(report['law'] or '?')}, "
        f"{_g(report['rate_hz'])} Hz, clock {escape(report['clock'] or '?')}, "
        f"{report['ticks']} ticks over {_fmt(report['duration_s'], 3)} s"
    )
    con.print(head)
    _verdict(con, report)
    for note in report["notes"]:
        con.print(f"[yellow]note:[/yellow] {escape(note)}")

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
        params = diag.get("parameters") or {}
        if params:
            names = [k for k in PARAMETER_COUNTS if k not in RARE_COUNTS or k in params]
            rows.append((f"parameter requests {' / '.join(names)}",
                         " / ".join(_fmt(params.get(k)) for k in names)))  # fmt: skip
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
            for row in rows:  # notes, sources, changes as written, not rich markup
                t.add_row(*("" if cell is None else escape(str(cell)) for cell in row))
            con.print(t)

    def verdict(item: dict[str, Any], ok: str) -> str:
        if item.get("unchanged"):
            return "unchanged"
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

    _canopen(con, report.get("canopen"), lockstep=report.get("clock") == "lockstep")

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


def _verdict(con: Any, report: dict[str, Any]) -> None:
    """The run's problems (``run not clean: ...``, as ``hil controller`` says it; ``problems:
    none``) and its warnings, one line each, as ``hil info`` judges the log."""
    if "problems" not in report:
        return
    problems = report["problems"]
    if problems:
        con.print(f"[bold red]run not clean:[/bold red] {escape('; '.join(problems))}")
    else:
        con.print("problems: none")
    for warning in report.get("warnings") or []:
        con.print(f"[yellow]warning:[/yellow] {escape(warning)}")


def _canopen(con: Any, co: dict[str, Any] | None, *, lockstep: bool = False) -> None:
    """The cia402 profile's CANopen section: SYNC jitter, latencies, counts, the EMCYs."""
    from rich.table import Table

    if co is None:
        return
    t = Table(title="CANopen (cia402): SYNC and PDO timing (µs)", title_justify="left")
    for col in ("", "median", "p99", "max"):
        t.add_column(col, justify="right" if col else "left")
    rows = (
        ("SYNC interval", co["sync"]["interval_us"]),
        # a lockstep run's SYNCs follow the world's steps: no error against the period
        (
            "SYNC period error (lockstep: none)" if lockstep else "SYNC period error",
            co["sync"]["period_error_us"],
        ),
        ("SYNC to TPDOs", co["sync_to_tpdo_us"]),
        ("PDO round trip", co["pdo_round_trip_us"]),
        ("torque to effect", co["torque_to_effect_us"]),
    )
    for label, s in rows:
        t.add_row(label, *(_fmt(s[k]) for k in ("median", "p99", "max")))
    con.print(t)
    con.print(
        f"SYNCs {co['sync']['syncs']}, answered {co['answered']}, incomplete "
        f"{co['incomplete']}; torque changes {co['changes']} (superseded {co['superseded']}, "
        f"never seen {co['never']}); frames {co['frames']}, undecodable {co['undecodable']}"
    )
    for node, states in co["drive_states"].items():
        con.print(f"node {node} power states: {' -> '.join(states)}")
    emcys = co["emcys"]
    if not emcys:
        con.print("EMCY: none")
        return
    et = Table(title="EMCY", title_justify="left")
    for col in ("t (s)", "node", "code", "meaning"):
        et.add_column(col)
    for e in emcys:
        meaning = "error reset" if e["error_reset"] else e["text"]
        et.add_row(_fmt(e["t_s"], 3), str(e["node"]), e["code"], meaning)
    con.print(et)


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
