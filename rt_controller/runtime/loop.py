"""The control loop, ros2_control style: the hardware is activated on the pacer's arming
steps, then, for each release of the pacer,

    observation = hardware.read(release)
    decision    = decide(observation)
    hardware.write(decision, release)
    record(cycle)

The pacer owns what depends on the clock mode, the hardware (:class:`~hal.hardware_interface.
HardwareInterface`) the links and the drive, the run context the configuration and every
total; ``decide`` is the pure per-tick rule
:meth:`rt_controller.control.controller.Controller.decide`, shared with replay and simulation.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hal.hardware_interface import HardwareInterface
from rt_controller.calibration.parameters import LAW_KEYS, ParameterService
from rt_controller.control.controller import Controller
from rt_controller.runtime import diagnostics
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.cycle_record import Timing, cycle_record, decision_fields, vec2
from rt_controller.runtime.pacers import Pacer, Release


class ControlLoop:
    """read → decide → write → record, once per release of ``pacer``."""

    def __init__(
        self,
        ctx: RunContext,
        controller: Controller,
        hw: HardwareInterface,
        pacer: Pacer,
        params: ParameterService,
    ) -> None:
        self.ctx, self.controller, self.hw, self.pacer = ctx, controller, hw, pacer
        self.params = params
        """Online parameter changes and operator actions, taken at each tick boundary."""
        self._diag_every = max(1, round(ctx.cfg.rates.control_hz))

    def run(self, max_ticks: int | None) -> None:
        """Activate the hardware, then the ticks until ``max_ticks`` or a stop; the requests
        still waiting then are refused and logged (:meth:`end_requests`)."""
        self.params.plan(max_ticks)  # a request past the planned end is refused at once
        last: Release | None = None
        try:
            if not self.activate():
                return
            for last in self.pacer.releases(max_ticks):
                self.take_parameters(last)
                self.take_actions(last)
                cycle = self.tick(last)
                if self.pacer.overran(last):
                    self.ctx.counters.deadline_misses += 1
                    cycle["deadline_miss"] = True
                if not self.record(cycle) and self.log_lost():  # looked at on a refusal only
                    return
        finally:
            self.end_requests(last)

    def end_requests(self, last: Release | None) -> None:
        """The change sets and actions still waiting when the run ends (after release
        ``last``; None: no tick ran), refused as not applied, answered and logged."""
        tick, t_ns = (None, 0) if last is None else (last.index, last.wake_ns)
        for o in self.params.end(tick, t_ns):
            self.ctx.recorder.record_parameters(o.record())
        for out in self.params.actions.end(tick, t_ns):
            self.ctx.recorder.record_event(out.record())

    def activate(self) -> bool:
        """Arm: the hardware's ``activate`` at each of the pacer's arming steps until it
        reports armed (True), or a stop came first (False)."""
        return any(self.hw.activate(now_ns) for now_ns in self.pacer.arming())

    def take_parameters(self, release: Release) -> None:
        """At the tick boundary, before the tick: the change sets due, judged; an accepted one
        is in force for the whole of this tick. Each outcome goes to the log."""
        cfg, outcomes = self.params.due(release.index, release.wake_ns)
        if cfg is not None:
            keys = {c["key"] for o in outcomes if o.accepted and not o.unchanged for c in o.changes}
            self.controller.reconfigure(cfg, law_changed=bool(keys & LAW_KEYS))
            self.ctx.cfg = cfg  # every part reads it from here on
        for o in outcomes:
            self.ctx.recorder.record_parameters(o.record())

    def take_actions(self, release: Release) -> None:
        """At the tick boundary, after the parameters: the operator actions due
        (:mod:`rt_controller.calibration.operator`), done or refused; each to the log."""
        for act in self.params.actions.due(release.index):
            reason = self.params.actions.refusal(act, release.index)
            reason = reason or self.hw.command(act.action)
            out = act.finish(
                release.index, accepted=reason is None, reason=reason, t_ns=release.wake_ns
            )
            self.ctx.recorder.record_event(out.record())

    def tick(self, release: Release) -> dict[str, Any]:
        """One tick's phases; the cycle record (every time stamp from the loop's clock)."""
        st, now = self.ctx.counters, self.ctx.clock.now_ns
        wake_ns, lateness_ns = release.wake_ns, release.lateness_ns
        # --- read
        obs = self.hw.read(wake_ns, self.pacer)
        t_read = now()
        # --- decide
        predict_ms, f_predict_ms = self.pacer.prediction_ms(obs)
        d = self.controller.decide(
            release.t_s,
            obs.q,
            obs.dq,
            obs.f,
            f_stale=obs.f_stale,
            state_stale=obs.state_stale,
            drive_mode=obs.drive_mode,
            state_age_s=predict_ms / 1e3,
            feature_age_s=f_predict_ms / 1e3,
            now_s=release.t_s + lateness_ns / 1e3 / 1e6,  # as replay rebuilds it from the record
        )
        t_solve = now()
        # --- write
        self.hw.write(d.torque, sync=release.sync, release_ns=release.release_ns)
        t_write = now()
        # --- record (from here on nothing delays the torque)
        fields = decision_fields(self.controller, d)
        st.stale_states += int(obs.state_stale)  # per tick as recorded, as `hil report` counts
        st.stale_features += int(obs.f_stale)
        st.late_states += int(not obs.state_new)
        st.outages.note(release.index, release.t_s, obs.f_stale or not obs.f_valid)
        if d.mode == "control":
            st.J += fields["cost"] / self.ctx.cfg.rates.control_hz
            st.fallbacks += int(fields["fallback"])
            self._follow_features(obs.f, release.t_s)
        st.ticks += 1
        st.missed_periods += release.missed
        st.solve.add(t_solve - t_read)
        st.lateness.add(lateness_ns)
        st.cycle.add(t_write - wake_ns)
        solve_us = (t_solve - t_read) / 1e3
        cycle_us = (t_write - wake_ns) / 1e3
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
            drives=obs.drives,
        )

    def record(self, cycle: dict[str, Any]) -> bool:
        """The record phase: the cycle to the recorder and, about once a second (every
        ``control_hz`` ticks), the diagnostics; whether the recorder took the cycle."""
        taken = bool(self.ctx.recorder.record_cycle(cycle))
        if self.ctx.counters.ticks % self._diag_every == 0:
            self.ctx.recorder.record_diagnostics(self.diagnostics())
        return taken

    def log_lost(self) -> bool:
        """Lockstep: whether the log can no longer be written (the recorder process died, the
        disk failed); the run then ends now, ``end_reason`` "log lost: ...", since a lockstep
        run exists for its log and no arm waits on it. Realtime runs on: the arm stays under
        control, and the records lost are counted and make the run not clean."""
        error = self.ctx.recorder.error
        if error is None or self.ctx.cfg.controller.clock != "lockstep":
            return False
        self.ctx.counters.end_reason = f"log lost: {error}"
        return True

    def diagnostics(self, final: bool = False) -> dict[str, Any]:
        """The ``/diagnostics`` record of this moment (:mod:`rt_controller.runtime.diagnostics`)."""
        ctx = self.ctx
        return diagnostics.build(
            t_ns=ctx.clock.now_ns(),
            tick=ctx.counters.ticks,
            **self.hw.diagnostics(),
            controller=ctx.counters.controller_block(),
            recorder=ctx.recorder.as_dict(),
            final=final,
            parameters=self.params.counters.as_dict(),
        )

    def _follow_features(self, f: np.ndarray, t_s: float) -> None:
        """The summary's view of the scenario: f at the first law tick and at the last, and
        when the target's jump was seen: a step of more than half the configured jump, from a
        period before ``scenario.jump_time`` on (the emulator starts the scenario with the
        run, to within a period; an earlier step is the arm's fast start)."""
        st = self.ctx.counters
        if st.ticks == 0 or not np.isfinite(st.f_first).all():
            st.f_first = vec2(f)
        sc = self.ctx.cfg.scenario
        due = t_s >= sc.jump_time - self.ctx.cfg.rates.control_period_ns / 1e9
        if sc.disturbance and due and st.jump_seen_s is None and np.isfinite(st.f_final).all():
            jump = math.hypot(sc.f_jump[0] - sc.f0[0], sc.f_jump[1] - sc.f0[1])
            if math.hypot(f[0] - st.f_final[0], f[1] - st.f_final[1]) > jump / 2:
                st.jump_seen_s = t_s
        st.f_final = vec2(f)
