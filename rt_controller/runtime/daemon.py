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

import contextlib
import math
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hal.config import RigConfig
from hal.drive_state import (
    MODE_ENABLED,
    MODE_NO_STATUS,
    DriveEvent,
    DriveMonitor,
    DriveUpdate,
    FaultReason,
)
from hal.errors import HalStopped, HalTimeoutError
from hal.joint_client import JointClient
from hal.secoc import rig_key
from hal.vision_codec import FeatureDecoder, feature_age_ns
from hal.zenoh_session import KEY_FEATURES, PayloadRing, ZenohSession, open_session
from rt_controller.control.controller import Controller, Decision, warm_up
from rt_controller.errors import ControllerError
from rt_controller.runtime import diagnostics
from rt_controller.runtime.cadence import Cadence, Clock, Idle, MonotonicClock, Tick
from rt_controller.runtime.cycle_record import Timing, cycle_record, decision_fields, vec2
from rt_controller.runtime.realtime import GcPaused, GilSwitchInterval, apply_realtime
from rt_controller.runtime.recorder import CycleRecorder
from rt_controller.runtime.recorder_process import RecorderService, RemoteRecorder
from rt_controller.sample_stats import percentile

STARTUP_TIMEOUT_S = 20.0
"""How long the daemon waits for the first joint state and features before giving up."""
STATE_POLL_NS = 100_000
"""Fake clock: the step by which a tick waiting for its joint state advances the clock."""
LOCKSTEP_SYNC_TIMEOUT_S = 2.0
"""Lockstep without a duration: without a Sync for this long the emulator has finished."""
LOCKSTEP_STALL_TIMEOUT_S = 30.0
"""Lockstep with a duration not yet reached: how long the DSP may stay silent (a stalled or
descheduled emulator; user-mode Linux runs about 10x slower) before the run ends short, which
makes it not clean."""
SYNC_POLL_S = 0.25
"""Lockstep: the wait for a Sync looks at the stop request this often."""
LOCKSTEP_FEATURE_TIMEOUT_S = 1.0
LIVE_DRAIN_TIMEOUT_S = 1.0
"""After the loop: how long the live stream may wait for the recorder's queue to drain."""
PREFETCH_GUARD_NS = 1_000_000
"""Realtime: the read-ahead while waiting for a release stops this long before the spin window."""
REHEARSAL_LEAD_NS = 200_000
"""Realtime: the rehearsal of the last tick's rule starts this long before the spin window."""
REHEARSAL_MIN_PERIOD_NS = 5_000_000
"""Realtime: rehearse only at this period or longer (faster ticks keep their code warm)."""
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
    live: bool = True
    """Publish every cycle and diagnostics record on zenoh (``hil/controller/cycle``,
    ``hil/controller/diagnostics``) from the recorder (its process, or its writer thread), for
    ``hil monitor``."""
    scene: bool = True
    """Draw the arm into the MCAP (Foxglove scene topics, :mod:`rt_controller.monitor.scene`)."""
    clock: Clock | None = None
    """The loop's clock (default: the monotonic clock, sleeping then spinning
    ``controller.spin_us`` before each release); tests pass a fake one."""


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
    late_states: int = 0
    """Realtime ticks whose period's joint state had not arrived at the release: they waited
    for it (``controller.state_wait_us``)."""
    old_states: int = 0
    """Of those, the ticks whose wait ran out: they used the previous period's state."""
    drive_ticks: dict[str, int] = field(default_factory=dict)
    """Ticks run while the DSP was not in *operation enabled*, by mode (no law ran in them)."""
    dsp_faults: dict[str, int] = field(default_factory=dict)
    """Faults the DSP reported, by reason (``watchdog``, ``position_limit``, ...)."""
    rearms: int = 0
    """Times the controller re-armed the DSP by its re-arm policy."""
    arming_ticks: int = 0
    """Realtime releases between ENABLE and *operation enabled*: each sent a zero torque
    (the command stream is cyclic from ENABLE on); no law ran, they are not in ``ticks``."""
    stopped_before_arming: bool = False
    """A stop request arrived during start-up: the DSP was never armed, no tick ran."""
    spin_s: float = 0.0
    """Realtime: seconds spent busy-waiting before deadlines (``controller.spin_us``)."""
    rehearsals: int = 0
    """Realtime: releases before which the last tick's rule was rehearsed
    (``controller.rehearse``)."""
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
    DSP fell silent, ...); anything else than the first two before ``planned_ticks`` makes
    the run not clean."""
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
            "f_first": self.f_first,
            "jump_seen_s": self.jump_seen_s,
            "planned_ticks": self.planned_ticks,
            "end_reason": self.end_reason,
            "deadline_misses": self.deadline_misses,
            "missed_periods": self.missed_periods,
            "stale_features": self.stale_features,
            "stale_states": self.stale_states,
            "fallbacks": self.fallbacks,
            "watchdog_trips": self.watchdog_trips,
            "late_states": self.late_states,
            "old_states": self.old_states,
            "drive_ticks": dict(self.drive_ticks),
            "dsp_faults": dict(self.dsp_faults),
            "rearms": self.rearms,
            "arming_ticks": self.arming_ticks,
            "spin_s": self.spin_s,
            "rehearsals": self.rehearsals,
            "stopped_before_arming": self.stopped_before_arming,
            "solve_us_median": pct(self.solve_us, 50),
            "solve_us_p99": pct(self.solve_us, 99),
            "lateness_us_p99": pct(self.lateness_us, 99),
            "cycle_us_p99": pct(self.cycle_us, 99),
        }


def run_problems(summary: dict[str, Any]) -> list[str]:
    """Why a finished run cannot be trusted, one short phrase each (empty: a clean run).

    A run is not clean when it ended before its duration for another reason than a stop
    request (the DSP fell silent), lost log records, tripped the DSP's watchdog, saw the DSP
    fault, received a stream of frames or messages that failed authentication (another sender
    on the rig's bus or zenoh: :data:`diagnostics.AUTH_FAULT_MIN` or more), or ran ticks without
    an enabled DSP (disarmed, restarted, silent); the commands exit non-zero and print these on
    one line.
    """
    out: list[str] = []
    planned, ticks = summary.get("planned_ticks"), int(summary.get("ticks") or 0)
    reason = summary.get("end_reason") or "duration"
    if planned is not None and ticks < planned and reason not in ("duration", "stopped"):
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


@dataclass(frozen=True)
class Inputs:
    """What the read phase of one tick found (NaN where absent)."""

    q: np.ndarray
    dq: np.ndarray
    f: np.ndarray
    state_ns: int | None
    """Receive time of the joint state (None when stale)."""
    state_age_ms: float
    state_stale: bool
    f_age_ms: float
    f_stale: bool
    f_valid: bool
    drive_mode: str
    """The DSP's drive mode (:data:`hal.drive_state.MODES`); the law runs only in ``enabled``."""


class RuleCall(NamedTuple):
    """What one tick hands the per-tick rule (kept for the rehearsal, :meth:`_rehearse`)."""

    t_s: float
    inputs: Inputs
    predict_ms: float
    f_predict_ms: float
    now_s: float


def apply_rule(ctl: Controller, call: RuleCall) -> Decision:
    """``ctl.decide`` on one tick's inputs (ages compensated as the record states them)."""
    inp = call.inputs
    return ctl.decide(
        call.t_s,
        inp.q,
        inp.dq,
        inp.f,
        f_stale=inp.f_stale,
        state_stale=inp.state_stale,
        drive_mode=inp.drive_mode,
        state_age_s=call.predict_ms / 1e3,
        feature_age_s=call.f_predict_ms / 1e3,
        now_s=call.now_s,
    )


def default_log_path(cfg: RigConfig, law: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path(cfg.controller.log_dir) / f"run-{stamp}-{law}.mcap"


def _scene_builder(cfg: RigConfig) -> Any:
    from rt_controller.monitor.scene import SceneBuilder

    return SceneBuilder(cfg)


def _live_publisher(session: Any) -> Any:
    """The recorder's live sink on ``session``, or None (with a warning) if zenoh refuses it:
    watching is optional, the run goes on without it."""
    from hal.errors import HalError
    from rt_controller.monitor.live import LivePublisher

    try:
        return LivePublisher(session)
    except HalError as exc:
        print(f"hil controller: warning: no live stream: {exc}", file=sys.stderr)
        return None


Recorder = CycleRecorder | RemoteRecorder
"""Either recorder (``controller.recorder``: a thread of this process, or its own process)."""


def recorder_service(cfg: RigConfig, opts: DaemonOptions) -> contextlib.AbstractContextManager:
    """The recorder's child process for ``controller.recorder = "process"`` (start it before
    the links: while this process has a single thread the child is forked, which is instant);
    a context giving None for ``"thread"``."""
    if cfg.controller.recorder != "process":
        return contextlib.nullcontext(None)
    return RecorderService(cfg, zenoh_endpoint=opts.zenoh_endpoint, zenoh_config=opts.zenoh_config)


def _wait_drained(rec: Recorder, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while rec.pending and time.monotonic() < deadline:
        time.sleep(0.002)


@contextlib.contextmanager
def open_links(
    cfg: RigConfig, opts: DaemonOptions, stop: threading.Event
) -> Iterator[tuple[JointClient, ZenohSession]]:
    """The controller's links: the CAN client in poll mode (the control thread reads the bus
    itself, no receive thread) and the zenoh session. The bus first: a bad ``--can`` is
    reported at once, not after waiting for zenoh. :class:`HalStopped` when ``stop`` is set
    while waiting for zenoh."""
    with JointClient.open(opts.can, cfg, start=False) as dsp:
        session = open_session(
            cfg,
            listen=False,
            endpoint=opts.zenoh_endpoint,
            config_file=opts.zenoh_config,
            wait_s=STARTUP_TIMEOUT_S,
            stop_event=stop,
        )
        try:
            yield dsp, session
        finally:
            session.close()


class ControllerDaemon:
    """Owns the law, the DSP client, the feature subscriber and the recorder for one run."""

    def __init__(self, cfg: RigConfig, options: DaemonOptions, stop: threading.Event) -> None:
        self.cfg = cfg
        self.opts = options
        self.stop = stop
        self.clock: Clock = options.clock or MonotonicClock(
            spin_ns=round(cfg.controller.spin_us * 1e3)
        )
        self._real_clock = options.clock is None
        self._ring: PayloadRing | None = None
        self._rec: Recorder | None = None
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
        self._state_wait_ns = min(round(cfg.controller.state_wait_us * 1e3), self.period_ns // 2)
        self._states_seen = -1
        """Joint states received up to the last tick's read (-1: no tick yet)."""
        self._can_base: dict[str, Any] = {}
        """The CAN receive counters when this run began (a plan's links outlive its runs)."""
        self._rehearsal: Controller | None = None
        """Realtime: a second controller that reruns the last tick's rule shortly before each
        release (``controller.rehearse``; see :meth:`_rehearse`)."""
        self._last_call: RuleCall | None = None
        self._last_write_delay_us = 0
        """Realtime: how long after its release the last torque command left (microseconds)."""
        self._rehearsal_due = False

    # --- wiring -----------------------------------------------------------------------------
    def _open_recorder(self, service: RecorderService | None) -> Recorder:
        """This run's log: in the recorder's process when there is a ``service``, else a
        writer thread here."""
        cfg, opts = self.cfg, self.opts
        run_info = {
            "clock": "lockstep" if opts.lockstep else "realtime",
            "can": opts.can or cfg.transport.can,
            "zenoh": opts.zenoh_config or opts.zenoh_endpoint or cfg.transport.zenoh_endpoint,
            "recorder": "thread" if service is None else f"process ({service.start_method})",
        }
        if service is not None:  # lockstep has no deadline: the tick waits for a busy recorder
            return service.open(
                self.log_path, cfg, run_info=run_info, scene=opts.scene, backpressure=opts.lockstep
            )
        scene = _scene_builder(cfg) if opts.scene else None
        return CycleRecorder(self.log_path, cfg, run_info=run_info, scene=scene)

    def run(self) -> dict[str, Any]:
        """Open the recorder and the links, run until stopped; the summary. The recorder is
        finished on every exit."""
        with recorder_service(self.cfg, self.opts) as service:
            rec = self._open_recorder(service)
            try:
                with open_links(self.cfg, self.opts, self.stop) as (dsp, session):
                    self._run_with(dsp, session, rec)
            except HalStopped:  # told to stop while waiting for zenoh
                self.stats.stopped_before_arming = True
            finally:
                rec.close()
        return self._summary(rec)

    def run_on(
        self, dsp: JointClient, session: ZenohSession, service: RecorderService | None = None
    ) -> dict[str, Any]:
        """One run on links that outlive it (``hil controller --plan``: a poll-mode client, an
        open session and the plan's recorder process, if any); the summary. Leaves them as it
        found them."""
        rec = self._open_recorder(service)
        try:
            self._run_with(dsp, session, rec)
        finally:
            rec.close()
        return self._summary(rec)

    def _run_with(self, dsp: JointClient, session: ZenohSession, rec: Recorder) -> None:
        """The run on open links: recorder hooks, the feature subscription, the loop."""
        self._rec = rec
        hooks = self._raw_hooks(rec)
        dsp.frame_hook, dsp.tx_hook = hooks.get("frame_hook"), hooks.get("tx_hook")
        self._can_base = diagnostics.counters(dsp.stats.e2e)
        live = None
        if isinstance(rec, RemoteRecorder):
            if self.opts.live:  # published by the recorder's process, on its own session
                rec.stream_live()
        else:
            live = _live_publisher(session) if self.opts.live else None
            rec.set_live(live)
        subscriber = None
        try:
            if self.opts.lockstep:  # the tick waits for its pose's answer: a callback feeds
                subscriber = session.subscribe(KEY_FEATURES, self._on_features(rec))
            else:  # the tick takes the newest features itself, no callback thread
                self._ring = session.subscribe_ring(KEY_FEATURES)
            self._loop(dsp, rec)
        finally:
            if live is not None:  # let the last records (final diagnostics) go out
                _wait_drained(rec, LIVE_DRAIN_TIMEOUT_S)
                rec.set_live(None)
                live.close()
            if self._ring is not None:
                self._ring.close()
                self._ring = None
            if subscriber is not None:
                with contextlib.suppress(Exception):  # a closed session undeclared it already
                    subscriber.undeclare()
            dsp.frame_hook = dsp.tx_hook = None

    def _summary(self, rec: Recorder) -> dict[str, Any]:
        rec.close()
        out = {**self.what_runs(), **self.stats.as_dict()}
        out.update(law=self.controller.law.name, log=str(self.log_path), recorder=rec.as_dict())
        if rec.error is not None:
            out["log_error"] = str(rec.error)
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

    def what_runs(self) -> dict[str, Any]:
        """What this run is: clock, rate, duration, law (with the horizon for rhc), CAN bus."""
        cfg, opts = self.cfg, self.opts
        rhc = cfg.controller.law == "rhc"
        return {
            "clock": "lockstep" if opts.lockstep else "realtime",
            "rate_hz": cfg.rates.control_hz,
            "duration_s": opts.duration_s or None,
            "law": cfg.controller.law,
            "horizon_s": cfg.rhc.horizon if rhc else None,
            "steps": cfg.rhc.steps if rhc else None,
            "can": opts.can or cfg.transport.can,
        }

    def _raw_hooks(self, rec: Recorder) -> dict[str, Any]:
        """Record every CAN frame as received and sent (stamped with the loop's clock)."""
        if not self.opts.record_raw:
            return {}
        now = self.clock.now_ns
        return {
            "frame_hook": lambda m: rec.record_can(m, now(), "rx"),
            "tx_hook": lambda m: rec.record_can(m, now(), "tx"),
        }

    def read_inputs(self, dsp: JointClient, now_ns: int) -> None:
        """The read phase's I/O, in the control thread: every CAN frame waiting on the bus and
        (realtime) the newest feature messages from the zenoh ring, fed to their decoders."""
        dsp.drain(now_ns, timestamps=self._real_clock)
        if self._ring is not None:
            rec = self._rec if self.opts.record_raw else None
            for payload in self._ring.drain():
                self.features.feed(payload, now_ns)
                if rec is not None:
                    rec.record_vision(payload, now_ns)

    def _on_features(self, rec: Recorder):
        feed, record, raw = self.features.feed, rec.record_vision, self.opts.record_raw

        def on_payload(payload: bytes) -> None:
            now = self.clock.now_ns()
            feed(payload, now)
            if raw:
                record(payload, now)

        return on_payload

    def _wait_ready(self, dsp: JointClient) -> None:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not self.stop.is_set():
            self.read_inputs(dsp, self.clock.now_ns())
            have_state = dsp.state_age_s() is not None
            if have_state and (self.opts.lockstep or self.features.latest is not None):
                return
            if time.monotonic() > deadline:
                missing = "joint state (CAN)" if not have_state else "image features (zenoh)"
                raise ControllerError(
                    f"no {missing} within {STARTUP_TIMEOUT_S:.0f} s: is `hil emulator` "
                    f"(and `hil vision`) running on the same transports?"
                )
            self._pause(10_000_000)

    def _pause(self, ns: int) -> None:
        """Wait ``ns`` on the loop's clock during start-up (a fake clock advances the rig)."""
        self.clock.sleep_until(self.clock.now_ns() + ns)

    def _enabled_now(self, dsp: JointClient, expired: bool) -> bool:
        """Whether the DSP reports *operation enabled*; raises once ``expired`` and it does not."""
        self.read_inputs(dsp, self.clock.now_ns())
        status = dsp.status
        for st in dsp.take_statuses():  # before the run: followed, not acted on (ENABLE resets)
            self.drive.update(st)
        if self.drive.mode == MODE_ENABLED:
            return True
        if expired:
            state = "no DspStatus" if status is None else status.drive_state.label
            fault = "" if status is None else f", fault {status.fault_reason.label}"
            raise ControllerError(
                f"the DSP did not enter operation enabled within {ENABLE_TIMEOUT_S:g} s "
                f"(state {state}{fault})"
            )
        return False

    def _wait_enabled(self, dsp: JointClient) -> None:
        """Lockstep, after ENABLE: wait until the DSP reports *operation enabled* (it answers a
        state change with a DspStatus at once), so the first tick runs the law. The lockstep
        DSP counts its watchdog in periods it advanced, and it advances none before this."""
        deadline = time.monotonic() + ENABLE_TIMEOUT_S
        while not self.stop.is_set():
            if self._enabled_now(dsp, time.monotonic() > deadline):
                return
            self._pause(1_000_000)

    def _arm_on_cadence(self, dsp: JointClient, cadence: Cadence) -> Tick | None:
        """Realtime: ENABLE at the first release, then a zero torque at every release until
        the DSP reports *operation enabled*; returns that release (its tick runs the law), or
        ``None`` when told to stop first.

        The command stream is cyclic from ENABLE on, as a CiA 402 master's PDOs are: the DSP
        arms its watchdog (``dsp.watchdog_periods``, 6 ms at 500 Hz) on ENABLE. The zero
        torques carry Enable = 0, so the first frame that applies torque is the first law
        tick's: the emulated DSP starts the scenario's clock there. Each release
        reads the transports first, so ENABLE goes out after the frames that queued up during
        start-up (locking memory takes a while) were drained, never before a drain that the
        watchdog would see as a gap. These releases are counted in ``arming_ticks``, not in
        ``ticks``.
        """
        deadline: int | None = None
        while not self.stop.is_set():
            tick = cadence.wait()
            expired = deadline is not None and self.clock.now_ns() > deadline
            if self._enabled_now(dsp, expired):
                return tick
            if deadline is None:
                dsp.enable()
                deadline = self.clock.now_ns() + round(ENABLE_TIMEOUT_S * 1e9)
            else:
                delay = self._since_us(tick.release_ns)  # Enable = 0: the scenario waits
                dsp.send_torque(0.0, 0.0, release_delay_us=delay, enable=False)
            self._states_seen = dsp.states_received
            self.stats.arming_ticks += 1
        return None

    # --- the loop ---------------------------------------------------------------------------
    def _loop(self, dsp: JointClient, rec: Recorder) -> None:
        cfg = self.cfg
        self._warm_up()
        if (
            cfg.controller.rehearse
            and self._real_clock
            and not self.opts.lockstep
            and self.period_ns >= REHEARSAL_MIN_PERIOD_NS
        ):
            self._rehearsal = Controller(cfg)
            warm_up(self._rehearsal, cfg)
        self._wait_ready(dsp)
        if self.stop.is_set():
            self.stats.stopped_before_arming = True
            return  # told to stop during start-up: the DSP is never armed
        if self.opts.realtime_settings:
            # After warm-up and the first inputs: the pages locked are those the tick, the
            # receive paths and the recorder have touched (runtime/realtime.py).
            rt = apply_realtime(cfg.controller.rt_priority, cfg.controller.cpu)
            for w in rt.warnings:
                print(f"hil controller: warning: {w}", file=sys.stderr)
        max_ticks = (
            math.floor(self.opts.duration_s * cfg.rates.control_hz + 1e-9)
            if self.opts.duration_s > 0
            else None
        )
        self.stats.planned_ticks = max_ticks
        try:
            with GcPaused(), GilSwitchInterval(cfg.controller.gil_switch_us / 1e6):
                self._run_mode(dsp, rec, max_ticks)
        finally:
            if self.stop.is_set() and self.stats.end_reason == "duration":
                self.stats.end_reason = "stopped"
            dsp.send_torque(0.0, 0.0)
            dsp.disable()
            self._final_diagnostics = self.diagnostics(dsp, rec, final=True)
            rec.record_diagnostics(self._final_diagnostics, final=True)

    def _run_mode(self, dsp: JointClient, rec: Recorder, max_ticks: int | None) -> None:
        """Arm the DSP and run the ticks in the configured clock mode."""
        if self.opts.lockstep:
            dsp.enable()
            self._wait_enabled(dsp)
            self._run_lockstep(dsp, rec, max_ticks)
        else:
            self._run_realtime(dsp, rec, max_ticks)

    # --- diagnostics ------------------------------------------------------------------------
    def _maybe_diagnostics(self, dsp: JointClient, rec: Recorder) -> None:
        """About once a second (every ``control_hz`` ticks), after the tick's write."""
        if self.stats.ticks % self._diag_every == 0:
            rec.record_diagnostics(self.diagnostics(dsp, rec))

    def diagnostics(self, dsp: JointClient, rec: Recorder, final: bool = False) -> dict:
        """The ``/diagnostics`` record of this moment (:mod:`rt_controller.runtime.diagnostics`)."""
        st = self.stats
        status = dsp.status
        recorder = rec.as_dict()
        if final:
            recorder.pop("pending", None)  # the final record is itself still queued
        return diagnostics.build(
            t_ns=self.clock.now_ns(),
            tick=st.ticks,
            can_rx=diagnostics.since(self._can_base, diagnostics.counters(dsp.stats.e2e)),
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
                "late_states": st.late_states,
                "old_states": st.old_states,
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

    def _run_realtime(self, dsp: JointClient, rec: Recorder, max_ticks: int | None) -> None:
        cadence = Cadence(self.period_ns, self.clock)
        try:
            first = self._arm_on_cadence(dsp, cadence)
            if first is not None:
                self._cadence_loop(dsp, rec, max_ticks, cadence, first)
        finally:
            spun = getattr(self.clock, "spun_ns", 0)  # a fake clock never spins
            self.stats.spin_s = spun / 1e9

    def _cadence_loop(
        self,
        dsp: JointClient,
        rec: Recorder,
        max_ticks: int | None,
        cadence: Cadence,
        first: Tick,
    ) -> None:
        """Realtime ticks from ``first`` (the release at which the DSP reported enabled)."""
        tick = first
        while not self.stop.is_set():
            if max_ticks is not None and tick.index - first.index >= max_ticks:
                return
            index = tick.index - first.index  # tick 0 is the first that runs the law
            t_s = (tick.release_ns - first.release_ns) / 1e9
            # the inputs are stamped when actually read (a preempted tick reads later than it
            # woke): a message that arrived after the wake-up is not "from the future"
            self.read_inputs(dsp, self.clock.now_ns())
            if dsp.states_received == self._states_seen:  # this period's sample is late
                self.stats.late_states += 1
                if self._state_wait_ns > 0:
                    self._await_state(dsp, tick.release_ns + self._state_wait_ns)
                else:
                    self.stats.old_states += 1
            self._states_seen = dsp.states_received
            self._tick(dsp, index, tick.wake_ns, tick.lateness_ns, tick.missed, t_s)
            if self.clock.now_ns() > cadence.deadline_of(tick):
                self.stats.deadline_misses += 1
                self._last_record["deadline_miss"] = True
            self._record(dsp, rec)
            self._rehearsal_due = self._rehearsal is not None
            tick = cadence.wait(self._prefetcher(dsp))

    def _prefetcher(self, dsp: JointClient) -> Idle | None:
        """Realtime, on the real clock: the wait for the next release reads the inputs as they
        arrive (blocking on the CAN socket, then decoding in this thread), so that the tick finds
        them decoded instead of decoding them after its release, when the interpreter's code
        has gone cold over the period (a two-frame decode takes 15 us warm, about 150 us after
        20 ms of sleep on a 2-core VM). Arrival stamps are unchanged: CAN frames carry the
        kernel's receive time; features are stamped when taken, now sooner. No decode starts
        within ``PREFETCH_GUARD_NS`` (at most a quarter period) of the spin window: one that ran
        cold past it would make the release late. None with a fake clock (its waits take no
        time)."""
        if not self._real_clock:
            return None
        guard_ns = min(PREFETCH_GUARD_NS, self.period_ns // 4)

        def idle(until_ns: int) -> None:
            now = self.clock.now_ns()
            stop_ns = until_ns - guard_ns
            if now >= stop_ns:  # too close to the release to start a (cold) decode
                if self._rehearsal_due:
                    at = until_ns - REHEARSAL_LEAD_NS
                    if now < at:
                        time.sleep((at - now) / 1e9)
                    self._rehearsal_due = False
                    self._rehearse(dsp)
                    return
                time.sleep(max(0, until_ns - now) / 1e9)
                return
            if dsp.wait_readable((stop_ns - now) / 1e9):
                self.read_inputs(dsp, self.clock.now_ns())

        return idle

    def _rehearse(self, dsp: JointClient) -> None:
        """Realtime, shortly before a release (``controller.rehearse``): run the last tick's
        phases again with nothing kept, so that the code the tick runs is warm when the release
        comes. After a period of sleep on a shared 2-core VM the first run of that code is
        several times slower; the rehearsal pays that instead of the tick.

        - read: the inputs are judged as the tick judges them, without following the drive
          state (the DSP's statuses stay for the tick);
        - decide: the last tick's rule call, on a second controller whose result is thrown
          away (the run's controller and its warm-started solver are untouched);
        - write: the last torque through :meth:`JointClient.rehearse_torque` (a shadow codec,
          nothing reaches the bus, the real counters do not move).
        """
        call, shadow = self._last_call, self._rehearsal
        if call is None or shadow is None:
            return
        self._read(dsp, self.clock.now_ns(), call.t_s, rehearsal=True)
        d = apply_rule(shadow, call)
        decision_fields(shadow, d)
        dsp.rehearse_torque(
            float(d.tau[0]), float(d.tau[1]), release_delay_us=self._last_write_delay_us
        )
        self.stats.rehearsals += 1

    def _since_us(self, release_ns: int) -> int:
        """Microseconds from ``release_ns`` to now on the loop's clock."""
        return (self.clock.now_ns() - release_ns) // 1000

    def _await_state(self, dsp: JointClient, deadline_ns: int) -> None:
        """Realtime read phase, when no joint state came since the last tick: wait for this
        period's state until ``deadline_ns`` (the release plus ``controller.state_wait_us``).

        The DSP samples a little before each tick (``dsp.state_lead_us``); a DSP process that
        ran late sends that sample after the release. The previous period's state is a whole
        period old; ``controller.predict_state`` compensates that age, and this wait avoids it.
        A wait that runs out uses the last state (counted in ``old_states``). Off by default
        (``controller.state_wait_us = 0``).
        """
        seen = dsp.states_received
        while dsp.states_received == seen:
            now = self.clock.now_ns()
            if now >= deadline_ns or self.stop.is_set():
                self.stats.old_states += 1
                return
            if self._real_clock:
                dsp.wait_readable((deadline_ns - now) / 1e9)
            else:  # a fake clock advances the rig while the tick waits
                self.clock.sleep_until(min(deadline_ns, now + STATE_POLL_NS))
            self.read_inputs(dsp, self.clock.now_ns())

    def _next_sync(self, dsp: JointClient, patience_s: float) -> int | None:
        """Lockstep: the next Sync's tick (the bus is read in this thread); None when told to
        stop or when the DSP stayed silent for ``patience_s`` (``end_reason`` says which)."""
        waited = 0.0
        while not self.stop.is_set():
            try:
                return dsp.wait_sync(SYNC_POLL_S)
            except HalTimeoutError:
                waited += SYNC_POLL_S
            if waited >= patience_s:
                self.stats.end_reason = f"no Sync from the DSP for {patience_s:g} s"
                return None
        self.stats.end_reason = "stopped"
        return None

    def _run_lockstep(self, dsp: JointClient, rec: Recorder, max_ticks: int | None) -> None:
        last = None
        patience = LOCKSTEP_SYNC_TIMEOUT_S if max_ticks is None else LOCKSTEP_STALL_TIMEOUT_S
        while not self.stop.is_set() and (max_ticks is None or self.stats.ticks < max_ticks):
            k = self._next_sync(dsp, patience)
            if k is None:
                return  # without a duration: the emulator finished its run
            if last is not None and k <= last:
                if k == last:  # a re-sent Sync: our command was lost, send it again
                    tau = self._last_record["tau"]
                    dsp.send_torque(tau[0], tau[1], tick=k)
                continue
            missed = 0 if last is None else k - last - 1
            last = k
            wake = self.clock.now_ns()
            self.features.wait_pose_seq(k, LOCKSTEP_FEATURE_TIMEOUT_S)
            self.read_inputs(dsp, self.clock.now_ns())
            self._tick(dsp, k, wake, 0, missed, k * self.period_ns / 1e9, sync=k)
            self._record(dsp, rec)

    def _record(self, dsp: JointClient, rec: Recorder) -> None:
        """The record phase: hand the finished cycle to the recorder (with the tick's raw
        frames: pickled into its pipe, or queued for its thread) and, about once a second, the
        diagnostics."""
        rec.record_cycle(self._last_record)
        self._maybe_diagnostics(dsp, rec)

    def _follow_drive(self, dsp: JointClient, now_ns: int) -> str:
        """Track the DSP's drive state (:class:`hal.drive_state.DriveMonitor`), count faults and
        apply the re-arm policy; the drive mode of this tick (the law runs only in ``enabled``).

        Policy (``controller.rearm_after_trip``, ``controller.rearm_after_restart``): a watchdog
        fault means this loop was late, so it may be reset and re-armed once per trip; a DSP
        that restarted (new session) or was disabled by someone else is re-armed only when
        configured; a limit or encoder fault never is.
        """
        self._follow_statuses(dsp)
        mode = self.drive.mode
        age = dsp.status_age_s_at(now_ns)
        if not self.opts.lockstep and (age is None or age > self._status_limit_s):
            mode = MODE_NO_STATUS  # a silent DSP: its last word no longer counts
        if mode != MODE_ENABLED:
            self.stats.drive_ticks[mode] = self.stats.drive_ticks.get(mode, 0) + 1
        return mode

    def _follow_statuses(self, dsp: JointClient) -> None:
        """Feed the drive monitor every status since the last read, in order, and act on each
        update's events: a fault, reset and enable that arrived between two reads are all
        seen (the newest status alone would show "fault, then fault" and no new trip)."""
        for status in dsp.take_statuses():
            self._on_drive_events(dsp, self.drive.update(status))

    def _on_drive_events(self, dsp: JointClient, upd: DriveUpdate) -> None:
        """Count faults and apply the re-arm policy for one monitor update."""
        ctl_cfg = self.cfg.controller
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

    def _read(
        self, dsp: JointClient, wake_ns: int, t_s: float, *, rehearsal: bool = False
    ) -> Inputs:
        """The read phase: the newest joint state and features, judged stale or not, and the
        DSP's drive mode (the inputs themselves were taken off the transports just before).
        A ``rehearsal`` reads the drive mode as it stands and changes nothing."""
        cfg = self.cfg
        state_stale = False
        state_ns = None
        try:
            state = dsp.latest_state(max_age_s=self._state_limit_s, now_ns=wake_ns)
            q, dq, state_ns = np.array(state.q), np.array(state.dq), state.t_ns
            state_age_ms = (wake_ns - state.t_ns) / 1e6
        except HalTimeoutError:
            state_stale, q, dq, state_age_ms = True, np.full(2, math.nan), np.zeros(2), math.nan
        feat, recv_ns = self.features.latest_received()
        if feat is None or recv_ns is None:
            f, f_age_ms = np.full(2, math.nan), math.nan
        elif self.opts.lockstep:
            # in integer ns: t_s * 1e9 rounds below k * period_ns at some ticks (4.02 s, ...),
            # and a frame captured at the tick itself came out 5e-13 ms "in the future": stale
            now_ns = round(t_s * 1e9)  # t_s = k * period exactly; rounding undoes the float
            f, f_age_ms = np.array(feat.f), (now_ns - feat.sim_time_ns) / 1e6
        else:  # by stamp and by arrival: a future stamp cannot make old data look fresh
            f, f_age_ms = np.array(feat.f), feature_age_ns(wake_ns, feat.stamp_ns, recv_ns) / 1e6
        return Inputs(
            q=q,
            dq=dq,
            f=f,
            state_ns=state_ns,
            state_age_ms=state_age_ms,
            state_stale=state_stale,
            f_age_ms=f_age_ms,
            f_stale=not (0.0 <= f_age_ms <= cfg.controller.feature_timeout_s * 1e3),
            f_valid=feat is not None and feat.valid,
            drive_mode=self.drive.mode if rehearsal else self._follow_drive(dsp, wake_ns),
        )

    def _prediction_ms(self, inp: Inputs) -> tuple[float, float]:
        """How far this tick's joint state and features are brought forward
        (``controller.predict_state``, ``controller.predict_features``): their ages in real
        time; 0 in lockstep (sampled at the tick), when stale or missing, and for a state that
        arrived after the wake-up."""
        if self.opts.lockstep:
            return 0.0, 0.0
        ctl = self.cfg.controller
        state = inp.state_age_ms if ctl.predict_state and not inp.state_stale else 0.0
        feats = inp.f_age_ms if ctl.predict_features and not inp.f_stale else 0.0
        return (
            state if math.isfinite(state) and state > 0 else 0.0,
            feats if math.isfinite(feats) and feats > 0 else 0.0,
        )

    def _follow_features(self, f: np.ndarray, t_s: float) -> None:
        """The summary's view of the scenario: f at the first law tick and at the last, and
        when the target's jump was seen (a step of more than half the configured jump)."""
        st = self.stats
        if st.ticks == 0 or not np.isfinite(st.f_first).all():
            st.f_first = vec2(f)
        sc = self.cfg.scenario
        if sc.disturbance and st.jump_seen_s is None and np.isfinite(st.f_final).all():
            jump = math.hypot(sc.f_jump[0] - sc.f0[0], sc.f_jump[1] - sc.f0[1])
            if math.hypot(f[0] - st.f_final[0], f[1] - st.f_final[1]) > jump / 2:
                st.jump_seen_s = t_s
        st.f_final = vec2(f)

    def _tick(
        self,
        dsp: JointClient,
        index: int,
        wake_ns: int,
        lateness_ns: int,
        missed: int,
        t_s: float,
        sync: int | None = None,
    ) -> None:
        """One tick as phases, ros2_control style: read -> decide -> write; the caller records.
        Every time stamp comes from the loop's clock."""
        cfg, st, now = self.cfg, self.stats, self.clock.now_ns
        # --- read
        inp = self._read(dsp, wake_ns, t_s)
        t_read = now()
        # --- decide
        predict_ms, f_predict_ms = self._prediction_ms(inp)
        now_s = t_s + lateness_ns / 1e3 / 1e6  # as replay rebuilds it from the record
        call = RuleCall(t_s, inp, predict_ms, f_predict_ms, now_s)
        d = apply_rule(self.controller, call)
        self._last_call = call
        fields = decision_fields(self.controller, d)
        # Counted per tick as recorded (f_stale / state_stale), the same way `hil report` does.
        st.stale_states += int(inp.state_stale)
        st.stale_features += int(inp.f_stale)
        if d.command is not None:
            st.J += fields["cost"] / cfg.rates.control_hz
            st.fallbacks += int(fields["fallback"])
            self._follow_features(inp.f, t_s)
        t_solve = now()
        # --- write (realtime: the command says how long after the release it leaves)
        tau = d.tau
        if sync is None:
            delay = self._last_write_delay_us = self._since_us(wake_ns - lateness_ns)
            dsp.send_torque(float(tau[0]), float(tau[1]), release_delay_us=delay)
        else:
            dsp.send_torque(float(tau[0]), float(tau[1]), tick=sync)
        t_write = now()
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
                law_us=0.0 if d.command is None else d.command.law.solve_ns / 1e3,
                write_us=(t_write - t_solve) / 1e3,
                cycle_us=cycle_us,
                e2e_us=math.nan if inp.state_ns is None else (t_write - inp.state_ns) / 1e3,
                missed_periods=missed,
            ),
            q=inp.q,
            dq=inp.dq,
            f=inp.f,
            f_age_ms=inp.f_age_ms,
            state_age_ms=inp.state_age_ms,
            f_valid=inp.f_valid,
            f_stale=inp.f_stale,
            state_stale=inp.state_stale,
            decision=fields,
            predict_ms=predict_ms,
            f_predict_ms=f_predict_ms,
        )
