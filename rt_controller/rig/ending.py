"""The summary of a run during which a process of the rig died (``hil up``, ``hil experiment``).

A killed controller prints no summary, a dead emulator or vision process ends the run early:
either way the supervisor still says what happened, from what is left:

* :class:`ProcessEnd`: which process, killed by which signal or exited with which status, and
  when the supervisor saw it;
* :func:`dsp_report`: the emulated DSP's own account (``hil emulator --json``): watchdog trips
  and how long after the last valid command the torque went off;
* :func:`log_contents`: the log's path, how many cycles it holds, whether it was finished;
* :func:`summary_after`: the run's summary with ``end_reason``, ``ended_by``, ``dsp``,
  ``log_contents`` and ``problems``; the counters are the controller's when it printed them,
  else those the log has.
"""

from __future__ import annotations

import json
import math
import re
import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rt_controller.errors import LogError
from rt_controller.runtime.counters import ENDED_FULL, run_problems, run_warnings

LOGGING_TO = re.compile(r"logging to (?P<path>\S.*?)\s*$", re.MULTILINE)
"""The controller's start-up line on stderr names its log (``hil controller: ... logging to
PATH``): the path of a run whose controller died before its summary."""
FROM_LOG = (
    "ticks", "J", "deadline_misses", "missed_periods", "stale_features", "f_final", "outages",
)  # fmt: skip
"""Counters of a killed controller's run, as :func:`~rt_controller.logtools.deadline_report.
summarize` reads them from its log."""


@dataclass(frozen=True)
class ProcessEnd:
    """A process of the rig that ended while the run went on."""

    name: str
    """``controller``, ``emulator``, ``vision`` or ``monitor``."""
    returncode: int
    """As :class:`subprocess.Popen` has it: negative for a signal."""
    at_ns: int
    """``time.monotonic_ns()`` when the supervisor saw it (the controller's log clock)."""
    unasked: bool = False
    """It ended while the run went on, the rig had not told it to stop: an exit status 0 is
    then an orderly stop on a signal from elsewhere (``kill``, a shutdown)."""
    stopped_because: str | None = None
    """Why the rig itself stopped it (e.g. its wall-clock budget ran out): its end is then the
    rig's stop, not an exit of its own, whatever its status (0 or SIGTERM: the stop)."""

    @property
    def signal_name(self) -> str | None:
        if self.returncode >= 0:
            return None
        try:
            return signal.Signals(-self.returncode).name
        except ValueError:
            return f"signal {-self.returncode}"

    @property
    def how(self) -> str:
        """``killed by SIGKILL``, ``exited with status 3``, or ``stopped by a signal the rig
        did not send (exit status 0)``: the stop SIGTERM or SIGINT asks for; ``stopped by the
        rig: WHY`` when the rig stopped it in order (:attr:`stopped_because`; SIGKILLed, it
        is ``killed by SIGKILL``)."""
        if self.stopped_because and self.returncode in (0, -signal.SIGTERM):  # the rig's stop
            return f"stopped by the rig: {self.stopped_because}"
        name = self.signal_name
        if name:
            return f"killed by {name}"
        if self.returncode == 0 and self.unasked:
            return "stopped by a signal the rig did not send (exit status 0)"
        return f"exited with status {self.returncode}"


def log_path_said(controller_stderr: str) -> Path | None:
    """The log path the controller announced on stderr (None: it died before saying)."""
    found = LOGGING_TO.findall(controller_stderr)
    return Path(found[0]) if found else None


def dsp_report(emulator_stdout: str) -> dict[str, Any]:
    """The DSP's watchdog account from the emulator's ``--json`` counters: trips, how long the
    torque stayed on after the last valid command (``torque_off_after_ms``), the scenario
    times of that command and of the trip, the drive state it ended in, and in lockstep the
    periods of the run it advanced with the held torque, no command within its reply timeout
    (``skipped_periods``; ``skipped_by_run`` for each run of a plan). ``reported`` False when
    the emulator printed no counters (it died itself)."""
    stats = None
    for line in emulator_stdout.splitlines():
        if line.startswith("{"):
            try:
                stats = json.loads(line)
            except json.JSONDecodeError:  # a line cut by a kill
                continue
    if not isinstance(stats, dict):
        return {"reported": False, "why": "the emulator printed no counters"}
    if stats.get("mode") == "cia402":
        return _drives_report(stats.get("drives") or [])
    return {
        "reported": True,
        "watchdog_trips": stats.get("watchdog_trips"),
        "torque_off_after_ms": stats.get("last_trip_latency_ms"),
        "last_command_s": stats.get("last_command_sim_s"),
        "torque_off_s": stats.get("last_trip_sim_s"),
        "watchdog_period_ms": stats.get("watchdog_period_ms"),
        "drive_state": stats.get("drive_state"),
        "fault_reason": stats.get("fault_reason"),
        "last_fault": stats.get("last_fault"),
        "skipped_periods": stats.get("skipped_periods", 0),
        "skipped_by_run": stats.get("skipped_by_run", []),
    }


def _drives_report(drives: list[dict[str, Any]]) -> dict[str, Any]:
    """The CiA 402 drives' account in the DSP's terms: a fault that took the torque away is a
    trip (SYNC loss and heartbeat loss are the drives' watchdogs), ``torque_off_after_ms`` the
    longest time from a drive's last SYNC to its torque off; each drive's own under ``drives``."""
    offs = [d["torque_off"] for d in drives if d.get("torque_off")]
    after = [o["after_last_sync_ms"] for o in offs if o.get("after_last_sync_ms") is not None]
    states = {d.get("state") for d in drives}
    return {
        "reported": True,
        "profile": "cia402",
        "watchdog_trips": len(offs),
        "torque_off_after_ms": max(after) if after else None,
        "drive_state": states.pop().lower() if len(states) == 1 else "mixed",
        "fault_reason": ", ".join(sorted({o["reason"] for o in offs})) or None,
        "emcys": {str(d.get("node_id")): d.get("emcys", []) for d in drives},
        "drives": {
            str(d.get("node_id")): {"state": d.get("state"), "torque_off": d.get("torque_off")}
            for d in drives
        },
    }


def dsp_words(dsp: dict[str, Any]) -> str:
    """The DSP's account in one line, for the table."""
    if not dsp.get("reported"):
        return str(dsp.get("why", "no report"))
    if dsp.get("profile") == "cia402":
        trips = dsp.get("watchdog_trips") or 0
        if not trips:
            return f"no drive fault; drives {dsp.get('drive_state')}"
        after = dsp.get("torque_off_after_ms")
        return (
            f"{trips} drive fault(s) ({dsp.get('fault_reason')}): torque off "
            + ("" if after is None else f"{after:.1f} ms after the last SYNC")
            + f"; drives {dsp.get('drive_state')}"
        )
    trips = dsp.get("watchdog_trips") or 0
    if not trips:
        return f"no watchdog trip; drive {dsp.get('drive_state')}"
    return (
        f"{trips} watchdog trip(s): torque off {dsp['torque_off_after_ms']:.1f} ms after the "
        f"last command (t = {dsp['torque_off_s']:.3f} s); drive {dsp.get('drive_state')}"
    )


def _read_log(path: Path | None, writer_pid: int | None = None) -> tuple[dict[str, Any], Any]:
    """What the log holds and the loaded log (None when it cannot be read, or when
    ``writer_pid``, this run's controller, did not write it: an earlier run's file at the
    path, which the controller had not replaced yet)."""
    if path is None:
        return {"path": None, "error": "the controller named no log before it died"}, None
    from rt_controller.logs import load

    try:
        run = load(path, raw=False)
    except LogError as exc:
        return {"path": str(path), "error": str(exc)}, None
    pid = run.info.get("pid")
    if writer_pid is not None and pid is not None and pid != str(writer_pid):
        why = f"an earlier run's (process {pid}), not replaced: the controller opened no log"
        return {"path": None, "error": f"no log of this run: {path} is {why}"}, None
    ticks = run.log.column("tick")
    n = run.log.n_cycles
    return {
        "path": str(path),
        "cycles": n,
        "finished": not run.truncated,
        "first_tick": int(ticks[0]) if ticks is not None and n else None,
        "last_tick": int(ticks[-1]) if ticks is not None and n else None,
    }, run


def log_contents(path: Path | None) -> dict[str, Any]:
    """The log at ``path``: cycles, finished (False: truncated), first and last tick; or the
    one-line reason it cannot be read."""
    return _read_log(path)[0]


def contents_words(contents: dict[str, Any]) -> str:
    """What the log holds in one line, for the table."""
    if "error" in contents:
        return str(contents["error"])
    state = "finished" if contents["finished"] else "TRUNCATED (the writer did not finish it)"
    return f"{contents['cycles']} cycles, {state}"


def end_words(summary: dict[str, Any]) -> str | None:
    """The run's ``end_reason`` for the table: ``stopped by SIGINT`` when the controller says
    which signal stopped it (its summary's ``stop_signal``), else as it is."""
    reason, by = summary.get("end_reason"), summary.get("stop_signal")
    return f"stopped by {by}" if reason == "stopped" and by else reason


def _tick_at(run: Any, at_ns: int | None) -> tuple[int | None, float | None]:
    """The log's tick at the monotonic time ``at_ns`` (None: its last) and its run time."""
    if run is None or not run.log.n_cycles:
        return None, None
    from rt_controller.logtools.deadline_report import time_axis

    ticks = run.log.column("tick")
    t, _ = time_axis(run.log)
    i = len(ticks) - 1
    t_ns = run.log.column("t_ns")
    if at_ns is not None and t_ns is not None:
        before = np.flatnonzero(np.asarray(t_ns, dtype=float) <= at_ns)
        i = int(before[-1]) if before.size else 0
    return int(ticks[i]), float(t[i])


def summary_after(
    end: ProcessEnd,
    summary: dict[str, Any] | None,
    log_path: Path | None,
    dsp: dict[str, Any],
    base: dict[str, Any],
    writer_pid: int | None = None,
) -> dict[str, Any]:
    """The run's summary after ``end``: the controller's ``summary`` (None: it printed none,
    its counters are then read from the log), ``base`` (what was run: clock, law, planned
    ticks) under it, with ``end_reason``, ``ended_by``, ``dsp``, ``log``, ``log_contents`` and
    ``problems`` filled in. ``writer_pid``: the controller's pid, so that a file at the log's
    path that another process wrote (an earlier run's) is never taken for this run's log."""
    out = {**base, **(summary or {})}
    if log_path is None and out.get("log"):
        log_path = Path(out["log"])
    contents, run = _read_log(log_path, writer_pid)
    if summary is None and run is not None:
        from rt_controller.logs.info import logged_summary
        from rt_controller.logtools.deadline_report import summarize

        report = summarize(run.log, max_list=0)
        out.update({k: report.get(k) for k in FROM_LOG})
        out["f_final_norm"] = report.get("f_final_norm")
        out.update(logged_summary(run))
    # a dying controller's own view is its last tick; another process's, the tick then
    tick, t = _tick_at(run, None if end.name == "controller" else end.at_ns)
    when = "before its first tick" if tick is None else f"at tick {tick} (t = {t:.3f} s)"
    own = (summary or {}).get("end_reason")
    out["end_reason"] = f"{end.name} {end.how} {when}"
    if own and own not in ENDED_FULL:  # the controller's own view of it, e.g. a silent DSP
        out["end_reason"] += f"; the controller: {own}"
    out["ended_by"] = {
        "process": end.name,
        "signal": end.signal_name,
        "exit_code": None if end.returncode < 0 else end.returncode,
        "tick": tick,
        "time_s": None if t is None or math.isnan(t) else t,
    }
    out["dsp"] = dsp
    if summary is None:
        _count_dsp_trips(out, dsp)
    out["log"] = contents["path"]
    out["log_contents"] = contents
    problems = run_problems(out)
    if not any(out["end_reason"] in p for p in problems):
        problems.insert(0, f"the run ended: {out['end_reason']}")
    if "error" in contents:
        said = contents["error"]
        problems.append(said if said.startswith("no log") else f"the log cannot be read: {said}")
    out["problems"] = problems
    if summary is None:
        out["warnings"] = run_warnings(out)
    out.setdefault("warnings", [])
    if end.stopped_because:  # the rig's own stop (the problem says why), not someone's signal
        out["warnings"] = [w for w in out["warnings"] if "stopped by SIG" not in w]
    return out


def _count_dsp_trips(out: dict[str, Any], dsp: dict[str, Any]) -> None:
    """The DSP's watchdog trips into the summary's counters where the controller counted fewer:
    a dead controller's last record cannot count the trip its death caused (the safe stop)."""
    trips = int(dsp.get("watchdog_trips") or 0) if dsp.get("reported") else 0
    if trips <= int(out.get("watchdog_trips") or 0):
        return
    out["watchdog_trips"] = trips  # a cia402 drive's: SYNC or heartbeat lost, by its reason
    out["dsp_faults"] = {
        **(out.get("dsp_faults") or {}),
        dsp.get("fault_reason") or "watchdog": trips,
    }


def refused_to_start(end: ProcessEnd, summary: dict[str, Any]) -> bool:
    """Whether ``end`` is a process that refused to start: exit status 2 (the ``hil`` commands'
    bad-usage status: a CAN interface that does not exist, no vision process on the zenoh
    endpoint, ...) before the controller ran a tick. That is reported as an error (exit 2), not
    as a run that ended short."""
    return end.returncode == 2 and not summary.get("ticks")


def stopped_from_outside(summary: dict[str, Any]) -> str:
    """The problem of a run whose controller was stopped by a signal the supervisor did not
    send (``kill``, a shutdown): a stop the supervisor did not ask for is an end like a
    death, not the run's duration. The signal is named when the controller's summary says it
    (``stop_signal``)."""
    ticks, planned = summary.get("ticks"), summary.get("planned_ticks")
    when = f"after {ticks} of {planned} ticks" if planned else f"after {ticks} ticks"
    by = f" ({summary['stop_signal']})" if summary.get("stop_signal") else ""
    return f"the controller was stopped by a signal the rig did not send, {when}{by}"
