"""What ``hil info LOG`` says about a log, like ``mcap info`` or ``ros2 bag info``: the run, the
config digest, duration, ticks, laws, deadline misses, problems and the topics."""

from __future__ import annotations

from collections import Counter
from typing import Any

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
    """The controller summary's counters as far as the log has them (the final diagnostics and
    the ``hil.recorder`` metadata): what :func:`rt_controller.runtime.counters.run_problems`
    judges. The DSP fault counts of the summary are not in the log."""
    last = final_diagnostics(run) or {}
    ctl, dsp = diagnostics.values_of(last, "controller"), diagnostics.values_of(last, "dsp")
    recorder = {k: _int(v) for k, v in run.recorder.items() if _int(v) is not None}
    if not recorder:  # not closed cleanly: the counters of the last diagnostics, whose
        recorder = diagnostics.values_of(last, "recorder")  # queue was still to be written
        recorder.pop("pending", None)
    out: dict[str, Any] = {
        "recorder": recorder,
        "watchdog_trips": ctl.get("watchdog_trips", 0),
        "drive_ticks": {k[len("ticks.") :]: v for k, v in dsp.items() if k.startswith("ticks.")},
        "rejections": {
            "can_rx": diagnostics.values_of(last, "can_rx"),
            "features": diagnostics.values_of(last, "features"),
            "dsp_rejected_frames": int(dsp.get("rejected_frames", 0) or 0),
        },
    }
    if run.truncated:
        out["log_error"] = "the writer did not finish it (truncated)"
    return out


def _int(value: Any) -> int | None:
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


def log_info(run: Run) -> dict[str, Any]:
    """The ``hil info --json`` object of ``run``."""
    from rt_controller.logtools.deadline_report import summarize
    from rt_controller.runtime.counters import run_problems

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
    notes = list(report["notes"])
    if not run.log.diagnostics:
        notes.append("no /diagnostics records: problems judged on the recorder's counters only")
    elif not (final_diagnostics(run) or {}).get("final"):
        notes.append("no final /diagnostics record: problems judged on the last one")
    return {
        "log": str(run.path),
        "library": run.log.library,
        "truncated": run.truncated,
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
        "problems": run_problems(logged_summary(run)),
        "topics": topics,
        "messages": sum(run.topic_counts.values()),
        "run_info": dict(info),
        "notes": notes,
    }
