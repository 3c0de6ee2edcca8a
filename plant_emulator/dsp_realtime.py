"""The realtime runner of the emulated DSP: its own frame clock.

The world holds its initial state (simulation time 0, joint state, status and camera pose still
published at their rates) until the first TorqueCommand that applies torque (Enable = 1, drive
*operation enabled*): the scenario's t = 0 is the controller's first law tick, however long it
took to start, as in lockstep. From then on physics follows ``time.monotonic_ns()`` at
``rates.physics_hz`` (a re-arm after a fault continues the run, it never restarts the
scenario); the joint state goes out once per control period, ``dsp.state_lead_us`` before the
controller's next tick (:class:`CommandPhase` learns the controller's phase from when its torque
commands arrive, less the delay after its release each one carries in ``Tick``), as a DSP
synchronised to its master's cycle would send them, or with ``dsp.state_sync = free`` at
``rates.state_hz`` on the DSP's own clock.

Watchdog and limits are evaluated at the scheduled time of every physics step, so a
descheduled emulator process still removes the torque at the right physics step. A scenario
reset (:mod:`hal.sim_control`) is refused: a realtime arm is not rewound.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from typing import Any

from hal.can_frames import RELEASE_DELAY_SATURATED, TorqueCommand
from plant_emulator.dsp_node import DspNode, DspStats


class CommandPhase:
    """Where in its period the controller's cycle runs, learnt from when its commands arrive.

    Each observation is a command's arrival less the delay after its release that the command
    reports (``TorqueCommand.Tick`` in realtime): the controller's release plus the transport
    and up to one physics step of this loop. The earliest of the last ``window`` (modulo the
    period, taken around the newest one so a phase near the period boundary does not wrap) is
    the best estimate of the tick; later ones only mean a busier machine.
    """

    def __init__(self, period_ns: int, window: int = 16) -> None:
        self.period_ns = period_ns
        self._recent: collections.deque[int] = collections.deque(maxlen=window)
        self.residue_ns: int | None = None
        """The estimate: tick times are ``residue_ns`` modulo the period (``None``: unknown)."""

    def observe(self, t_ns: int) -> None:
        p = self.period_ns
        self._recent.append(t_ns % p)
        ref, half = self._recent[-1], p // 2
        self.residue_ns = (ref + min((r - ref + half) % p - half for r in self._recent)) % p

    def snap(self, t_ns: int) -> int:
        """The tick nearest ``t_ns`` on the learnt phase (``t_ns`` itself while unknown): one
        command's release estimate is late by its own transport and send time, the phase by
        the least of the window's."""
        if self.residue_ns is None:
            return t_ns
        p = self.period_ns
        return t_ns - ((t_ns - self.residue_ns + p // 2) % p - p // 2)

    def reset(self) -> None:
        self._recent.clear()
        self.residue_ns = None


class RealtimeDsp(DspNode):
    """The DSP on its own clock (``time.monotonic_ns()``; tests drive :meth:`service` with a
    fake one)."""

    lockstep = False

    def __init__(self, cfg: Any, bus: Any, **kwargs: Any) -> None:
        """The options of :class:`~plant_emulator.dsp_node.DspNode`."""
        super().__init__(cfg, bus, **kwargs)
        self.state_sync = cfg.dsp.state_sync == "command"
        self.state_lead_ns = round(cfg.dsp.state_lead_us * 1e3)
        self._states_owed = 0
        """States due during a catch-up not yet sent (:meth:`physics_step`)."""
        self.phase = CommandPhase(self.control_period_ns)
        self._t0_ns = 0
        self._held_steps = 0
        """Physics periods passed while the world held its initial state."""

    def _take_torque(self, frame: TorqueCommand, now_ns: int) -> bool:
        if frame.tick < RELEASE_DELAY_SATURATED:
            # realtime Tick: how long after the controller's release it was sent
            self.phase.observe(now_ns - frame.tick * 1000)
        super()._take_torque(frame, now_ns)
        if frame.enable and self.torque_enabled and not self.scenario_started:
            # t = 0 at the command's release (Tick: how long after it the frame left)
            delay_ns = frame.tick * 1000 if frame.tick < RELEASE_DELAY_SATURATED else 0
            self.start_scenario(max(self._t0_ns, self.phase.snap(now_ns - delay_ns)))
        return True

    def _forced_on(self) -> None:
        if not self.scenario_started:  # forced on: the held world starts now
            self.start_scenario(self._t0_ns + self._held_steps * self.physics_period_ns)

    # --- physics ----------------------------------------------------------------------------
    def physics_step(self, last: bool = True) -> None:
        """One physics step with the held torque, then sensors and periodic frames.

        ``last = False``: more steps follow at once (a late process catching up); a joint
        state due now waits for the last of them, so that it goes out as a sample of the
        world when it is sent, as a real DSP's would, and not as an old one that looks fresh.
        """
        self.world.hold(self.applied_torque(), 1, self.encoder)
        self.stats.physics_steps += 1
        self.check_limits()
        k = self.world.step_index
        due = self._state_due_at(k)
        if due and not last:
            self._states_owed += 1
        elif last and (due or self._states_owed):
            self.stats.states_late += self._states_owed > 0
            self.stats.states_merged += self._states_owed + due - 1
            self._states_owed = 0
            self.send_state()
        # The camera watches the arm, not the CAN bus: its pose keeps the world's rate.
        if k % self.pose_every == 0:
            self.publish_pose()
        if k % self.status_every == 0:
            self.send_status()

    def _state_due_at(self, k: int) -> bool:
        """Realtime: whether the joint state goes out after physics step ``k``."""
        return self.state_due(k) if self.state_sync else k % self.state_every == 0

    def state_due(self, k: int) -> bool:
        """``state_sync = command``: whether the sample after physics step ``k`` goes out.

        One step per control period: the one whose time lies ``state_lead_ns`` (up to a step)
        before the controller's next tick, the lead taken modulo the period (at 500 Hz the
        default 3 ms lead samples 1 ms before the tick). Until the controller's phase is known,
        or once its commands stopped for a watchdog time, on the DSP's own control-period
        clock; when a period is a single physics step (1 kHz), after every step. A short
        period once got a state after every step whenever it was not longer than the lead:
        two per period at 500 Hz, twice the frames the controller decodes on its tick.
        """
        period, step = self.control_period_ns, self.physics_period_ns
        if period <= step:
            return True
        t_k = self._t0_ns + k * step
        phase = self.phase.residue_ns
        if phase is None or self.last_cmd_ns is None or t_k - self.last_cmd_ns > self.watchdog_ns:
            return k % self.substeps == 0
        # the step whose time lies within one step after (tick - lead), modulo the period
        # (lead 0: the step at the tick itself; a lead of a period or more wraps around)
        return (t_k - phase + self.state_lead_ns) % period < step

    # --- the frame clock ----------------------------------------------------------------------
    @property
    def scenario_started(self) -> bool:
        """Once a command applied torque (the scenario's t = 0)."""
        return self.stats.scenario_start_ns is not None

    def start_scenario(self, t0_ns: int) -> None:
        """Realtime: the scenario's t = 0 falls at ``t0_ns`` (DSP clock): physics step 0
        begins there, from the initial state the world held until then."""
        self._t0_ns = t0_ns
        self.stats.scenario_start_ns = t0_ns

    def start_realtime(self, now_ns: int) -> None:
        """Realtime: the world holds its initial state from ``now_ns`` until the scenario
        starts (:meth:`start_scenario`); sends the initial state, status and pose."""
        self._t0_ns = now_ns
        self._held_steps = 0
        self.send_state()
        self.send_status()
        self.publish_pose()

    def _hold(self, now_ns: int) -> int:
        """Realtime, before the scenario starts: no physics, but the joint state, the camera
        pose and the status go out at their rates, and the watchdog armed by an ENABLE is
        evaluated, as after the start. Periods missed by a late process are skipped, not
        caught up (the samples would all be the same). Returns when the next period is due."""
        period = self.physics_period_ns
        due = (now_ns - self._t0_ns) // period
        if due > self._held_steps:
            window = max(self.state_every, self.status_every, self.substeps)
            steps = range(max(self._held_steps, due - window) + 1, due + 1)
            self._held_steps = due
            self.check_watchdog(now_ns)
            if any(self._state_due_at(k) for k in steps):
                self.send_state()
                self.stats.held_states += 1
            if any(k % self.pose_every == 0 for k in steps):
                self.publish_pose()
            if any(k % self.status_every == 0 for k in steps):
                self.send_status()
        return self._t0_ns + (self._held_steps + 1) * period

    def service(self, now_ns: int) -> int:
        """Realtime: handle the waiting frames, then run every physics step due by ``now_ns``
        (before the scenario starts: :meth:`_hold`).

        The watchdog is evaluated at each step's scheduled time, so torque goes off at the
        right physics step even when the process was late. Returns when the next step is due.
        The clock is a parameter: tests drive this with a fake clock.
        """
        self.drain(now_ns)
        if not self.scenario_started:
            return self._hold(now_ns)
        period = self.physics_period_ns
        due = (now_ns - self._t0_ns) // period
        if self.world.step_index < due:
            late = now_ns - (self._t0_ns + (self.world.step_index + 1) * period)
            self.stats.max_lateness_ns = max(self.stats.max_lateness_ns, late)
        while self.world.step_index < due:
            self.check_watchdog(self._t0_ns + self.world.step_index * period)
            self.physics_step(last=self.world.step_index + 1 == due)
        return self._t0_ns + (self.world.step_index + 1) * period

    def idle(self, until_ns: int, clock: Callable[[], int] = time.monotonic_ns) -> None:
        """Realtime, between physics steps: handle each frame when it arrives, as a CAN receive
        interrupt would, until ``until_ns``. A frame's arrival time is what dates it: the
        scenario's t = 0 (a command's release) and the controller's phase are taken from it, so
        they are not a step late, which would shift every torque by up to a step against the
        ticks and change the run."""
        while (left_ns := until_ns - clock()) > 0:
            msg = self.bus.recv(timeout=left_ns / 1e9)
            if msg is None:
                return
            self.handle(msg, clock())

    def run(self, stop: threading.Event, duration_s: float = 0.0) -> DspStats:
        """Physics on the monotonic clock; behind schedule it catches up, never drifts."""
        self.warm_up()
        start = time.monotonic_ns()
        self.start_realtime(start)
        end = start + round(duration_s * 1e9) if duration_s > 0 else None
        while not stop.is_set():
            now = time.monotonic_ns()
            if end is not None and now >= end:
                break
            self.idle(self.service(now))
        # Frames that arrived before the stop are handled (and counted), never silently lost.
        self.drain(time.monotonic_ns())
        self._finish()
        return self.stats


__all__ = ["CommandPhase", "RealtimeDsp"]
