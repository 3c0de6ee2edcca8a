"""``report.md`` of a sweep: J against each axis (median and spread) and a pass/fail map.

A run passes when it finished (status ok), ran clean (no ``problems``, no DSP fault) and ends
with final |f| below ``study.pass_f_final_px``. The plots are PNGs in ``plots/`` next to the
report: per axis, J of every run (points) with the median per value and the 25-75 % band
(grid axes) or per decile bin of the value (distribution axes); for two grid axes, the map of
the share of passing runs per cell, annotated with the median J.
"""

from __future__ import annotations

import itertools
import math
import re
from pathlib import Path
from typing import Any

from rt_controller.sweep.results import PARQUET
from rt_controller.sweep.spec import Spec

MAX_TABLE_ROWS = 60


def passed(df: Any, threshold_px: float) -> Any:
    return (
        (df["status"] == "ok")
        & (df["problems"].fillna("") == "")
        & (df["dsp_faults"] == 0)
        & (df["f_final_norm"] < threshold_px)
    )


def _safe(key: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", key)


def _plot_axis(df: Any, key: str, grid: bool, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    ok = df[df["status"] == "ok"]
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    numeric = ok[key].dtype.kind in "fiu"
    if grid:
        values = list(dict.fromkeys(df[key]))  # the spec's order
        xs = values if numeric else list(range(len(values)))
        med, lo, hi = [], [], []
        for v in values:
            j = ok.loc[ok[key] == v, "J"].to_numpy(dtype=float)
            j = j[np.isfinite(j)]
            med.append(np.median(j) if j.size else np.nan)
            lo.append(np.percentile(j, 25) if j.size else np.nan)
            hi.append(np.percentile(j, 75) if j.size else np.nan)
        pos = {v: x for v, x in zip(values, xs, strict=True)}
        ax.scatter([pos[v] for v in ok[key]], ok["J"], s=10, alpha=0.35, color="tab:gray",
                   label="runs")  # fmt: skip
        ax.fill_between(xs, lo, hi, alpha=0.25, color="tab:blue", label="25-75 %")
        ax.plot(xs, med, "o-", color="tab:blue", label="median")
        if not numeric:
            ax.set_xticks(xs, [str(v) for v in values])
    else:
        x = ok[key].to_numpy(dtype=float)
        j = ok["J"].to_numpy(dtype=float)
        ax.scatter(x, j, s=10, alpha=0.35, color="tab:gray", label="runs")
        if x.size >= 10:
            edges = np.quantile(x, np.linspace(0, 1, 11))
            mid, med, lo, hi = [], [], [], []
            for a, b in itertools.pairwise(edges):
                sel = (x >= a) & (x <= b) & np.isfinite(j)
                if sel.any():
                    mid.append(float(np.median(x[sel])))
                    med.append(float(np.median(j[sel])))
                    lo.append(float(np.percentile(j[sel], 25)))
                    hi.append(float(np.percentile(j[sel], 75)))
            ax.fill_between(mid, lo, hi, alpha=0.25, color="tab:blue", label="25-75 % (deciles)")
            ax.plot(mid, med, "o-", color="tab:blue", label="median (deciles)")
    ax.set_xlabel(key)
    ax.set_ylabel("J")
    ax.set_title(f"J against {key} ({len(ok)} runs)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _plot_map(df: Any, kx: str, ky: str, threshold: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    xs, ys = list(dict.fromkeys(df[kx])), list(dict.fromkeys(df[ky]))
    share = np.full((len(ys), len(xs)), np.nan)
    labels = [["" for _ in xs] for _ in ys]
    ok_mask = passed(df, threshold)
    for i, y in enumerate(ys):
        for k, x in enumerate(xs):
            cell = (df[kx] == x) & (df[ky] == y)
            n = int(cell.sum())
            if n:
                good = int((cell & ok_mask).sum())
                share[i, k] = good / n
                j = df.loc[cell & (df["status"] == "ok"), "J"].to_numpy(dtype=float)
                med = f"\nJ {np.nanmedian(j):.3g}" if j.size and np.isfinite(j).any() else ""
                labels[i][k] = f"{good}/{n}{med}"
    fig, ax = plt.subplots(figsize=(1.2 * len(xs) + 2.5, 0.8 * len(ys) + 2.0), dpi=110)
    im = ax.imshow(share, cmap="RdYlGn", vmin=0, vmax=1, origin="lower", aspect="auto")
    for i in range(len(ys)):
        for k in range(len(xs)):
            ax.text(k, i, labels[i][k], ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(xs)), [f"{v:g}" if isinstance(v, float) else str(v) for v in xs])
    ax.set_yticks(range(len(ys)), [f"{v:g}" if isinstance(v, float) else str(v) for v in ys])
    ax.set_xlabel(kx)
    ax.set_ylabel(ky)
    ax.set_title(f"passing runs (final |f| < {threshold:g} px, clean)")
    fig.colorbar(im, ax=ax, label="share passing")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.4g}"
    return str(v)


def _missing_lines(df: Any, spec: Spec) -> list[str]:
    """The runs of the spec with no row yet (an interrupted sweep), and their points."""
    missing = spec.runs - len(df)
    if missing <= 0:
        return []
    complete = int((df.groupby("point").size() >= spec.study.repetitions).sum())
    return [
        f"- **not finished: {missing} run(s)**, at {len(spec.points) - complete} point(s) (the "
        "sweep was interrupted: the same command runs them); the figures below are over the "
        "finished runs only"
    ]


def _point_table(df: Any, spec: Spec) -> list[str]:
    """One line per point of the spec, in its order, those with no finished run too."""
    stats = df.groupby("point").agg(
        finished=("run_key", "size"),
        ok=("status", lambda s: int((s == "ok").sum())),
        passed=("passed", "sum"),
        J_median=("J", "median"),
        J_min=("J", "min"),
        J_max=("J", "max"),
        f_final_median=("f_final_norm", "median"),
    )
    names = [*stats.columns]
    head = [*spec.axis_keys, "runs", *names]
    lines = ["## Per point", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p, values in enumerate(spec.points[:MAX_TABLE_ROWS]):
        got = stats.loc[p].tolist() if p in stats.index else [0, 0, 0, *[math.nan] * 4]
        cells = [*values.values(), spec.study.repetitions, *got]
        lines.append("| " + " | ".join(_fmt(v) for v in cells) + " |")
    if len(spec.points) > MAX_TABLE_ROWS:
        lines.append(f"\n({len(spec.points) - MAX_TABLE_ROWS} more points: results.parquet)")
    return [*lines, ""]


def write_report(out: Path, spec: Spec) -> Path:
    """Write ``out/report.md`` (and ``out/plots/*.png``) from ``out/results.parquet``."""
    import pandas as pd

    out = Path(out)
    path = out / "report.md"
    study = spec.study
    lines = [f"# Sweep: {study.name}", ""]
    if not (out / PARQUET).exists():
        lines.append(f"No run has finished yet (0 of {spec.runs}): the same command runs them.")
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        return path
    df = pd.read_parquet(out / PARQUET)
    df = df[df["spec_hash"] == spec.spec_hash]
    ok = df[df["status"] == "ok"]
    good = passed(df, study.pass_f_final_px)
    engines = ", ".join(sorted(set(df["engine"])))
    lines += [
        f"Spec `{spec.path}` (hash `{spec.spec_hash}`), engine {engines}, "
        f"{study.duration_s:g} s per run, {study.repetitions} repetition(s) per point, "
        f"{len(spec.points)} point(s).",
        "",
        f"- runs: {len(df)} of {spec.runs} finished; {len(ok)} ok, {len(df) - len(ok)} failed",
        *_missing_lines(df, spec),
        f"- passing (clean, final |f| < {study.pass_f_final_px:g} px): {int(good.sum())}",
        f"- J over the ok runs: median {_fmt(float(ok['J'].median()) if len(ok) else math.nan)}"
        f", 5-95 % {_fmt(float(ok['J'].quantile(0.05)) if len(ok) else math.nan)} .. "
        f"{_fmt(float(ok['J'].quantile(0.95)) if len(ok) else math.nan)}",
        f"- run wall time: sum {df['wall_s'].sum():.1f} s, median {df['wall_s'].median():.3g} s",
        f"- version {', '.join(sorted(set(df['version'])))}",
    ]
    if "rig" in set(df["engine"]):  # the simulate engine drives no hardware
        lines.append(f"- hardware profile: {', '.join(spec.hardware_profiles())}")
    lines.append("")
    plots = out / "plots"
    plots.mkdir(exist_ok=True)
    grid_keys = [a.key for a in spec.axes if a.grid]
    for axis in spec.axes:
        if not len(ok):
            break
        png = plots / f"J_vs_{_safe(axis.key)}.png"
        _plot_axis(df, axis.key, axis.grid, png)
        lines += [
            f"## J against `{axis.key}`",
            "",
            f"![J against {axis.key}](plots/{png.name})",
            "",
        ]
    if len(grid_keys) == 2 and len(df):
        png = plots / "pass_map.png"
        _plot_map(df, grid_keys[0], grid_keys[1], study.pass_f_final_px, png)
        lines += ["## Pass/fail map", "", f"![pass/fail map](plots/{png.name})", ""]
    if spec.axis_keys and len(df):
        lines += _point_table(df.assign(passed=good), spec)
    failed = df[df["status"] != "ok"]
    if len(failed):
        lines += ["## Failed runs", ""]
        for rec in failed.head(20).itertuples(index=False):
            lines.append(f"- point {rec.point} rep {rec.rep} (`{rec.run_key}`): {rec.error}")
        lines.append("")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
