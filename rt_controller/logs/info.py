"""What ``hil info LOG`` says about a log, like ``mcap info`` or ``ros2 bag info``: the run, the
config digest, duration, ticks, laws, deadline misses, problems and the topics."""

from __future__ import annotations

from collections import Counter
from typing import Any

from hal.drive_state import MODE_ENABLED, MODES
from rt_controller.logs.run import Run
from rt_controller.runtime import diagnostics

RUN_KEYS = (
    "clock",
    "law",
    "rate_hz",
    "can",
    "zenoh",
    "recorder",
    "start_wall_time",
    "hostname",
    "numba_cpu_name",
)
"""The ``hil.run`` metadata ``hil info`` shows (``--json`` has all of it under ``run_info``)."""


def final_diagnostics(run: Run) -> dict[str, Any] | None:
    """The run's final ``/diagnostics`` record, else its last one (a killed run), else None."""
    records = run.log.diagnostics
    finals = [r for r in records if r.get("final")]
    return (finals or records or [None])[-1]


def logged_summary(run: Run) -> dict[str, Any]:
    """The controller summary's counters as far as the log has them: what
    :func:`rt_controller.runtime.counters.run_problems` and ``run_warnings`` judge. From the
    final ``/diagnostics`` record (with the run's ``dsp_faults``, ``drive_ticks`` and
    ``outages``: ``RunCounters.judged``) and the ``hil.recorder`` metadata; where the log has
    no final record with them (a killed run, an older log) the outages are rebuilt from the
    cycle records, the ticks without an enabled DSP taken from the ``dsp`` component's
    ``ticks.*`` (else the cycle records' modes), and no DSP fault is known."""
    last = final_diagnostics(run) or {}
    final = last if last.get("final") else {}
    ctl, dsp = diagnostics.values_of(last, "controller"), diagnostics.values_of(last, "dsp")
    recorder = {k: _int(v) for k, v in run.recorder.items() if _int(v) is not None}
    if not recorder:  # not closed cleanly: the counters of the last diagnostics, whose
        recorder = diagnostics.values_of(last, "recorder")  # queue was still to be written
        recorder.pop("pending", None)
    out: dict[str, Any] = {
        "clock": run.info.get("clock"),
        "recorder": recorder,
        "watchdog_trips": ctl.get("watchdog_trips", 0),
        "dsp_faults": _counts(final.get("dsp_faults")) or {},
        "drive_ticks": _counts(final.get("drive_ticks")),
        "outages": final.get("outages"),
        "rejections": {
            "can_rx": diagnostics.values_of(last, "can_rx"),
            "features": diagnostics.values_of(last, "features"),
            "dsp_rejected_frames": int(dsp.get("rejected_frames", 0) or 0),
        },
        "parameters": diagnostics.values_of(last, "parameters"),
    }
    if final.get("end_reason") is not None:  # how the run ended, as its summary says it
        end = run_end(run)
        end["ticks"] = end.pop("ticks_run")
        out.update(end)
    if out["drive_ticks"] is None:  # the dsp profile's counts, else the cycle records'
        ticks = {k[len("ticks.") :]: v for k, v in dsp.items() if k.startswith("ticks.")}
        out["drive_ticks"] = ticks or _drive_ticks_of_cycles(run)
    if not isinstance(out["outages"], dict):
        from rt_controller.logtools.deadline_report import log_outages

        out["outages"] = log_outages(run.log)
    walk = run.log.walk
    if walk is not None and walk.footer and walk.skipped:
        out["log_error"] = (
            f"{len(walk.skipped)} damaged chunk(s) ({walk.skipped_bytes} bytes) could not be "
            "read and were skipped"
        )
    elif run.truncated:
        out["log_error"] = "the writer did not finish it (truncated)"
    return out


def _counts(value: Any) -> dict[str, int] | None:
    """A ``{name: count}`` block of the final record; None where it is not one."""
    if not isinstance(value, dict):
        return None
    counts = {str(k): _int(v) for k, v in value.items()}
    return {k: v for k, v in counts.items() if v}


def _drive_ticks_of_cycles(run: Run) -> dict[str, int]:
    """Ticks without an enabled DSP by mode, from the cycle records' ``law`` (the drive's mode
    in such a tick: ``fault``, ``no_status``, ...)."""
    laws = run.log.column("law")
    if laws is None:
        return {}
    modes = set(MODES) - {MODE_ENABLED}
    return dict(Counter(str(x) for x in laws if str(x) in modes))


def judge(run: Run, ticks: int) -> tuple[list[str], list[str], list[str]]:
    """The log's verdict as the controller's rule gives it: its problems (``run_problems`` on
    :func:`logged_summary`, then :func:`log_problems`), its warnings (``run_warnings``) and
    notes on what the verdict rests on. ``ticks``: the cycle records read."""
    from rt_controller.runtime.counters import run_problems, run_warnings

    summary = logged_summary(run)
    problems = run_problems(summary) + log_problems(run, ticks)
    notes = []
    if not run.log.diagnostics:
        notes.append("no /diagnostics records: problems judged on the recorder's counters only")
    elif not (final_diagnostics(run) or {}).get("final"):
        notes.append("no final /diagnostics record: problems judged on the last one")
    return problems, run_warnings(summary), notes


def _int(value: Any) -> int | None:
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


def log_problems(run: Run, ticks: int) -> list[str]:
    """What the log itself says is wrong with the run, beyond the counters: the controller
    always writes a final ``/diagnostics`` record when it ends a run in order, so a complete
    log without one is of a run killed or cut (a truncated log already says so); a copy that
    ``hil recover`` made by skipping damaged chunks lost ticks; records that could not be read
    were skipped (``LoadedLog.rejected``)."""
    out = []
    by_controller = "replay_of" not in run.info and (
        bool(run.log.diagnostics) or "recorder" in run.info
    )  # not a replay's log (``hil replay --out``: no diagnostics)
    if by_controller and not run.truncated and not (final_diagnostics(run) or {}).get("final"):
        out.append(
            "no final /diagnostics record: the run did not end in order (the controller or its "
            f"recorder was killed, or the log was cut) after {ticks} ticks"
        )
    skipped = _int((run.log.recovered_info or {}).get("skipped_bytes"))
    if skipped:
        out.append(f"recovered from a damaged log: {skipped} bytes of damaged chunks skipped")
    for topic, n in sorted(run.log.rejected.items()):
        out.append(f"{n} {topic} message(s) could not be read as records and were skipped")
    return out


def run_end(run: Run) -> dict[str, Any]:
    """How the run ended, as its final ``/diagnostics`` record says: ``planned_ticks`` (the
    ticks its duration asked for; None: until stopped), ``end_reason``, ``ticks_run`` and
    ``stop_signal`` (the signal that stopped it, e.g. ``SIGINT``); None each where the log does
    not say (an older log, or no final record)."""
    final = final_diagnostics(run) or {}
    if not final.get("final"):
        final = {}
    reason, by = final.get("end_reason"), final.get("stop_signal")
    return {
        "planned_ticks": _int(final.get("planned_ticks")),
        "end_reason": reason if isinstance(reason, str) else None,
        "ticks_run": _int(final.get("tick")) if "end_reason" in final else None,
        "stop_signal": by if isinstance(by, str) else None,
    }


def recovered_from(run: Run) -> dict[str, Any] | None:
    """The ``hil.recovered`` record of a copy made by ``hil recover`` (where from, bytes kept
    and lost, why the read of the input stopped) with a ``line`` for people; None otherwise."""
    meta = run.log.recovered_info
    if meta is None:
        return None
    out: dict[str, Any] = {"from": meta.get("from"), "stopped": meta.get("stopped")}
    for key in ("input_bytes", "kept_bytes", "skipped_bytes"):
        out[key] = _int(meta.get(key))
    if out["input_bytes"] is not None and out["kept_bytes"] is not None:
        out["lost_bytes"] = out["input_bytes"] - out["kept_bytes"]
    lost, skipped = out.get("lost_bytes"), out["skipped_bytes"]
    out["line"] = (
        f"recovered by `hil recover` from {out['from']}: kept {out['kept_bytes']} of "
        f"{out['input_bytes']} bytes, lost {'unknown' if lost is None else lost} "
        f"({out['stopped'] or 'unknown'}"
        + (f"; {skipped} bytes of damaged chunks skipped)" if skipped else ")")
    )
    return out


def judged_report(log: Any, *, max_list: int = 50) -> dict[str, Any]:
    """``hil report``'s dict of a loaded log (:func:`~rt_controller.logtools.deadline_report.
    summarize`) with the run's ``problems`` and ``warnings`` as ``hil info`` judges them
    (:func:`judge`)."""
    from rt_controller.logtools.deadline_report import summarize

    out = summarize(log, max_list=max_list)
    out["problems"], out["warnings"], _ = judge(Run(log), log.n_cycles)
    return out


def log_info(run: Run) -> dict[str, Any]:
    """The ``hil info --json`` object of ``run``."""
    from rt_controller.logtools.deadline_report import summarize

    report = summarize(run.log, max_list=0)
    laws = run.log.column("law")
    info = run.info
    run_summary = {k: info[k] for k in RUN_KEYS if k in info}
    if report.get("law") and "law" not in run_summary:
        run_summary["law"] = report["law"]
    if report.get("clock") and "clock" not in run_summary:
        run_summary["clock"] = report["clock"]
    topics = {
        topic: {"messages": n, "schema": run.log.schemas.get(topic)}
        for topic, n in sorted(run.topic_counts.items())
    }
    for topic, schema in sorted(run.log.schemas.items()):
        topics.setdefault(topic, {"messages": 0, "schema": schema})
    t = run.log.column("tick")
    problems, warnings, judged_notes = judge(run, report["ticks"])
    notes = list(report["notes"]) + judged_notes
    recovered = recovered_from(run)
    return {
        "log": str(run.path),
        "library": run.log.library,
        "truncated": run.truncated,
        "damaged": bool(run.log.walk and run.log.walk.footer and run.log.walk.skipped),
        "run": run_summary,
        "config_digest": run.config_digest,
        "duration_s": report["duration_s"],
        "time_axis": report["time_axis"],
        "ticks": report["ticks"],
        "first_tick": int(t[0]) if t is not None and len(t) else None,
        "last_tick": int(t[-1]) if t is not None and len(t) else None,
        "laws": dict(Counter(str(x) for x in laws)) if laws is not None else {},
        "deadline_misses": report["deadline_misses"],
        "missed_periods": report["missed_periods"],
        **run_end(run),
        "problems": problems,
        "warnings": warnings,
        "rejected": dict(run.log.rejected),
        "recovered": recovered,
        "topics": topics,
        "messages": sum(run.topic_counts.values()),
        "run_info": dict(info),
        "notes": notes,
    }
