"""The figures of ``hil report`` (PNG, matplotlib's object API): lateness, cycle and solve
time, f, xi, u, tau over time with the online changes marked, and the camera's contact sheet."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hal.whole_file import written_whole
from rt_controller.logtools.contact_sheet import write_contact_sheet
from rt_controller.logtools.deadline_report import (
    change_entry,
    flags,
    numbers,
    period_us,
    stats,
    time_axis,
)
from rt_controller.logtools.reader import LoadedLog


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
        if (k := _tick(rec)) in at:
            kind = "accepted" if rec.get("accepted") else "refused"
            out.append(ChangeLine(at[k], kind, change_entry(rec)["changes"]))
    for rec in log.events:
        if (k := _tick(rec)) in at:
            label = str(rec.get("action") or "") + (f": {rec['note']}" if rec.get("note") else "")
            out.append(ChangeLine(at[k], "event", label))
    return out


def _tick(rec: dict[str, Any]) -> int | None:
    """A record's tick, None when it has no integer one (a hand-made or damaged record)."""
    tick = rec.get("tick")
    return tick if isinstance(tick, int) and not isinstance(tick, bool) else None


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
    # a line of one point draws nothing: a one-tick log's values get a marker
    dot: dict[str, Any] = {"marker": "o", "ms": 4} if len(t) < 2 else {}

    def save(fig: Figure, name: str) -> None:
        path = out / f"{stem}_{name}.png"
        with written_whole(path) as tmp:  # a full disk: no half PNG, the last one stays
            fig.savefig(tmp, dpi=110, format="png")
        written.append(path)

    late = log.column("lateness_us")
    if late is not None:
        fig = Figure(figsize=(8, 4), layout="constrained")
        ax = fig.add_subplot()
        v = numbers(late)
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
        cyc = numbers(cyc)  # text in a hand-edited log: a gap
        fig = Figure(figsize=(9, 4), layout="constrained")
        ax = fig.add_subplot()
        ax.plot(t, cyc, lw=0.8, label="cycle time", **dot)
        per = period_us(log)
        if per:
            ax.axhline(per, color="tab:red", ls="--", label=f"deadline (period {per:g} µs)")
        miss = log.column("deadline_miss")
        if miss is not None and np.any(m := flags(miss)):
            ax.plot(t[m], cyc[m], "rx", label="deadline miss")
        c = cyc
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
        solve = numbers(solve)
        res = log.column("residual")
        fig = Figure(figsize=(9, 5), layout="constrained")
        ax = fig.add_subplot(2, 1, 1)
        ax.plot(t, solve, lw=0.8, **dot)
        s_stats = stats(solve)
        if s_stats is not None:
            ax.axhline(s_stats["p99"], color="tab:red", ls="--", lw=0.8, label="p99")
            ax.legend(loc="best")
        ax.set_ylabel("solve time (µs)")
        ax.set_title("Solver")
        ax2 = fig.add_subplot(2, 1, 2, sharex=ax)
        if res is not None:
            r = numbers(res)
            ax2.plot(t, r, lw=0.8, color="tab:orange", **dot)
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
            ax.plot(t, col[:, j], lw=1.0, label=f"{name}{j + 1}", **dot)
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
