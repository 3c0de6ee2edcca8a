"""One counters dataclass for a controller run: the summary, the ``/diagnostics`` record's
``controller`` block and :func:`run_problems` all read it, so they always agree."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rt_controller.runtime import diagnostics
from rt_controller.runtime.host_steal import DISTURBED_STEAL_PERCENT
from rt_controller.sample_stats import percentile

ENDED_FULL = ("duration", "stopped")
"""End reasons of a run that is not short for a fault: its duration reached, or told to stop."""


@dataclass
class RunCounters:
    """Running totals of one run."""

    ticks: int = 0
    J: float = 0.0
    deadline_misses: int = 0
    missed_periods: int = 0
    stale_features: int = 0
    stale_states: int = 0
    fallbacks: int = 0
    watchdog_trips: int = 0
    late_states: int = 0
    """Realtime ticks whose period's joint state had not arrived at the release: they used the
    previous period's state (its age is compensated, ``controller.predict_state``)."""
    drive_ticks: Counter[str] = field(default_factory=Counter)
    """Ticks run while the DSP was not in *operation enabled*, by mode (no law ran in them)."""
    dsp_faults: Counter[str] = field(default_factory=Counter)
    """Faults the DSP reported, by reason (``watchdog``, ``position_limit``, ...)."""
    rearms: int = 0
    """Times the controller re-armed the DSP by its re-arm policy."""
    arming_ticks: int = 0
    """Realtime releases between ENABLE and *operation enabled*: each sent a zero torque
    (the command stream is cyclic from ENABLE on); no law ran, they are not in ``ticks``."""
    stopped_before_arming: bool = False
    """A stop request arrived during start-up: the DSP was never armed, no tick ran."""
    host_steal_percent: float | None = None
    """Realtime: the hypervisor's steal over the law ticks, in percent of the CPUs' time
    (None in lockstep, or where ``/proc/stat`` has no steal)."""
    spin_s: float = 0.0
    """Realtime: seconds spent busy-waiting before deadlines (``controller.spin_us``)."""
    rehearsals: int = 0
    """Realtime: releases before which the last tick was rehearsed (``controller.rehearse``)."""
    f_final: list[float] = field(default_factory=lambda: [math.nan, math.nan])
    f_first: list[float] = field(default_factory=lambda: [math.nan, math.nan])
    """The features the first law tick saw (the scenario's f(0))."""
    jump_seen_s: float | None = None
    """Run time of the first tick whose features stepped by more than half the scenario's
    target jump (None: no such step, or the scenario has no disturbance)."""
    planned_ticks: int | None = None
    """Ticks the duration asks for (None: no duration, run until stopped)."""
    end_reason: str = "duration"
    """Why the loop ended: ``duration``, ``stopped`` (a stop request) or a short phrase (the
    DSP fell silent, ...); anything but :data:`ENDED_FULL` before ``planned_ticks`` makes the
    run not clean."""
    solve_us: list[float] = field(default_factory=list)
    lateness_us: list[float] = field(default_factory=list)
    cycle_us: list[float] = field(default_factory=list)

    def controller_block(self) -> dict[str, int]:
        """The counters of the ``/diagnostics`` record's ``controller`` component."""
        names = (
            "ticks",
            "deadline_misses",
            "missed_periods",
            "stale_features",
            "stale_states",
            "late_states",
            "fallbacks",
            "watchdog_trips",
        )
        return {n: getattr(self, n) for n in names}

    def as_dict(self) -> dict[str, Any]:
        """The summary's counters (sample lists as median and p99)."""
        pct = percentile
        return {
            **self.controller_block(),
            "J": self.J,
            "f_final": self.f_final,
            "f_final_norm": float(np.hypot(*self.f_final)),
            "f_first": self.f_first,
            "jump_seen_s": self.jump_seen_s,
            "planned_ticks": self.planned_ticks,
            "end_reason": self.end_reason,
            "drive_ticks": dict(self.drive_ticks),
            "dsp_faults": dict(self.dsp_faults),
            "rearms": self.rearms,
            "arming_ticks": self.arming_ticks,
            "spin_s": self.spin_s,
            "host_steal_percent": self.host_steal_percent,
            "rehearsals": self.rehearsals,
            "stopped_before_arming": self.stopped_before_arming,
            "solve_us_median": pct(self.solve_us, 50),
            "solve_us_p99": pct(self.solve_us, 99),
            "lateness_us_p99": pct(self.lateness_us, 99),
            "cycle_us_p99": pct(self.cycle_us, 99),
        }


def run_problems(summary: dict[str, Any]) -> list[str]:
    """Why a finished run cannot be trusted, one short phrase each (empty: a clean run): it
    ended short for another reason than a stop request, lost or could not encode log records,
    tripped the DSP's watchdog, saw a DSP fault, received a stream of frames or messages that
    failed authentication (:data:`diagnostics.AUTH_FAULT_MIN` or more), or ran ticks without
    an enabled DSP. ``summary``: a run's summary, also as rebuilt from a log.
    """
    out: list[str] = []
    planned, ticks = summary.get("planned_ticks"), int(summary.get("ticks") or 0)
    reason = summary.get("end_reason") or "duration"
    if planned is not None and ticks < planned and reason not in ENDED_FULL:
        out.append(f"the run ended after {ticks} of {planned} ticks: {reason}")
    rec = summary.get("recorder") or {}
    lost = int(rec.get("dropped", 0)) + int(rec.get("pending", 0))
    if lost:
        out.append(f"{lost} log record(s) lost")
    if rec.get("encode_errors"):
        out.append(f"{rec['encode_errors']} log record(s) could not be encoded")
    if summary.get("log_error"):
        out.append(f"the MCAP log is incomplete: {summary['log_error']}")
    if summary.get("watchdog_trips"):
        out.append(f"{summary['watchdog_trips']} DSP watchdog trip(s)")
    faults = {k: v for k, v in (summary.get("dsp_faults") or {}).items() if k != "watchdog"}
    if faults:
        out.append("DSP fault(s): " + ", ".join(f"{k} {v}" for k, v in faults.items()))
    rejections = summary.get("rejections") or {}
    for name, what in (("can_rx", "CAN frame(s)"), ("features", "vision message(s)")):
        auth = diagnostics.auth_failures(rejections.get(name) or {})
        if sum(auth.values()) >= diagnostics.AUTH_FAULT_MIN:
            reasons = ", ".join(f"{k} {v}" for k, v in auth.items() if v)
            out.append(f"{sum(auth.values())} {what} failed authentication ({reasons})")
    dsp_rejected = int(rejections.get("dsp_rejected_frames") or 0)
    if dsp_rejected >= diagnostics.AUTH_FAULT_MIN:
        out.append(f"the DSP rejected {dsp_rejected} frame(s) (DspStatus.RejectedFrames)")
    drive = summary.get("drive_ticks") or {}
    if drive:
        what = ", ".join(f"{k} {v}" for k, v in drive.items())
        out.append(f"{sum(drive.values())} tick(s) without an enabled DSP ({what})")
    return out


def run_warnings(summary: dict[str, Any]) -> list[str]:
    """What makes a clean run's J differ from the paper's experiment, one phrase each (empty:
    nothing): a realtime run during which the hypervisor took
    :data:`~rt_controller.runtime.host_steal.DISTURBED_STEAL_PERCENT` or more of the CPUs'
    time. The run is still clean (its exit status says so); its J is not the lockstep one's.
    """
    steal = summary.get("host_steal_percent")
    if summary.get("clock") != "realtime" or steal is None or steal < DISTURBED_STEAL_PERCENT:
        return []
    late = summary.get("late_states")
    return [
        f"the hypervisor took {steal:.0f} % of the CPUs' time during the run ({late} tick(s) "
        f"on a late joint state): the realtime J can differ from the lockstep experiment's "
        f"by more than 1 %; `hil up --lockstep` runs it deterministically"
    ]
