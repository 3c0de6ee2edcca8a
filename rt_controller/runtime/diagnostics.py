"""The ``/diagnostics`` record: every counter a supervisor needs, about once a second, like ROS
``diagnostic_msgs/DiagnosticArray`` (per component ``can_rx``, ``features``, ``dsp``,
``controller``, ``recorder``: a level, a message and key/values). The controller's summary and
``hil report`` take their counters from it, so they agree.
"""

from __future__ import annotations

from typing import Any

OK, WARN, ERROR = 0, 1, 2

DIAGNOSTICS_SCHEMA: dict[str, Any] = {
    "title": "hil.Diagnostics",
    "description": "Counters of every component of the controller process (about 1 Hz, and a "
    "final one at the end of the run), like ROS diagnostic_msgs/DiagnosticArray.",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "time.monotonic_ns() when taken"},
        "tick": {"type": "integer", "description": "ticks run so far"},
        "final": {"type": "boolean", "description": "the last record of the run"},
        "level": {"type": "integer", "description": "worst status level: 0 ok, 1 warn, 2 error"},
        "planned_ticks": {
            "type": ["integer", "null"],
            "description": "final record only: the ticks the run's duration asked for (null: "
            "no duration, run until stopped)",
        },
        "end_reason": {
            "type": "string",
            "description": "final record only: why the loop ended: duration, stopped (a stop "
            "request) or a short phrase (no Sync from the DSP, ...)",
        },
        "stop_signal": {
            "type": ["string", "null"],
            "description": "final record only: the signal that stopped the controller "
            "(SIGINT, SIGTERM) when end_reason is stopped by one; null otherwise",
        },
        "dsp_faults": {
            "type": "object",
            "additionalProperties": {"type": "integer"},
            "description": "final record only: faults the drive(s) reported in the run, by "
            "reason (watchdog, position_limit, emcy_8700, heartbeat_lost, ...)",
        },
        "drive_ticks": {
            "type": "object",
            "additionalProperties": {"type": "integer"},
            "description": "final record only: ticks run without an enabled drive, by mode "
            "(fault, no_status, disarmed, dsp_restarted)",
        },
        "outages": {
            "type": "object",
            "description": "final record only: the run's camera outages as the controller "
            "counted them (warn_periods, max_share, count, listed, longest, longest_ticks, "
            "ticks_on_stale_or_invalid, share), the block of its summary",
        },
        "status": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "name": {"type": "string"},
                    "level": {"type": "integer"},
                    "message": {"type": "string"},
                    "values": {"type": "object", "additionalProperties": {}},
                },
                "required": ["name", "level", "message", "values"],
            },
        },
    },
    "required": ["t_ns", "tick", "level", "status"],
}


def since(base: dict[str, Any], now: dict[str, Any]) -> dict[str, Any]:
    """Counters ``now`` minus ``base`` (counters missing from ``base`` count from zero)."""
    return {k: v - base.get(k, 0) if isinstance(v, int) else v for k, v in now.items()}


AUTH_REJECTIONS = ("bad_mac", "stale_freshness", "future_freshness")
"""Receiver counters of frames/messages that failed authentication (hal/secoc.py)."""
AUTH_FAULT_MIN = 10
"""This many authentication failures in a run are a sustained stream, not a glitch: an error
in ``/diagnostics`` and a reason the run is not clean."""


def auth_failures(values: dict[str, Any]) -> dict[str, int]:
    """The authentication failures among a receiver's counters, by reason."""
    return {k: int(values.get(k, 0)) for k in AUTH_REJECTIONS if k in values}


def _rx_status(name: str, values: dict[str, Any], what: str) -> dict[str, Any]:
    bad, auth = rejected(values), sum(auth_failures(values).values())
    if auth >= AUTH_FAULT_MIN:
        return _status(name, ERROR, f"{auth} {what} failed authentication", values)
    if bad:
        return _status(name, WARN, f"{bad} {what} rejected", values)
    return _status(name, OK, f"all {what} accepted", values)


def _status(name: str, level: int, message: str, values: dict[str, Any]) -> dict[str, Any]:
    return {"name": name, "level": level, "message": message, "values": values}


def rejected(values: dict[str, Any]) -> int:
    """Rejections in a receiver's counters (its ``rejected`` total, else every ``bad_*`` and
    ``stale_*`` bucket)."""
    if "rejected" in values:
        return int(values["rejected"])
    return sum(int(v) for k, v in values.items() if k.startswith(("bad_", "stale_")))


def _parameters_status(values: dict[str, Any]) -> dict[str, Any]:
    """The parameter service's status: an error when it failed on requests (lost unanswered,
    a fault of the controller's, as a lost record is the recorder's), a warning when it
    refused unauthenticated ones (someone else's)."""
    failed, rogue = int(values.get("failed", 0)), int(values.get("unauthenticated", 0))
    if failed:
        why = f"{failed} request(s) failed in the controller, refused or unanswered"
        return _status(
            "parameters", ERROR, why + (f"; {rogue} unauthenticated" if rogue else ""), values
        )
    why = f"{rogue} unauthenticated request(s)" if rogue else "no unauthenticated request"
    return _status("parameters", WARN if rogue else OK, why, values)


def build(
    *,
    t_ns: int,
    tick: int,
    can_rx: dict[str, Any],
    features: dict[str, Any],
    dsp: dict[str, Any],
    controller: dict[str, Any],
    recorder: dict[str, Any],
    final: bool = False,
    parameters: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One ``/diagnostics`` record from the components' counters (``parameters``: the online
    parameter service's accepted/refused/unauthenticated counts, and ``failed`` when the
    controller failed on some, when it runs)."""
    lost = int(recorder.get("dropped", 0)) + int(recorder.get("encode_errors", 0))
    dsp_bad = bool(dsp.get("watchdog_tripped")) or int(controller.get("watchdog_trips", 0)) > 0
    misses = int(controller.get("deadline_misses", 0))
    status = [
        _rx_status("can_rx", can_rx, "frame(s)"),
        _rx_status("features", features, "message(s)"),
        _status(
            "dsp",
            ERROR if dsp_bad else OK,
            "watchdog tripped" if dsp_bad else ("armed" if dsp.get("torque_enabled") else "idle"),
            dsp,
        ),
        _status(
            "controller",
            WARN if misses else OK,
            f"{misses} deadline miss(es)" if misses else "on time",
            controller,
        ),
        _status(
            "recorder",
            ERROR if lost else OK,
            f"{lost} record(s) lost" if lost else "nothing lost",
            recorder,
        ),
    ]
    if parameters is not None:
        status.append(_parameters_status(parameters))
    return {
        "t_ns": int(t_ns),
        "tick": int(tick),
        "final": final,
        "level": max(s["level"] for s in status),
        "status": status,
    }


def with_run_end(
    record: dict[str, Any],
    planned_ticks: int | None,
    end_reason: str,
    judged: dict[str, Any] | None = None,
    stop_signal: str | None = None,
) -> dict[str, Any]:
    """The run's final record with how the run ended, so its log alone tells a run cut short
    (``tick`` < ``planned_ticks``, or an ``end_reason`` other than its duration) from a whole
    one (``hil info``), which signal stopped it (``stop_signal``, as the summary says), and with
    ``judged``: the counters of the run's verdict that are nowhere else in the log
    (``dsp_faults``, ``drive_ticks``, ``outages``: ``RunCounters.judged``)."""
    end = {"planned_ticks": planned_ticks, "end_reason": end_reason, "stop_signal": stop_signal}
    return {**record, **end, **(judged or {})}


def values_of(record: dict[str, Any], name: str) -> dict[str, Any]:
    """The key/values of component ``name`` in a diagnostics record ({} if absent)."""
    for s in record.get("status", []):
        if s.get("name") == name:
            return dict(s.get("values", {}))
    return {}
