"""The control loop, ros2_control style: for each release of the pacer,

    observation = hardware.read(release)
    decision    = decide(observation)
    hardware.write(decision, release)
    record(cycle)

The pacer owns what depends on the clock mode, the hardware the transports, the drive policy
the DSP's drive state, the counters every total; ``decide`` is the pure per-tick rule
:meth:`rt_controller.control.controller.Controller.decide`, shared with replay and simulation.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from hal.config import RigConfig
from rt_controller.calibration.parameters import LAW_KEYS, ParameterService
from rt_controller.control.controller import Controller, Decision
from rt_controller.runtime import diagnostics
from rt_controller.runtime.cadence import Clock
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.cycle_record import Timing, cycle_record, decision_fields, vec2
from rt_controller.runtime.drive_policy import DrivePolicy
from rt_controller.runtime.hardware import Observation, RigHardware
from rt_controller.runtime.pacers import Pacer, Release


class RuleCall(NamedTuple):
    """What one tick hands the per-tick rule (kept for the rehearsal)."""

    t_s: float
    obs: Observation
    predict_ms: float
    f_predict_ms: float
    now_s: float


def apply_rule(ctl: Controller, call: RuleCall) -> Decision:
    """``ctl.decide`` on one tick's observation (ages compensated as the record states them)."""
    o = call.obs
    return ctl.decide(
        call.t_s,
        o.q,
        o.dq,
        o.f,
        f_stale=o.f_stale,
        state_stale=o.state_stale,
        drive_mode=o.drive_mode,
        state_age_s=call.predict_ms / 1e3,
        feature_age_s=call.f_predict_ms / 1e3,
        now_s=call.now_s,
    )


class ControlLoop:
    """read → decide → write → record, once per release of ``pacer``."""

    def __init__(
        self,
        cfg: RigConfig,
        controller: Controller,
        hw: RigHardware,
        pacer: Pacer,
        drive: DrivePolicy,
        recorder: Any,
        counters: RunCounters,
        clock: Clock,
        params: ParameterService,
    ) -> None:
        self.cfg, self.controller, self.hw, self.pacer = cfg, controller, hw, pacer
        self.drive, self.recorder, self.counters, self.clock = drive, recorder, counters, clock
        self.params = params
        """Online parameter changes and operator actions, taken at each tick boundary."""
        self.last_call: RuleCall | None = None
        """The last tick's rule call (the rehearsal replays it)."""
        self.last_write_delay_us = 0
        self._diag_every = max(1, round(cfg.rates.control_hz))

    def run(self, max_ticks: int | None) -> None:
        for release in self.pacer.releases(max_ticks):
            self.take_parameters(release)
            self.take_actions(release)
            cycle = self.tick(release)
            if self.pacer.overran(release):
                self.counters.deadline_misses += 1
                cycle["deadline_miss"] = True
            self.record(cycle)

    def take_parameters(self, release: Release) -> None:
        """At the tick boundary, before the tick: the change sets due, judged; an accepted one
        is in force for the whole of this tick. Each outcome goes to the log."""
        cfg, outcomes = self.params.due(release.index, release.wake_ns)
        if cfg is not None:
            keys = {c["key"] for o in outcomes if o.accepted for c in o.changes}
            self.controller.reconfigure(cfg, law_changed=bool(keys & LAW_KEYS))
            self.cfg = self.hw.cfg = cfg
            self.pacer.retune(cfg)
        for o in outcomes:
            self.recorder.record_parameters(o.record())

    def take_actions(self, release: Release) -> None:
        """At the tick boundary, after the parameters: the operator actions due
        (:mod:`rt_controller.calibration.operator`), done or refused; each to the log."""
        for act in self.params.actions.due(release.index):
            reason = act.refusal or self.drive.operate(self.hw.dsp, act.action)
            out = act.finish(
                release.index, accepted=reason is None, reason=reason, t_ns=release.wake_ns
            )
            self.recorder.record_event(out.record())

    def read(self, release: Release) -> Observation:
        """The read phase: the observation, with the drive state followed to this tick."""
        mode = self.drive.follow(self.hw.dsp, release.wake_ns, self.pacer.status_limit_s)
        return self.observe(release.wake_ns, mode)

    def observe(self, wake_ns: int, drive_mode: str) -> Observation:
        """The inputs at ``wake_ns``, judged by the pacer's limits and ages."""
        p = self.pacer
        return self.hw.read(
            wake_ns,
            state_limit_s=p.state_limit_s,
            feature_age=p.feature_age_ms,
            drive_mode=drive_mode,
        )

    def tick(self, release: Release) -> dict[str, Any]:
        """One tick's phases; the cycle record (every time stamp from the loop's clock)."""
        st, now = self.counters, self.clock.now_ns
        wake_ns, lateness_ns = release.wake_ns, release.lateness_ns
        # --- read
        obs = self.read(release)
        t_read = now()
        # --- decide
        predict_ms, f_predict_ms = self.pacer.prediction_ms(obs)
        now_s = release.t_s + lateness_ns / 1e3 / 1e6  # as replay rebuilds it from the record
        call = RuleCall(release.t_s, obs, predict_ms, f_predict_ms, now_s)
        d = apply_rule(self.controller, call)
        self.last_call = call
        t_solve = now()
        # --- write
        self.last_write_delay_us = self.hw.write(
            d.torque, sync=release.sync, release_ns=release.release_ns
        )
        t_write = now()
        # --- record (from here on nothing delays the torque)
        fields = decision_fields(self.controller, d)
        st.stale_states += int(obs.state_stale)  # per tick as recorded, as `hil report` counts
        st.stale_features += int(obs.f_stale)
        st.outages.note(release.index, release.t_s, obs.f_stale or not obs.f_valid)
        if d.mode == "control":
            st.J += fields["cost"] / self.cfg.rates.control_hz
            st.fallbacks += int(fields["fallback"])
            self._follow_features(obs.f, release.t_s)
        st.ticks += 1
        st.missed_periods += release.missed
        solve_us = (t_solve - t_read) / 1e3
        cycle_us = (t_write - wake_ns) / 1e3
        st.solve_us.append(solve_us)
        st.lateness_us.append(lateness_ns / 1e3)
        st.cycle_us.append(cycle_us)
        return cycle_record(
            tick=release.index,
            t_ns=wake_ns,
            sim_time_s=release.t_s,
            timing=Timing(
                lateness_us=lateness_ns / 1e3,
                read_us=(t_read - wake_ns) / 1e3,
                solve_us=solve_us,
                law_us=d.solve_ns / 1e3,
                write_us=(t_write - t_solve) / 1e3,
                cycle_us=cycle_us,
                e2e_us=math.nan if obs.state_ns is None else (t_write - obs.state_ns) / 1e3,
                missed_periods=release.missed,
            ),
            q=obs.q,
            dq=obs.dq,
            f=obs.f,
            f_age_ms=obs.f_age_ms,
            state_age_ms=obs.state_age_ms,
            f_valid=obs.f_valid,
            f_stale=obs.f_stale,
            state_stale=obs.state_stale,
            decision=fields,
            predict_ms=predict_ms,
            f_predict_ms=f_predict_ms,
            param_set=self.params.param_set,
        )

    def record(self, cycle: dict[str, Any]) -> None:
        """The record phase: the cycle to the recorder and, about once a second (every
        ``control_hz`` ticks), the diagnostics."""
        self.recorder.record_cycle(cycle)
        if self.counters.ticks % self._diag_every == 0:
            self.recorder.record_diagnostics(self.diagnostics())

    def diagnostics(self, final: bool = False) -> dict[str, Any]:
        """The ``/diagnostics`` record of this moment (:mod:`rt_controller.runtime.diagnostics`)."""
        recorder = self.recorder.as_dict()
        if final:
            recorder.pop("pending", None)  # the final record is itself still queued
        return diagnostics.build(
            t_ns=self.clock.now_ns(),
            tick=self.counters.ticks,
            **self.hw.counters(),
            dsp=self.drive.block(self.hw.dsp),
            controller=self.counters.controller_block(),
            recorder=recorder,
            final=final,
            parameters=self.params.counters.as_dict(),
        )

    def _follow_features(self, f: np.ndarray, t_s: float) -> None:
        """The summary's view of the scenario: f at the first law tick and at the last, and
        when the target's jump was seen (a step of more than half the configured jump)."""
        st = self.counters
        if st.ticks == 0 or not np.isfinite(st.f_first).all():
            st.f_first = vec2(f)
        sc = self.cfg.scenario
        if sc.disturbance and st.jump_seen_s is None and np.isfinite(st.f_final).all():
            jump = math.hypot(sc.f_jump[0] - sc.f0[0], sc.f_jump[1] - sc.f0[1])
            if math.hypot(f[0] - st.f_final[0], f[1] - st.f_final[1]) > jump / 2:
                st.jump_seen_s = t_s
        st.f_final = vec2(f)
