"""The PNG figures of ``hil experiment``: the paper's Fig. 3 and Fig. 4 overlays and a Table I
bar chart (matplotlib, imported only here)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hal.whole_file import written_whole
from rt_controller.rig.experiment import (
    RunResult,
    RunSpec,
    Settings,
    fmt_t,
)
from rt_controller.rig.experiment_results import LAW_NAMES, table1_rows

LAW_STYLES = {"rhc": "-", "ioc": "--", "pbc": "-."}
HORIZON_STYLES = {0.02: "-", 0.1: "--", 1.0: "-."}
PANELS = {"f": ("f", "px"), "xi": ("ξ", ""), "u": ("u", "N·m")}
"""The overlays' quantities: ``STEM_<key>.png`` each, with its symbol and unit."""
FIGURE_FILES = (
    *(f"{stem}_{name}.png" for stem in ("fig3", "fig4") for name in PANELS),
    "table1_J.png",
)
"""Every figure file an experiment may write in its output folder."""


# ---------------------------------------------------------------------------------- figures
def plot_overlay(
    curves: list[tuple[str, str, Path]], outdir: Path, stem: str, title: str, jump_s: float | None
) -> list[Path]:
    """``STEM_f.png``, ``STEM_xi.png``, ``STEM_u.png``: each run's curves overlaid.

    ``curves`` holds (legend label, matplotlib line style, MCAP log). Components go in stacked
    panels, like the paper's figures; the target jump is marked with a dotted line.
    """
    from matplotlib.figure import Figure

    from rt_controller.logtools.deadline_report import time_axis
    from rt_controller.logtools.reader import read_log

    logs = [(label, style, read_log(path, raw=False)) for label, style, path in curves]
    written = []
    for name, (sym, unit) in PANELS.items():
        fig = Figure(figsize=(8, 5.5), layout="constrained")
        axes = fig.subplots(2, 1, sharex=True)
        for label, style, log in logs:
            col = log.column(name)
            if col is None or col.ndim != 2:
                continue
            t, t_label = time_axis(log)
            axes[-1].set_xlabel(t_label)
            for j, ax in enumerate(axes):
                ax.plot(t, col[:, j], style, lw=1.2, label=label)
        for j, ax in enumerate(axes):
            ax.set_ylabel(f"{sym}{j + 1}" + (f" ({unit})" if unit else ""))
            ax.grid(alpha=0.3)
            if jump_s is not None:
                ax.axvline(jump_s, color="grey", ls=":", lw=0.8)
        axes[0].legend(loc="best", fontsize="small")
        fig.suptitle(f"{title}: {sym}(t)")
        path = outdir / f"{stem}_{name}.png"
        with written_whole(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        written.append(path)
    return written


def plot_table1(rows: list[dict[str, Any]], outdir: Path) -> Path:
    """``table1_J.png``: J of every repetition per horizon, with the average."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.add_subplot()
    for i, r in enumerate(rows):
        js = [j for j in r["J"] if j is not None]
        ax.plot([i] * len(js), js, "o", alpha=0.7, color="tab:blue")
        if r["average"] is not None:
            ax.plot([i - 0.2, i + 0.2], [r["average"]] * 2, "-", color="tab:red", lw=2)
    ax.set_xticks(range(len(rows)), [f"T = {fmt_t(r['horizon_s'])} s" for r in rows])
    ax.set_xlim(-0.5, len(rows) - 0.5)
    ax.set_ylabel("J")
    ax.set_title("Table I: J per repetition (dots) and average (bar)")
    ax.grid(alpha=0.3, axis="y")
    path = outdir / "table1_J.png"
    with written_whole(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def write_figures(
    settings: Settings, runs_by_exp: dict[str, list[RunSpec]], runs: dict[str, RunResult]
) -> dict[str, list[Path]]:
    """The figures of every experiment whose runs all succeeded."""
    out: dict[str, list[Path]] = {}
    for exp, specs in runs_by_exp.items():
        if any(runs[s.name].status != "ok" for s in specs):
            continue
        cfg = runs[specs[0].name].config
        jump = cfg.scenario.jump_time if cfg.scenario.disturbance else None
        if exp == "fig3":
            curves = [
                (LAW_NAMES[s.law] + (f" (T = {fmt_t(s.horizon_s)} s)" if s.horizon_s else ""),
                 LAW_STYLES[s.law], runs[s.name].log)
                for s in specs
            ]  # fmt: skip
            out[exp] = plot_overlay(curves, settings.out, "fig3", "Fig. 3: RHC vs IOC vs PBC", jump)
        elif exp == "fig4":
            curves = [
                (f"T = {fmt_t(s.horizon_s)} s", HORIZON_STYLES[s.horizon_s], runs[s.name].log)
                for s in specs
            ]
            out[exp] = plot_overlay(curves, settings.out, "fig4", "Fig. 4: RHC horizons", jump)
        else:
            out[exp] = [plot_table1(table1_rows(specs, runs), settings.out)]
    return out
