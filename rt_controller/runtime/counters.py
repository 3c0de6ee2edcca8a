"""One counters dataclass for a controller run: the summary, the ``/diagnostics`` record's
``controller`` block and :func:`run_problems` all read it, so they always agree."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from hal.durations import Durations
from rt_controller.runtime import diagnostics
from rt_controller.runtime.host_steal import DISTURBED_STEAL_PERCENT

ENDED_FULL = ("duration", "stopped")
"""End reasons of a run that is not short for a fault: its duration reached, or told to stop."""
OUTAGES_LISTED = 10
"""Camera outages named one by one (warnings, the summary); the rest are counted."""


@dataclass
class Outage:
    """A stretch of ticks in a row on stale or invalid features."""

    start_tick: int
    start_s: float
    """Run time of its first tick."""
    ticks: int = 0
    end_s: float = 0.0
    """Run time of its last tick."""

    def as_dict(self, period_s: float) -> dict[str, Any]:
        return {
            "start_tick": self.start_tick,
            "start_s": self.start_s,
            "ticks": self.ticks,
            "s": self.end_s - self.start_s + period_s,
        }


@dataclass
class OutageTracker:
    """Camera outages: stretches of ticks that ran on stale or invalid features (the law held
    or used old image features), found tick by tick in the loop or from a log's ``f_stale`` and
    ``f_valid`` columns (:func:`find_outages`), so ``hil up`` and ``hil report`` agree.

    A stretch longer than ``warn_periods`` ticks is an outage (a warning each); more than
    ``max_share`` of all ticks on such features makes the run not clean (:func:`run_problems`).
    """

    warn_periods: int = 5
    max_share: float = 0.25
    ticks: int = 0
    bad_ticks: int = 0
    """Ticks on stale or invalid features, in any stretch."""
    count: int = 0
    """Outages closed so far (stretches longer than ``warn_periods``)."""
    listed: list[Outage] = field(default_factory=list)
    """The first :data:`OUTAGES_LISTED` outages."""
    longest: Outage | None = None
    """The longest stretch closed so far (an outage or not)."""
    current: Outage | None = None
    """The stretch going on at the last tick (None: that tick had good features)."""

    @classmethod
    def from_config(cls, controller: Any) -> OutageTracker:
        """The thresholds of ``cfg.controller`` (``outage_warn_periods``, ``outage_max_share``)."""
        return cls(int(controller.outage_warn_periods), float(controller.outage_max_share))

    def note(self, tick: int, t_s: float, bad: bool) -> None:
        """One tick: ``bad`` when it ran on stale or invalid features."""
        self.ticks += 1
        if bad:
            self.bad_ticks += 1
            if self.current is None:
                self.current = Outage(tick, t_s)
            self.current.ticks += 1
            self.current.end_s = t_s
        elif self.current is not None:
            self._close(self.current)
            self.current = None

    def _close(self, stretch: Outage) -> None:
        if self.longest is None or stretch.ticks > self.longest.ticks:
            self.longest = stretch
        if stretch.ticks > self.warn_periods:
            self.count += 1
            if len(self.listed) < OUTAGES_LISTED:
                self.listed.append(stretch)

    def as_dict(self, period_s: float) -> dict[str, Any]:
        """The summary's ``outages`` block, the open stretch counted as ended (on a copy: the
        run may go on)."""
        done = replace(self, listed=list(self.listed))
        if self.current is not None:
            done._close(self.current)
        return {
            "warn_periods": done.warn_periods,
            "max_share": done.max_share,
            "count": done.count,
            "listed": [o.as_dict(period_s) for o in done.listed],
            "longest": None if done.longest is None else done.longest.as_dict(period_s),
            "longest_ticks": 0 if done.longest is None else done.longest.ticks,
            "ticks_on_stale_or_invalid": done.bad_ticks,
            "share": done.bad_ticks / done.ticks if done.ticks else 0.0,
        }


def find_outages(
    ticks: np.ndarray,
    t_s: np.ndarray,
    bad: np.ndarray,
    warn_periods: int,
    max_share: float,
    period_s: float,
) -> dict[str, Any]:
    """The ``outages`` block of a recorded run: ``bad[i]`` when tick ``ticks[i]`` (at run time
    ``t_s[i]``) ran on stale or invalid features."""
    tracker = OutageTracker(warn_periods, max_share)
    for k, t, b in zip(ticks, t_s, bad, strict=True):
        tracker.note(int(k), float(t), bool(b))
    return tracker.as_dict(period_s)


def outage_words(o: dict[str, Any]) -> str:
    """One outage (an entry of the ``outages`` block) in words."""
    return (
        f"from tick {o['start_tick']} (t = {o['start_s']:.3f} s): {o['ticks']} ticks "
        f"({o['s']:.2f} s)"
    )


DIAGNOSTICS = {"diagnostics": True}
"""Metadata of a :class:`RunCounters` field that is also in the ``/diagnostics`` record."""


@dataclass
class RunCounters:
    """Running totals of one run. Every field is in the summary (:meth:`as_dict`); those
    marked :data:`DIAGNOSTICS` also in the ``/diagnostics`` record (:meth:`controller_block`)."""

    ticks: int = field(default=0, metadata=DIAGNOSTICS)
    deadline_misses: int = field(default=0, metadata=DIAGNOSTICS)
    missed_periods: int = field(default=0, metadata=DIAGNOSTICS)
    stale_features: int = field(default=0, metadata=DIAGNOSTICS)
    stale_states: int = field(default=0, metadata=DIAGNOSTICS)
    late_states: int = field(default=0, metadata=DIAGNOSTICS)
    """Realtime ticks whose period's joint state had not arrived at the release: they used the
    previous period's state (its age is compensated, ``controller.predict_state``)."""
    fallbacks: int = field(default=0, metadata=DIAGNOSTICS)
    watchdog_trips: int = field(default=0, metadata=DIAGNOSTICS)
    J: float = 0.0
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
    DSP fell silent, ...); anything but :data:`ENDED_FULL` makes the run not clean, and a stop
    before ``planned_ticks`` is a warning."""
    solve: Durations = field(default_factory=Durations)
    """Per-tick times for the summary's percentiles, in fixed memory however long the run:
    the rule's decide (read to solve), the wake-up's lateness and the cycle (wake to write)."""
    lateness: Durations = field(default_factory=Durations)
    cycle: Durations = field(default_factory=Durations)
    outages: OutageTracker = field(default_factory=OutageTracker)
    """Camera outages (thresholds: ``controller.outage_warn_periods``, ``outage_max_share``)."""
    period_s: float = field(default=0.02, metadata={"summary": False})
    """The control period (the length in seconds of an outage's last tick)."""

    def controller_block(self) -> dict[str, int]:
        """The counters of the ``/diagnostics`` record's ``controller`` component."""
        return {
            f.name: getattr(self, f.name) for f in fields(self) if f.metadata.get("diagnostics")
        }

    def judged(self) -> dict[str, Any]:
        """What :func:`run_problems` judges that only the loop counts: the DSP's faults, the
        ticks without an enabled DSP and the camera outages. The run's final ``/diagnostics``
        record carries them (:func:`diagnostics.with_run_end`), so a log is judged as its run
        was (``hil info``, ``hil report``). Taken once, at the end of the run."""
        return {
            "dsp_faults": dict(self.dsp_faults),
            "drive_ticks": dict(self.drive_ticks),
            "outages": self.outages.as_dict(self.period_s),
        }

    def as_dict(self) -> dict[str, Any]:
        """The summary's counters: the fields (counts by kind as plain dicts), the per-tick
        times as median and p99, the outages as their block."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.metadata.get("summary", True) and not isinstance(value, Durations | OutageTracker):
                out[f.name] = dict(value) if isinstance(value, Counter) else value
        out.update(
            f_final_norm=float(np.hypot(*self.f_final)),
            solve_us_median=_us(self.solve, 50),
            solve_us_p99=_us(self.solve, 99),
            lateness_us_p99=_us(self.lateness, 99),
            cycle_us_p99=_us(self.cycle, 99),
            outages=self.outages.as_dict(self.period_s),
        )
        return out


def _us(durations: Durations, q: float) -> float:
    """The ``q``-th percentile in us; NaN before the first tick."""
    return durations.percentile_us(q) if len(durations) else math.nan


def _int0(value: Any) -> int:
    """A counter read from a summary or a log: 0 where absent or not a number."""
    try:
        return int(value or 0)
    except (TypeError, ValueError):
        return 0


def _image_count(summary: dict[str, Any], name: str) -> int:
    """A camera-image counter of the controller's feature link (:class:`~rt_controller.runtime.
    feature_link.FeatureLink`) from a summary: ``images_rejected`` (refused for the log) or
    ``images_missing`` (announced by their features, not in the log: a realtime link may drop
    one; a lockstep one waits, so there one missing means the log is incomplete)."""
    rejections = summary.get("rejections") or {}
    return int((rejections.get("features") or {}).get(name, 0))


def _other_sender(can_rx: dict[str, Any]) -> str:
    """Why the DSP rejected frames when another node sent this controller's own ids
    (``ignored``): a second controller driving the same DSP interleaves its commands."""
    ignored = _int0(can_rx.get("ignored"))
    if not ignored:
        return ""
    return (
        f": {ignored} frame(s) with this controller's own ids from another node "
        "(another controller on this bus?)"
    )


def _short(summary: dict[str, Any]) -> bool:
    """Whether the run had fewer ticks than its duration asked for."""
    planned = summary.get("planned_ticks")
    return planned is not None and int(summary.get("ticks") or 0) < planned


def _ended_after(summary: dict[str, Any]) -> str:
    """``the run ended after 60 of 250 ticks`` (``after 60 ticks`` without a duration)."""
    planned, ticks = summary.get("planned_ticks"), int(summary.get("ticks") or 0)
    return f"the run ended after {ticks}{'' if planned is None else f' of {planned}'} ticks"


def run_problems(summary: dict[str, Any]) -> list[str]:
    """Why a finished run cannot be trusted, one short phrase each (empty: a clean run): it ended
    for another reason than its duration or a stop request, lost or could not encode log
    records or camera images (in lockstep, also an announced image that never came), lost
    vision messages or images to an exception in the feature link's zenoh callbacks (the
    session's ``callback_errors``), tripped the DSP's watchdog, saw a DSP fault, received a
    stream of frames or messages that failed authentication (:data:`diagnostics.AUTH_FAULT_MIN`
    or more), ran ticks without an enabled DSP, or (lockstep, as the emulator's report in
    ``dsp`` says) had periods the DSP advanced without their command, which makes it another
    run than the deterministic one. ``summary``: a run's summary, also as rebuilt from a log.
    """
    out: list[str] = []
    reason = summary.get("end_reason") or "duration"
    if reason not in ENDED_FULL:  # "duration" may run fewer ticks: periods missed are skipped
        out.append(f"{_ended_after(summary)}: {reason}")
    rec = summary.get("recorder") or {}
    lost = int(rec.get("dropped", 0)) + int(rec.get("pending", 0))  # pending: an older log
    if lost:
        out.append(f"{lost} log record(s) lost")
    if rec.get("encode_errors"):
        out.append(f"{rec['encode_errors']} log record(s) could not be encoded")
    if rec.get("image_errors"):
        out.append(f"{rec['image_errors']} camera image(s) could not be written to the log")
    if summary.get("log_error"):
        out.append(f"the MCAP log is incomplete: {summary['log_error']}")
    if summary.get("watchdog_trips"):
        out.append(f"{summary['watchdog_trips']} DSP watchdog trip(s)")
    unanswered = (summary.get("dsp") or {}).get("skipped_periods")
    if unanswered and summary.get("clock") == "lockstep":
        out.append(
            f"the DSP advanced {unanswered} lockstep period(s) with the held torque (no command "
            f"within dsp.lockstep_reply_timeout_s): not the deterministic run"
        )
    faults = {k: v for k, v in (summary.get("dsp_faults") or {}).items() if k != "watchdog"}
    if faults:
        out.append("DSP fault(s): " + ", ".join(f"{k} {v}" for k, v in faults.items()))
    rejections = summary.get("rejections") or {}
    for name, what in (("can_rx", "CAN frame(s)"), ("features", "vision message(s)")):
        auth = diagnostics.auth_failures(rejections.get(name) or {})
        if sum(auth.values()) >= diagnostics.AUTH_FAULT_MIN:
            reasons = ", ".join(f"{k} {v}" for k, v in auth.items() if v)
            out.append(f"{sum(auth.values())} {what} failed authentication ({reasons})")
    images = _image_count(summary, "images_rejected")
    if images >= diagnostics.AUTH_FAULT_MIN:
        out.append(f"{images} camera image(s) refused for the log (not authentic or malformed)")
    missing = _image_count(summary, "images_missing")
    if missing and summary.get("clock") == "lockstep":
        out.append(f"{missing} camera image(s) announced by their features are not in the log")
    failed = _int0((rejections.get("features") or {}).get("callback_errors"))
    if failed:
        out.append(
            f"{failed} feature-link callback error(s): vision message(s) or camera image(s) "
            "lost to an exception in a zenoh callback (a bug)"
        )
    dsp_rejected = int(rejections.get("dsp_rejected_frames") or 0)
    if dsp_rejected >= diagnostics.AUTH_FAULT_MIN:
        out.append(
            f"the DSP rejected {dsp_rejected} frame(s) (DspStatus.RejectedFrames)"
            + _other_sender(rejections.get("can_rx") or {})
        )
    drive = summary.get("drive_ticks") or {}
    if drive:
        what = ", ".join(f"{k} {v}" for k, v in drive.items())
        out.append(f"{sum(drive.values())} tick(s) without an enabled DSP ({what})")
    outages = summary.get("outages") or {}
    if outages.get("share", 0.0) > outages.get("max_share", 1.0):
        longest = outages["longest"]
        out.append(
            f"{outages['ticks_on_stale_or_invalid']} tick(s) ({outages['share']:.0%} of the run) "
            f"on stale or invalid features, more than controller.outage_max_share "
            f"({outages['max_share']:.0%}); the longest camera outage {outage_words(longest)}"
        )
    return out


def outage_warnings(outages: dict[str, Any]) -> list[str]:
    """One warning per camera outage of an ``outages`` block (at most
    :data:`OUTAGES_LISTED`, then how many more), the longest marked."""
    listed, count = outages.get("listed") or [], int(outages.get("count") or 0)
    longest = outages.get("longest")
    out = []
    for o in listed:
        mark = " (the longest)" if count > 1 and o == longest else ""
        out.append(
            f"camera outage {outage_words(o)} on stale or invalid features{mark}: "
            f"the law held or used old image features"
        )
    if count > len(listed):
        out.append(
            f"{count - len(listed)} more camera outage(s); the longest {outage_words(longest)}"
        )
    return out


def parameter_warnings(counts: dict[str, Any]) -> list[str]:
    """The warnings of the parameter service's counts (the ``parameters`` component of
    ``/diagnostics``): requests refused as unauthenticated, and requests the controller failed
    on (``failed``: only counted, so the warning names no request)."""
    out = []
    rogue, failed = _int0(counts.get("unauthenticated")), _int0(counts.get("failed"))
    if rogue:
        out.append(
            f"{rogue} unauthenticated parameter request(s) refused (wrong key, replayed, "
            "malformed or stale `hil param set`; none applied)"
        )
    if failed:
        out.append(
            f"{failed} parameter request(s) failed in the controller, refused or unanswered (a "
            "fault of the controller's, not the request's; it logged why the first failed)"
        )
    return out


def run_warnings(summary: dict[str, Any]) -> list[str]:
    """What makes a clean run's J differ from the paper's experiment, one phrase each (empty:
    nothing): a stop request before the run's duration (its J is of fewer ticks), camera
    outages (:func:`outage_warnings`), scene drawings or live records the
    recorder could not make (the cycles themselves are logged), a few camera images refused for
    the log (a stream of them is a problem), parameter requests refused as unauthenticated
    (none was applied, but someone sent them) or that the controller failed on
    (:func:`parameter_warnings`), and a realtime run during which the hypervisor took
    :data:`~rt_controller.runtime.host_steal.DISTURBED_STEAL_PERCENT` or more of the CPUs'
    time. The run is still clean (its exit status says so); its J is not the lockstep one's.
    """
    out = outage_warnings(summary.get("outages") or {})
    if summary.get("end_reason") == "stopped" and _short(summary):
        by = summary.get("stop_signal")
        out.append(f"{_ended_after(summary)}: stopped{f' by {by}' if by else ''}")
    rec = summary.get("recorder") or {}
    if rec.get("scene_errors"):
        out.append(f"{rec['scene_errors']} cycle(s) without their 3D scene in the log")
    if rec.get("live_errors"):
        out.append(f"{rec['live_errors']} record(s) did not reach the live view")
    images = _image_count(summary, "images_rejected")
    if 0 < images < diagnostics.AUTH_FAULT_MIN:
        out.append(f"{images} camera image(s) refused for the log (not authentic or malformed)")
    missing = _image_count(summary, "images_missing")
    if missing and summary.get("clock") != "lockstep":
        out.append(f"{missing} camera image(s) announced by their features are not in the log")
    out += parameter_warnings(summary.get("parameters") or {})
    steal = summary.get("host_steal_percent")
    if summary.get("clock") != "realtime" or steal is None or steal < DISTURBED_STEAL_PERCENT:
        return out
    late = summary.get("late_states")
    out.append(
        f"the hypervisor took {steal:.0f} % of the CPUs' time during the run ({late} tick(s) "
        f"on a late joint state): the realtime J can differ from the lockstep experiment's "
        f"by more than 1 %; `hil up --lockstep` runs it deterministically"
    )
    return out
