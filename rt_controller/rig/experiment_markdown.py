"""``report.md`` of ``hil experiment``: the results dict rendered as Markdown (tables, claims,
comparison with the paper's Table I)."""

from __future__ import annotations

import json
from typing import Any

from rt_controller.rig.experiment import TABLE1_DEFAULT_NOISE_PX, fmt_t
from rt_controller.rig.experiment_results import LAW_NAMES, PAPER_TABLE1, paper_table1_markdown


def noise_words(noise_px: float, model: str) -> str:
    """The camera noise of runs: ``0.5 px pixel noise``, or the rendering camera's sensor."""
    if model == "image":
        return "the camera sensor's noise"
    return f"{noise_px:g} px pixel noise"


# ---------------------------------------------------------------------------------- report
def _j(x: float | None, digits: int = 3) -> str:
    """J, or "—" for a run without one (failed, or not run: its status says which)."""
    return "—" if x is None else f"{x:.{digits}f}"


def _scenario_text(sc: dict[str, Any]) -> str:
    q0 = ", ".join(f"{q:.4g}" for q in sc["q0"])
    text = (
        f'scenario "{sc["name"]}": q(0) = ({q0}) rad, f(0) = ({sc["f0"][0]:g}, {sc["f0"][1]:g}) px'
    )
    if sc["disturbance"]:
        fj = sc["f_jump"]
        text += f", target jump to f = ({fj[0]:g}, {fj[1]:g}) px at t = {sc['jump_time']:g} s"
    return text


_LOCKSTEP_TEXT = {
    "dsp": "(the emulated DSP clocks every tick with Sync frames: deterministic, faster than "
    "real time).",
    "cia402": "(the controller's CANopen SYNC steps the emulated drives' world by one period: "
    "deterministic, faster than real time).",
}
_PROFILE_TEXT = {
    "dsp": "(our DSP behind `hal/hil.dbc`, CAN FD with E2E and SecOC).",
    "cia402": "(two CANopen CiA 402 drives in cyclic synchronous torque; not authenticated; "
    "every run on a fresh set of processes).",
}
"""What report.md says of each clock and hardware profile (``hardware.profile``)."""


def render_report(res: dict[str, Any], four_v0: float | None = None) -> str:
    """``report.md``: what was run, the J tables, the figures, the comparison with the paper."""
    model = _model(res)
    md: list[str] = [f"# hil experiment: {', '.join(res['experiments'])}", ""]
    md += [
        f"Created {res['created']} by `{res['command']}`.",
        "",
        "## What was run",
        "",
        f"- Clock: **{res['clock']}** "
        + (
            _LOCKSTEP_TEXT[res.get("profile", "dsp")]
            if res["clock"] == "lockstep"
            else "(monotonic deadlines at the control rate: timing jitter makes runs differ)."
        ),
        f"- Hardware profile: **{res.get('profile', 'dsp')}** "
        + _PROFILE_TEXT[res.get("profile", "dsp")],
        f"- Each run: `hil emulator`, `hil vision`, `hil controller` as separate processes for "
        f"{res['duration_s']:g} s of plant time at a control rate of {res['rate_hz']:g} Hz; "
        + _scenario_text(res["scenario"])
        + ".",
        f"- Config: {res['config']}{_sets_text(res.get('config_sets'))} "
        f"(camera.model = {model}, camera.noise_px = "
        f"{res['config_noise_px']:g}). Each run's full configuration is in `configs/`, its MCAP "
        "log in `logs/`.",
        "- RHC horizon steps N (when only T is given, N = max(rhc.steps, ceil(T / 0.05 s)), "
        "as `hil controller --horizon T` does): "
        + ", ".join(
            f"T = {t} s → N = {n} (Δτ = {float(t) / n:.3g} s)" for t, n in res["steps"].items()
        )
        + ".",
    ]
    md.append(f"- CAN bus: {_bus_text(res['runs'])}.")
    for exp in ("fig3", "fig4"):
        if exp in res:
            same = res[exp]["noise_px"] == res["config_noise_px"] or model == "image"
            source = "the config's" if same else "--noise"
            md.append(
                f"- {exp}: {noise_words(res[exp]['noise_px'], model)} ({source}), "
                f"seed {res[exp]['seed']}."
            )
    if "table1" in res:
        t1 = res["table1"]
        why = (
            "the rendering camera's sensor noise, drawn from the seed"
            if model == "image"
            else f"pixel noise {t1['noise_px']:g} px (`--noise`, else the config's "
            f"camera.noise_px, else {TABLE1_DEFAULT_NOISE_PX:g} px when that is 0: with no "
            "noise every lockstep repetition would be identical)"
        )
        md.append(
            f"- table1: {t1['reps']} repetitions per horizon that differ by the camera noise seed "
            f"(repetition i uses seed i: {t1['seeds']}); {why}."
        )
    md += ["", "### Runs", "", "| run | law | T (s) | N | noise (px) | seed | J | J(t ≥ 4 s) | "
           "misses | fallbacks | wall (s) | status |", "|---|---|---:|---:|---:|---:|---:|---:|"
           "---:|---:|---:|---|"]  # fmt: skip
    for r in res["runs"]:
        cells = [
            f"`{r['name']}`",
            r["law"],
            "—" if r["horizon_s"] is None else f"{fmt_t(r['horizon_s'])}",
            "—" if r["steps"] is None else str(r["steps"]),
            f"{r['noise_px']:g}",
            str(r["seed"]),
            _j(r["J"]),
            "—" if r["J_steady"] is None else f"{r['J_steady']:.4f}",
            str(r["deadline_misses"] if r["deadline_misses"] is not None else "—"),
            str(r["fallbacks"] if r["fallbacks"] is not None else "—"),
            "—" if r["wall_s"] is None else f"{r['wall_s']:.1f}",
            _status(r),
        ]
        md.append("| " + " | ".join(cells) + " |")
    md += ["", "Each run again (from inside this folder):", "", "```sh"]
    md += [r["command"] for r in res["runs"]] + ["```", ""]

    if "fig3" in res:
        J = res["fig3"]["J"]
        md += [
            "## Fig. 3: receding horizon (T = 0.02 s) vs inverse optimal vs passivity based",
            "",
            "Solid: RHC, dashed: IOC, dash-dot: PBC (as in the paper). The dotted line marks the "
            "target jump.",
            "",
            "| law | J |",
            "|---|---:|",
            *(f"| {LAW_NAMES[k]} ({k.upper()}) | {_j(v)} |" for k, v in J.items()),
            "",
            *(f"![{p}]({p})" for p in res["fig3"]["figures"]),
            "",
        ]
    if "fig4" in res:
        J = res["fig4"]["J"]
        md += [
            "## Fig. 4: receding horizon with T = 0.02, 0.1, 1.0 s",
            "",
            "Solid: T = 0.02 s, dashed: T = 0.1 s, dash-dot: T = 1.0 s (as in the paper).",
            "",
            "| horizon | N | J | J(t ≥ 4 s) |",
            "|---|---:|---:|---:|",
            *(
                f"| T = {k} s | {res['steps'].get(k, '—')} | {_j(v)} | "
                f"{_opt(res['fig4']['J_steady'].get(k))} |"
                for k, v in J.items()
            ),
            "",
            *(f"![{p}]({p})" for p in res["fig4"]["figures"]),
            "",
        ]
    if "table1" in res:
        t1 = res["table1"]
        md += [
            "## Table I: values of the objective function",
            "",
            f"J of each repetition, sorted ascending per row as in the paper, and the average "
            f"({noise_words(t1['noise_px'], model)}, seeds {t1['seeds']}):",
            "",
            t1["markdown"],
            "",
            *_left_out(t1["rows"]),
            "The same values in run order (seed by seed):",
            "",
            "| Horizon length | "
            + " | ".join(f"seed {s}" for s in t1["seeds"])
            + " | spread (max - min) |",
            "|---|" + "---:|" * (len(t1["seeds"]) + 1),
        ]
        for row in t1["rows"]:
            md.append(
                f"| T = {fmt_t(row['horizon_s'])} s | "
                + " | ".join(_j(j) for j in row["J"])
                + f" | {_spread(row)} |"
            )
        md += ["", *(f"![{p}]({p})" for p in t1["figures"]), ""]
        md += ["The paper's Table I (its own J scale, see below):", "", paper_table1_markdown(), ""]
    md += _comparison(res, four_v0)
    if res["failures"]:
        md += ["## Failures", ""]
        md += [f"- `{f['run']}` ({f['label']}):\n\n  ```\n  {_indent(f['error'])}\n  ```"
               for f in res["failures"]]  # fmt: skip
        md.append("")
    return "\n".join(md)


def _status(run: dict[str, Any]) -> str:
    """A run's status cell: a run not run says so, and why when known (a process died)."""
    if run["status"] != "pending":
        return run["status"]
    return run["error"] or "not run"


def _spread(row: dict[str, Any]) -> str:
    """A Table I row's max - min over its runs that ended ok: "—" under two (one run has no
    spread), and over fewer than the row's runs it says how many, as the average does."""
    ok = row["J_sorted"]
    if len(ok) < 2:
        return "—"
    text = f"{ok[-1] - ok[0]:.4f}"
    return text if len(ok) == len(row["J"]) else f"{text} ({len(ok)} of {len(row['J'])})"


def _left_out(rows: list[dict[str, Any]]) -> list[str]:
    """The note under Table I naming the runs its averages leave out (failed or not run)."""
    names = [f"`{name}`" for row in rows for name in row.get("failed", [])]
    if not names:
        return []
    return [
        f"Not in the table nor its averages (failed or not run, see Runs): {', '.join(names)}; "
        "an average or spread over fewer runs than the row has says how many, e.g. (4 of 5).",
        "",
    ]


def _bus_text(runs: list[dict[str, Any]]) -> str:
    buses = sorted({r["can"] for r in runs if r["can"]})
    if not buses:
        return "none used"
    if len(buses) > 1 and all(b.startswith("udp_multicast") for b in buses):
        return (
            "host-local `udp_multicast`, a private port per run (the automatic bus is shared by "
            "every rig on the host); see the commands below"
        )
    return ", ".join(f"`{b}`" for b in buses)


_SEEDED = {"image": "the camera sensor's noise", "analytic": "Gaussian pixel noise"}
"""What the seed of a repetition draws, by camera model."""


def _model(res: dict[str, Any]) -> str:
    """The runs' camera model (results written before it was recorded: analytic)."""
    return res.get("camera_model", "analytic")


def _noise_note(res: dict[str, Any]) -> list[str]:
    """How the repetitions' spread compares with the paper's (table1 only)."""
    if "table1" not in res:
        return []
    ours = []
    for row in res["table1"]["rows"]:
        js, avg = row["J_sorted"], row["average"]
        if len(js) > 1 and avg:  # one run has no spread
            ours.append(f"T = {fmt_t(row['horizon_s'])} s: {100 * (js[-1] - js[0]) / avg:.2f} %")
    paper = ", ".join(
        f"T = {fmt_t(h)} s: {100 * (v[-1] - v[0]) / a:.1f} %" for h, (v, a) in PAPER_TABLE1.items()
    )
    return [
        "**Repetitions.** The paper's runs differ by real camera noise, friction and timing; "
        f"ours differ only by the seed of {_SEEDED[_model(res)]} on an emulated, friction-free "
        f"arm ({res['clock']} clock). Spread (max - min) / average per row, ours: "
        f"{', '.join(ours) or '—'}; the paper's: {paper}.",
        "",
    ]


def _opt(x: float | None, digits: int = 4) -> str:
    return "—" if x is None else f"{x:.{digits}f}"


def _indent(text: str | None) -> str:
    return (text or "").replace("\n", "\n  ")


def _comparison(res: dict[str, Any], four_v0: float | None) -> list[str]:
    ref = (
        f" For this scenario J* = 4V(x(0)) ≈ {four_v0:.2f} (eq. 28: the inverse-optimal cost "
        "of an endless run without the jump, in continuous time); the target jump at 3 s starts "
        "a second transient that the runs also pay for."
        if four_v0 is not None
        else ""
    )
    md = [
        "## Comparison with the paper",
        "",
        "**Scale.** Our J is the paper's stage cost l(x, u) = 4xᵀQx + uᵀR⁻¹u (eq. 25) summed "
        "over the logged ticks times the control period (J = Σ_k l(x_k, u_k) / rate, as every "
        "hil summary reports it), with f in pixels and the paper's gains (eq. 34)." + ref + " The "
        "paper's Table I values (≈ 3300-4300) are on a different absolute scale that the paper "
        "does not define (units, integration window and any weighting of its logged J are not "
        "stated), so only orderings and relative differences are comparable, not the numbers.",
        "",
        *_noise_note(res),
        "**Qualitative claims, checked on these runs:**",
        "",
    ]
    for c in res["claims"]:
        mark = {True: "reproduced", False: "**not reproduced**", None: "not checked"}
        md.append(f"- {c['claim']}: {mark[c['reproduced']]} ({c['evidence']}).")
    if not res["claims"]:
        md.append("- (no complete experiment to check)")
    md.append("")
    return md


def _sets_text(sets: dict[str, Any] | None) -> str:
    """The ``--set`` keys of every run, as typed (``, with --set gains.kp=0.3``), or nothing."""
    if not sets:
        return ""
    return ", with " + " ".join(f"`--set {k}={json.dumps(v)}`" for k, v in sets.items())
