"""The results of ``hil experiment``: Table I rows, one JSON-ready results dict per sweep and
the paper's qualitative claims checked against the runs of :mod:`rt_controller.rig.experiment`."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rt_controller.rig.experiment import (
    HORIZONS_S,
    STEADY_FROM_S,
    RunResult,
    RunSpec,
    Settings,
    fmt_t,
)

LAW_NAMES = {"rhc": "receding horizon", "ioc": "inverse optimal", "pbc": "passivity based"}
PAPER_TABLE1: dict[float, tuple[list[int], int]] = {
    0.02: ([3352, 3357, 3367, 3477, 3486], 3408),
    0.1: ([3277, 3297, 3364, 3385, 3462], 3357),
    1.0: ([4097, 4158, 4204, 4211, 4252], 4184),
}
"""Table I of the paper: five runs per horizon (ascending) and the average."""


# ---------------------------------------------------------------------------------- results
def ordinal(n: int) -> str:
    """1st, 2nd, 3rd, 4th, ..., 11th, 12th, 13th, 21st."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def _mean(values: Sequence[float | None]) -> float | None:
    ok = [v for v in values if v is not None]
    return float(np.mean(ok)) if ok and len(ok) == len(values) else None


def ok_value(run: RunResult, value: float | None) -> float | None:
    """``value`` (a figure of ``run``) if the run ended ok, else None: a failed run's J (one
    cut short, or not clean) never enters a table's aggregate or a claim."""
    return value if run.status == "ok" else None


def table1_rows(specs: list[RunSpec], runs: dict[str, RunResult]) -> list[dict[str, Any]]:
    """One row per horizon: J per rep (seed order; None for a run that failed or did not run),
    sorted ascending, their average and how many runs it averages, N, seeds."""
    rows = []
    for h in HORIZONS_S:
        mine = [runs[s.name] for s in specs if s.horizon_s == h]
        js = [ok_value(r, r.J) for r in mine]
        ok = [j for j in js if j is not None]
        rows.append(
            {
                "horizon_s": h,
                "steps": mine[0].config.rhc.steps,
                "seeds": [r.spec.seed for r in mine],
                "J": js,
                "J_sorted": sorted(ok),
                "average": float(np.mean(ok)) if ok else None,
                "average_count": len(ok),
                "J_steady": [ok_value(r, r.J_steady) for r in mine],
                "failed": [r.spec.name for r in mine if r.status != "ok"],
            }
        )
    return rows


def _complete(row: dict[str, Any]) -> bool:
    """Whether a Table I row's average is over all its runs (rows without a count: if set)."""
    return row["average"] is not None and row.get("average_count", len(row["J"])) == len(row["J"])


def table1_markdown(rows: list[dict[str, Any]], digits: int = 3) -> str:
    """Rows like the paper's Table I: ``T = 0.02 s | 1st .. Nth (ascending) | average``; an
    average over fewer than the row's runs (some failed or did not run) says so: ``(4 of 5)``."""
    reps = max(len(r["J"]) for r in rows)
    head = ["Horizon length", *(ordinal(i + 1) for i in range(reps)), "average"]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (reps + 1)]
    for r in rows:
        cells = [f"{j:.{digits}f}" for j in r["J_sorted"]]
        cells += ["—"] * (reps - len(cells))
        avg = "—" if r["average"] is None else f"{r['average']:.{digits}f}"
        if r["average"] is not None and not _complete(r):  # some runs failed or did not run
            avg += f" ({r['average_count']} of {len(r['J'])})"
        lines.append(f"| T = {fmt_t(r['horizon_s'])} s | " + " | ".join([*cells, avg]) + " |")
    return "\n".join(lines)


def paper_table1_markdown() -> str:
    """The paper's Table I in the same layout."""
    lines = ["| Horizon length | 1st | 2nd | 3rd | 4th | 5th | average |", "|---|" + "---:|" * 6]
    for h, (vals, avg) in PAPER_TABLE1.items():
        lines.append(f"| T = {fmt_t(h)} s | " + " | ".join(str(v) for v in [*vals, avg]) + " |")
    return "\n".join(lines)


def run_record(run: RunResult, out: Path, duration_s: float) -> dict[str, Any]:
    """JSON-ready description of one run of ``duration_s`` (paths relative to the output
    folder)."""
    s = run.summary
    return {
        "name": run.spec.name,
        "law": run.spec.law,
        "horizon_s": run.spec.horizon_s,
        "steps": run.config.rhc.steps if run.spec.law == "rhc" else None,
        "noise_px": run.spec.noise_px,
        "seed": run.spec.seed,
        "profile": run.config.hardware.profile,
        "status": run.status,
        "error": run.error,
        "J": run.J,
        "J_steady": run.J_steady,
        "f_final": s.get("f_final"),
        "ticks": s.get("ticks"),
        "deadline_misses": s.get("deadline_misses"),
        "fallbacks": s.get("fallbacks"),
        "stale_features": s.get("stale_features"),
        "solve_us_median": s.get("solve_us_median"),
        "wall_s": run.wall_s,
        "can": run.can,
        "log": _rel(run.log, out),
        "config": _rel(run.config_file, out),
        "command": rerun_command(run, out, duration_s),
    }


def _rel(path: Path, out: Path) -> str:
    try:
        return str(path.relative_to(out))
    except ValueError:
        return str(path)


def rerun_command(run: RunResult, out: Path, duration_s: float) -> str:
    """The ``hil up`` command (run inside the output folder) that repeats this run of
    ``duration_s`` (also one cut short or never started), its code compiled for the CPU target
    the run's log records (``hil --target-of``) where the host can run it, so a lockstep rerun
    on another CPU gives the same J. It logs beside the run's log (``NAME.rerun.mcap``, replaced
    by the next rerun), which it keeps to compare with."""
    clock = "" if run.config.controller.clock == "realtime" else " --lockstep"
    can = f" --can {run.can}" if run.can else ""
    log = _rel(run.log, out)
    rerun = _rel(run.log.with_name(f"{run.log.stem}.rerun.mcap"), out)
    return (
        f"hil --target-of {log} up{clock}{can} --law {run.spec.law} --duration {duration_s:g} "
        f"--config {_rel(run.config_file, out)} --log {rerun} --force"
    )


def build_results(
    settings: Settings,
    runs_by_exp: dict[str, list[RunSpec]],
    runs: dict[str, RunResult],
    command: str,
    figures: dict[str, list[Path]] | None = None,
) -> dict[str, Any]:
    """The whole experiment as one JSON-ready dict (also what ``--json`` prints)."""
    out = settings.out
    base = settings.base_config()
    figures = figures or {}
    res: dict[str, Any] = {
        "command": command,
        "out": str(out),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "experiments": list(runs_by_exp),
        "clock": settings.clock,
        "profile": settings.hardware_profile(),
        "duration_s": settings.duration_s,
        "config": settings.config or "embedded default",
        "config_sets": settings.sets,
        "config_noise_px": base.camera.noise_px,
        "camera_model": base.camera.model,
        "rate_hz": base.rates.control_hz,
        "scenario": base.to_dict()["scenario"],
        "steps": {f"{fmt_t(h)}": None for h in HORIZONS_S},
        "runs": [run_record(r, out, settings.duration_s) for r in runs.values()],
        "failures": [
            {"run": r.spec.name, "label": r.spec.label, "error": r.error}
            for r in runs.values()
            if r.status == "failed"
        ],
    }
    for r in runs.values():
        if r.spec.law == "rhc" and r.spec.horizon_s is not None:
            res["steps"][f"{fmt_t(r.spec.horizon_s)}"] = r.config.rhc.steps
    res["steps"] = {k: v for k, v in res["steps"].items() if v is not None}
    for exp, specs in runs_by_exp.items():
        figs = [_rel(p, out) for p in figures.get(exp, [])]
        if exp == "table1":
            rows = table1_rows(specs, runs)
            res[exp] = {
                "reps": settings.reps,
                "noise_px": specs[0].noise_px,
                "seeds": rows[0]["seeds"],
                "rows": rows,
                "markdown": table1_markdown(rows),
                "paper": {
                    f"{fmt_t(h)}": {"J": v, "average": a} for h, (v, a) in PAPER_TABLE1.items()
                },
                "figures": figs,
            }
        else:
            key = (lambda s: s.law) if exp == "fig3" else (lambda s: f"{fmt_t(s.horizon_s)}")
            res[exp] = {
                "noise_px": specs[0].noise_px,
                "seed": specs[0].seed,
                "J": {key(s): ok_value(runs[s.name], runs[s.name].J) for s in specs},
                "J_steady": {key(s): ok_value(runs[s.name], runs[s.name].J_steady) for s in specs},
                "runs": {key(s): s.name for s in specs},
                "figures": figs,
            }
    res["claims"] = claims(res, runs_by_exp, runs)
    return res


# ----------------------------------------------------------------------- qualitative claims
def _max_f_gap(a: RunResult, b: RunResult) -> float | None:
    """Largest |f_a(t) - f_b(t)| (px) over the common ticks of two runs."""
    from rt_controller.logtools.reader import read_log

    fa = read_log(a.log, raw=False).column("f")
    fb = read_log(b.log, raw=False).column("f")
    if fa is None or fb is None:
        return None
    n = min(len(fa), len(fb))
    return float(np.nanmax(np.hypot(*(fa[:n] - fb[:n]).T))) if n else None


def claims(
    res: dict[str, Any], runs_by_exp: dict[str, list[RunSpec]], runs: dict[str, RunResult]
) -> list[dict[str, Any]]:
    """The paper's qualitative statements, each checked against these numbers."""
    out: list[dict[str, Any]] = []

    def add(claim: str, holds: bool | None, evidence: str) -> None:
        out.append({"claim": claim, "reproduced": holds, "evidence": evidence})

    if "fig3" in res and all(v is not None for v in res["fig3"]["J"].values()):
        J = res["fig3"]["J"]
        add(
            "Fig. 3: the laws that minimise the objective (RHC, IOC) beat passivity-based control",
            J["pbc"] > max(J["rhc"], J["ioc"]),
            f"J: RHC {J['rhc']:.3f}, IOC {J['ioc']:.3f}, PBC {J['pbc']:.3f}",
        )
        add(
            "Fig. 3: RHC is not inferior to inverse-optimal control",
            J["rhc"] <= J["ioc"],
            f"J_RHC - J_IOC = {J['rhc'] - J['ioc']:+.4f} "
            f"({100 * (J['rhc'] / J['ioc'] - 1):+.2f} %)",
        )
        specs = {s.law: s for s in runs_by_exp["fig3"]}
        gap = _max_f_gap(runs[specs["rhc"].name], runs[specs["ioc"].name])
        if gap is not None:
            add(
                "Fig. 3: RHC and IOC trajectories are almost the same",
                gap < 0.05 * 200.0,
                f"max |f_RHC - f_IOC| = {gap:.2f} px (|f(0)| = 200 px)",
            )
    src, avg = _horizon_values(res)
    if avg is not None:
        a = {h: avg[f"{fmt_t(h)}"] for h in HORIZONS_S}
        text = ", ".join(f"T = {fmt_t(h)} s: {v:.3f}" for h, v in a.items())
        add(
            f"{src}: T = 1.0 s has the largest J (the longer horizon is worse)",
            a[1.0] > max(a[0.02], a[0.1]),
            f"J ({'average' if src == 'Table I' else 'single run'}): {text}",
        )
        add(
            f"{src}: J is not monotonically increasing in T (T = 0.1 s beats T = 0.02 s)",
            a[0.1] < a[0.02],
            f"J(T = 0.1 s) - J(T = 0.02 s) = {a[0.1] - a[0.02]:+.4f}",
        )
    steady_src, steady = _steady_values(res)
    if steady is not None:
        text = ", ".join(f"T = {h} s: {v:.4f}" for h, v in steady.items())
        add(
            f"{steady_src}: after t = 4 s the T = 1.0 s controller is worse than the others",
            steady["1.0"] > max(steady["0.02"], steady["0.1"]),
            f"J over t >= {STEADY_FROM_S:g} s: {text}",
        )
    return out


def _horizon_values(res: dict[str, Any]) -> tuple[str, dict[str, float] | None]:
    if "table1" in res:
        rows = res["table1"]["rows"]
        if all(_complete(r) for r in rows):  # averages over every run of each row
            return "Table I", {f"{fmt_t(r['horizon_s'])}": r["average"] for r in rows}
    if "fig4" in res and all(v is not None for v in res["fig4"]["J"].values()):
        return "Fig. 4", dict(res["fig4"]["J"])
    return "", None


def _steady_values(res: dict[str, Any]) -> tuple[str, dict[str, float] | None]:
    """J over t >= 4 s per horizon (Fig. 4 runs, else the Table I averages)."""
    if "fig4" in res:
        src, vals = "Fig. 4", res["fig4"]["J_steady"]
    elif "table1" in res:
        src = "Table I runs"
        vals = {
            fmt_t(r["horizon_s"]): _mean(r["J_steady"]) if r["J_steady"] else None
            for r in res["table1"]["rows"]
        }
    else:
        return "", None
    return src, (vals if all(v is not None for v in vals.values()) else None)


def initial_4v(runs: dict[str, RunResult]) -> float | None:
    """4 V(x(0)) from a successful log (noise-free if any): J* of inverse-optimal control."""
    from rt_controller.logtools.reader import read_log

    ok = sorted((r for r in runs.values() if r.status == "ok"), key=lambda r: r.spec.noise_px > 0)
    for r in ok:
        v = read_log(r.log, raw=False).column("V")
        if v is not None and v.size and math.isfinite(float(v[0])):
            return 4.0 * float(v[0])
    return None
