"""The controller daemon: a hard-cadence loop around the control law, with the rig's I/O.

Each tick: read the latest joint state (CAN) and image features (zenoh) with their ages, run the
law, compute tau by eq. (11), send it, and queue the cycle for the MCAP recorder. Two clock modes:
``realtime`` (absolute monotonic deadlines) and ``lockstep`` (one tick per DSP ``Sync`` frame,
waiting for the features that answer the same period).

Safety: stale features put the loop in *hold* (tau = -2 R dq, a pure joint damper; no image term,
so nothing stale or NaN reaches the amplifiers) and the law is re-initialised when they return;
a silent DSP sends zero torque and counts the tick as ``state_stale``.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hal.config import RigConfig
from hal.drive_state import MODE_ENABLED, MODE_NO_STATUS, DriveEvent, DriveMonitor, FaultReason
from hal.errors import HalStopped, HalTimeoutError
from hal.joint_client import JointClient
from hal.secoc import rig_key
from hal.vision_codec import FeatureDecoder, feature_age_ns
from hal.zenoh_session import KEY_FEATURES, open_session
from rt_controller.control.controller import Controller, warm_up
from rt_controller.errors import ControllerError
from rt_controller.runtime import diagnostics
from rt_controller.runtime.cadence import Cadence, MonotonicClock
from rt_controller.runtime.cycle_record import Timing, cycle_record, decision_fields, vec2
from rt_controller.runtime.realtime import GcPaused, apply_realtime
from rt_controller.runtime.recorder import CycleRecorder
from rt_controller.sample_stats import percentile

STARTUP_TIMEOUT_S = 20.0
"""How long the daemon waits for the first joint state and features before giving up."""
LOCKSTEP_SYNC_TIMEOUT_S = 2.0
"""Lockstep: without a Sync for this long the emulator is taken to have finished."""
LOCKSTEP_FEATURE_TIMEOUT_S = 1.0
ENABLE_TIMEOUT_S = 5.0
"""How long the daemon waits for the DSP to report *operation enabled* after ENABLE."""


@dataclass
class DaemonOptions:
    """How one daemon run is wired."""

    can: str | None = None
    lockstep: bool = False
    duration_s: float = 0.0
    """0 = until stopped (realtime) or until the Sync frames stop (lockstep)."""
    log_path: Path | None = None
    zenoh_endpoint: str | None = None
    zenoh_config: str | None = None
    realtime_settings: bool = True
    record_raw: bool = True
    """Also record every CAN frame and vision payload as received."""


@dataclass
class RunStats:
    """Running totals of a daemon run (the summary ``hil up`` prints)."""

    ticks: int = 0
    J: float = 0.0
    deadline_misses: int = 0
    missed_periods: int = 0
    stale_features: int = 0
    stale_states: int = 0
    fallbacks: int = 0
    watchdog_trips: int = 0
    drive_ticks: dict[str, int] = field(default_factory=dict)
    """Ticks run while the DSP was not in *operation enabled*, by mode (no law ran in them)."""
    dsp_faults: dict[str, int] = field(default_factory=dict)
    """Faults the DSP reported, by reason (``watchdog``, ``position_limit``, ...)."""
    rearms: int = 0
    """Times the controller re-armed the DSP by its re-arm policy."""
    stopped_before_arming: bool = False
    """A stop request arrived during start-up: the DSP was never armed, no tick ran."""
    f_final: list[float] = field(default_factory=lambda: [math.nan, math.nan])
    solve_us: list[float] = field(default_factory=list)
    lateness_us: list[float] = field(default_factory=list)
    cycle_us: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        pct = percentile
        return {
            "ticks": self.ticks,
            "J": self.J,
            "f_final": self.f_final,
            "f_final_norm": float(np.hypot(*self.f_final)),
            "deadline_misses": self.deadline_misses,
            "missed_periods": self.missed_periods,
            "stale_features": self.stale_features,
            "stale_states": self.stale_states,
            "fallbacks": self.fallbacks,
            "watchdog_trips": self.watchdog_trips,
            "drive_ticks": dict(self.drive_ticks),
            "dsp_faults": dict(self.dsp_faults),
            "rearms": self.rearms,
            "stopped_before_arming": self.stopped_before_arming,
            "solve_us_median": pct(self.solve_us, 50),
            "solve_us_p99": pct(self.solve_us, 99),
            "lateness_us_p99": pct(self.lateness_us, 99),
            "cycle_us_p99": pct(self.cycle_us, 99),
        }


def run_problems(summary: dict[str, Any]) -> list[str]:
    """Why a finished run cannot be trusted, one short phrase each (empty: a clean run).

    A run is not clean when it lost log records, tripped the DSP's watchdog, saw the DSP
    fault, received a stream of frames or messages that failed authentication (another sender
    on the rig's bus or zenoh: :data:`diagnostics.AUTH_FAULT_MIN` or more), or ran ticks without
    an enabled DSP (disarmed, restarted, silent); the commands exit non-zero and print these on
    one line.
    """
    out: list[str] = []
    rec = summary.get("recorder") or {}
    lost = int(rec.get("dropped", 0)) + int(rec.get("pending", 0))
    if lost:
        out.append(f"{lost} log record(s) lost")
    if rec.get("encode_errors"):
        out.append(f"{rec['encode_errors']} log record(s) could not be encoded")
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


def default_log_path(cfg: RigConfig, law: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path(cfg.controller.log_dir) / f"run-{stamp}-{law}.mcap"


class ControllerDaemon:
    """Owns the law, the DSP client, the feature subscriber and the recorder for one run."""

    def __init__(self, cfg: RigConfig, options: DaemonOptions, stop: threading.Event) -> None:
        self.cfg = cfg
        self.opts = options
        self.stop = stop
        self._diag_every = max(1, round(cfg.rates.control_hz))
        self._final_diagnostics: dict[str, Any] | None = None
        self.controller = Controller(cfg)
        self.model = self.controller.model
        self.period_ns = cfg.rates.control_period_ns
        self.stats = RunStats()
        self.log_path = options.log_path or default_log_path(cfg, cfg.controller.law)
        self.drive = DriveMonitor()
        self._status_limit_s = 3.0 / cfg.rates.status_hz
        """Realtime: a DspStatus older than three status periods means the DSP went silent
        (lockstep needs no such limit: without a live DSP there is no Sync and no tick)."""
        # Lockstep: the DSP announces the state with every Sync, so its wall-clock age only
        # reflects how long this tick waited (for features); a silent DSP ends the run instead.
        self._state_limit_s = (
            LOCKSTEP_SYNC_TIMEOUT_S + LOCKSTEP_FEATURE_TIMEOUT_S
            if options.lockstep
            else cfg.controller.state_timeout_s
        )
        self.features = FeatureDecoder.from_config(cfg.controller, key=rig_key(cfg))

    # --- wiring -----------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        """Run until stopped; returns the summary. The recorder is finished on every exit."""
        cfg, opts = self.cfg, self.opts
        rec = CycleRecorder(
            self.log_path,
            cfg,
            run_info={
                "clock": "lockstep" if opts.lockstep else "realtime",
                "can": opts.can or cfg.transport.can,
                "zenoh": opts.zenoh_config or opts.zenoh_endpoint or cfg.transport.zenoh_endpoint,
            },
        )
        hooks: dict[str, Any] = {}
        if opts.record_raw:
            hooks = {
                "frame_hook": lambda m: rec.record_can(m, time.monotonic_ns(), "rx"),
                "tx_hook": lambda m: rec.record_can(m, time.monotonic_ns(), "tx"),
            }
        try:
            # The bus first: a bad --can is reported at once, not after waiting for zenoh.
            with JointClient.open(opts.can, cfg, **hooks) as dsp:
                try:
                    session = open_session(
                        cfg,
                        listen=False,
                        endpoint=opts.zenoh_endpoint,
                        config_file=opts.zenoh_config,
                        stop_event=self.stop,
                    )
                except HalStopped:
                    self.stats.stopped_before_arming = True
                    return self._summary(rec)
                try:
                    session.subscribe(KEY_FEATURES, self._on_features(rec))
                    self._loop(dsp, rec)
                finally:
                    session.close()
        finally:
            rec.close()
        return self._summary(rec)

    def _summary(self, rec: CycleRecorder) -> dict[str, Any]:
        rec.close()
        out = self.stats.as_dict()
        out.update(law=self.controller.law.name, log=str(self.log_path), recorder=rec.as_dict())
        final = self._final_diagnostics or {}
        out["rejections"] = {
            "can_rx": diagnostics.values_of(final, "can_rx"),
            "features": diagnostics.values_of(final, "features"),
            "dsp_rejected_frames": int(
                diagnostics.values_of(final, "dsp").get("rejected_frames", 0)
            ),
        }
        out["problems"] = run_problems(out)
        return out

    def _on_features(self, rec: CycleRecorder):
        feed, record, raw = self.features.feed, rec.record_vision, self.opts.record_raw

        def on_payload(payload: bytes) -> None:
            now = time.monotonic_ns()
            feed(payload, now)
            if raw:
                record(payload, now)

        return on_payload

    def _wait_ready(self, dsp: JointClient) -> None:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not self.stop.is_set():
            have_state = dsp.state_age_s() is not None
            if have_state and (self.opts.lockstep or self.features.latest is not None):
                return
            if time.monotonic() > deadline:
                missing = "joint state (CAN)" if not have_state else "image features (zenoh)"
                raise ControllerError(
                    f"no {missing} within {STARTUP_TIMEOUT_S:.0f} s: is `hil emulator` "
                    f"(and `hil vision`) running on the same transports?"
                )
            time.sleep(0.01)

    def _wait_enabled(self, dsp: JointClient) -> None:
        """After ENABLE: wait until the DSP reports *operation enabled* (it answers a state
        change with a DspStatus at once), so the first tick runs the law."""
        deadline = time.monotonic() + ENABLE_TIMEOUT_S
        while not self.stop.is_set():
            status = dsp.status
            self.drive.update(status)
            if self.drive.mode == MODE_ENABLED:
                return
            if time.monotonic() > deadline:
                state = "no DspStatus" if status is None else status.drive_state.label
                fault = "" if status is None else f", fault {status.fault_reason.label}"
                raise ControllerError(
                    f"the DSP did not enter operation enabled within {ENABLE_TIMEOUT_S:g} s "
                    f"(state {state}{fault})"
                )
            time.sleep(0.002)

    # --- the loop ---------------------------------------------------------------------------
    def _loop(self, dsp: JointClient, rec: CycleRecorder) -> None:
        cfg = self.cfg
        self._warm_up()
        if self.opts.realtime_settings:
            rt = apply_realtime(cfg.controller.rt_priority, cfg.controller.cpu)
            for w in rt.warnings:
                print(f"hil controller: warning: {w}", file=sys.stderr)
        self._wait_ready(dsp)
        if self.stop.is_set():
            self.stats.stopped_before_arming = True
            return  # told to stop during start-up: the DSP is never armed
        dsp.enable()
        self._wait_enabled(dsp)
        max_ticks = (
            math.floor(self.opts.duration_s * cfg.rates.control_hz + 1e-9)
            if self.opts.duration_s > 0
            else None
        )
        try:
            with GcPaused():
                if self.opts.lockstep:
                    self._run_lockstep(dsp, rec, max_ticks)
                else:
                    self._run_realtime(dsp, rec, max_ticks)
        finally:
            dsp.send_torque(0.0, 0.0)
            dsp.disable()
            self._final_diagnostics = self.diagnostics(dsp, rec, final=True)
            rec.record_diagnostics(self._final_diagnostics, final=True)

    # --- diagnostics ------------------------------------------------------------------------
    def _maybe_diagnostics(self, dsp: JointClient, rec: CycleRecorder) -> None:
        """About once a second (every ``control_hz`` ticks), after the tick's write."""
        if self.stats.ticks % self._diag_every == 0:
            rec.record_diagnostics(self.diagnostics(dsp, rec))

    def diagnostics(self, dsp: JointClient, rec: CycleRecorder, final: bool = False) -> dict:
        """The ``/diagnostics`` record of this moment (:mod:`rt_controller.runtime.diagnostics`)."""
        st = self.stats
        status = dsp.status
        recorder = rec.as_dict()
        if final:
            recorder.pop("pending", None)  # the final record is itself still queued
        return diagnostics.build(
            t_ns=time.monotonic_ns(),
            tick=st.ticks,
            can_rx=diagnostics.counters(dsp.stats.e2e),
            features=diagnostics.counters(self.features.counts),
            dsp={
                "status_received": status is not None,
                "mode": self.drive.mode,
                "drive_state": status.drive_state.label if status else "none",
                "fault_reason": status.fault_reason.label if status else "none",
                "session": int(status.session) if status else 0,
                "torque_enabled": bool(status and status.torque_enabled),
                "watchdog_tripped": bool(status and status.watchdog_tripped),
                "rejected_frames": int(status.rejected_frames) if status else 0,
                **{f"events.{k}": v for k, v in self.drive.counters().items()},
                **{f"ticks.{k}": v for k, v in st.drive_ticks.items()},
            },
            controller={
                "ticks": st.ticks,
                "deadline_misses": st.deadline_misses,
                "missed_periods": st.missed_periods,
                "stale_features": st.stale_features,
                "stale_states": st.stale_states,
                "fallbacks": st.fallbacks,
                "watchdog_trips": st.watchdog_trips,
            },
            recorder=recorder,
            final=final,
        )

    def _warm_up(self) -> None:
        """Compile and exercise every branch of the tick before the DSP is armed (never inside
        the loop): see :func:`rt_controller.control.controller.warm_up`."""
        warm_up(self.controller, self.cfg)

    def _run_realtime(self, dsp: JointClient, rec: CycleRecorder, max_ticks: int | None) -> None:
        clock = MonotonicClock(spin_ns=round(self.cfg.controller.spin_us * 1e3))
        cadence = Cadence(self.period_ns, clock)
        first = None
        while not self.stop.is_set():
            tick = cadence.wait()
            first = tick.index if first is None else first
            if max_ticks is not None and tick.index - first >= max_ticks:
                return
            t_s = (tick.release_ns - cadence.start_ns) / 1e9
            self._tick(dsp, rec, tick.index, tick.wake_ns, tick.lateness_ns, tick.missed, t_s)
            end = time.monotonic_ns()
            if end > cadence.deadline_of(tick):
                self.stats.deadline_misses += 1
                self._last_record["deadline_miss"] = True
            rec.record_cycle(self._last_record)
            self._maybe_diagnostics(dsp, rec)

    def _run_lockstep(self, dsp: JointClient, rec: CycleRecorder, max_ticks: int | None) -> None:
        last = None
        while not self.stop.is_set() and (max_ticks is None or self.stats.ticks < max_ticks):
            try:
                k = dsp.wait_sync(LOCKSTEP_SYNC_TIMEOUT_S)
            except HalTimeoutError:
                return  # the emulator finished its run
            if last is not None and k <= last:
                if k == last:  # a re-sent Sync: our command was lost, send it again
                    tau = self._last_record["tau"]
                    dsp.send_torque(tau[0], tau[1], tick=k)
                continue
            missed = 0 if last is None else k - last - 1
            last = k
            wake = time.monotonic_ns()
            self.features.wait_pose_seq(k, LOCKSTEP_FEATURE_TIMEOUT_S)
            self._tick(dsp, rec, k, wake, 0, missed, k * self.period_ns / 1e9, sync=k)
            rec.record_cycle(self._last_record)
            self._maybe_diagnostics(dsp, rec)

    def _follow_drive(self, dsp: JointClient) -> str:
        """Track the DSP's drive state (:class:`hal.drive_state.DriveMonitor`), count faults and
        apply the re-arm policy; the drive mode of this tick (the law runs only in ``enabled``).

        Policy (``controller.rearm_after_trip``, ``controller.rearm_after_restart``): a watchdog
        fault means this loop was late, so it may be reset and re-armed once per trip; a DSP
        that restarted (new session) or was disabled by someone else is re-armed only when
        configured; a limit or encoder fault never is.
        """
        ctl_cfg = self.cfg.controller
        upd = self.drive.update(dsp.status)
        for ev in upd.events:
            if ev is DriveEvent.FAULT:
                reason = upd.fault.label
                self.stats.dsp_faults[reason] = self.stats.dsp_faults.get(reason, 0) + 1
                if upd.fault is FaultReason.WATCHDOG:
                    self.stats.watchdog_trips += 1
                    if ctl_cfg.rearm_after_trip:
                        dsp.enable(reset_fault=True)
                        self.stats.rearms += 1
            elif ev is DriveEvent.DSP_RESTARTED and ctl_cfg.rearm_after_restart:
                self.drive.acknowledge_restart()
                dsp.enable(reset_fault=False)
                self.stats.rearms += 1
            elif ev is DriveEvent.DISARMED and ctl_cfg.rearm_after_restart:
                dsp.enable(reset_fault=False)
                self.stats.rearms += 1
        mode = self.drive.mode
        age = dsp.status_age_s
        if not self.opts.lockstep and (age is None or age > self._status_limit_s):
            mode = MODE_NO_STATUS  # a silent DSP: its last word no longer counts
        if mode != MODE_ENABLED:
            self.stats.drive_ticks[mode] = self.stats.drive_ticks.get(mode, 0) + 1
        return mode

    def _tick(
        self,
        dsp: JointClient,
        rec: CycleRecorder,
        index: int,
        wake_ns: int,
        lateness_ns: int,
        missed: int,
        t_s: float,
        sync: int | None = None,
    ) -> None:
        cfg, st = self.cfg, self.stats
        # --- read
        state_stale = False
        state_ns = None
        try:
            state = dsp.latest_state(max_age_s=self._state_limit_s)
            q, dq, state_ns = np.array(state.q), np.array(state.dq), state.t_ns
            state_age_ms = (wake_ns - state.t_ns) / 1e6
        except HalTimeoutError:
            state_stale, q, dq, state_age_ms = True, np.full(2, math.nan), np.zeros(2), math.nan
        feat, recv_ns = self.features.latest_received()
        if feat is None or recv_ns is None:
            f, f_age_ms = np.full(2, math.nan), math.nan
        elif self.opts.lockstep:
            f, f_age_ms = np.array(feat.f), (t_s * 1e9 - feat.sim_time_ns) / 1e6
        else:  # by stamp and by arrival: a future stamp cannot make old data look fresh
            f, f_age_ms = np.array(feat.f), feature_age_ns(wake_ns, feat.stamp_ns, recv_ns) / 1e6
        f_stale = not (0.0 <= f_age_ms <= cfg.controller.feature_timeout_s * 1e3)
        drive_mode = self._follow_drive(dsp)
        t_read = time.monotonic_ns()
        # --- decide
        d = self.controller.decide(
            t_s, q, dq, f, f_stale=f_stale, state_stale=state_stale, drive_mode=drive_mode
        )
        fields = decision_fields(self.controller, d)
        # Counted per tick as recorded (f_stale / state_stale), the same way `hil report` does.
        st.stale_states += int(state_stale)
        st.stale_features += int(f_stale)
        if d.command is not None:
            st.J += fields["cost"] / cfg.rates.control_hz
            st.fallbacks += int(fields["fallback"])
            st.f_final = vec2(f)
        t_solve = time.monotonic_ns()
        # --- write
        tau = d.tau
        dsp.send_torque(float(tau[0]), float(tau[1]), tick=sync)
        t_write = time.monotonic_ns()
        st.ticks += 1
        st.missed_periods += missed
        solve_us = (t_solve - t_read) / 1e3
        st.solve_us.append(solve_us)
        st.lateness_us.append(lateness_ns / 1e3)
        cycle_us = (t_write - wake_ns) / 1e3
        st.cycle_us.append(cycle_us)
        self._last_record = cycle_record(
            tick=index,
            t_ns=wake_ns,
            sim_time_s=t_s,
            timing=Timing(
                lateness_us=lateness_ns / 1e3,
                read_us=(t_read - wake_ns) / 1e3,
                solve_us=solve_us,
                write_us=(t_write - t_solve) / 1e3,
                cycle_us=cycle_us,
                e2e_us=math.nan if state_ns is None else (t_write - state_ns) / 1e3,
                missed_periods=missed,
            ),
            q=q,
            dq=dq,
            f=f,
            f_age_ms=f_age_ms,
            state_age_ms=state_age_ms,
            f_valid=feat is not None and feat.valid,
            f_stale=f_stale,
            state_stale=state_stale,
            decision=fields,
        )
