"""The lockstep runner of the emulated DSP: it steps on Sync.

Once per control period the DSP sends ``Sync(k)`` and advances the physics by one period only
after the controller's command for period ``k`` arrived, so a run is deterministic and as fast
as the processes allow. The watchdog counts on the simulation clock at the start of each
period; limits are checked at the end of each control period.

If the command of period ``k`` does not come within ``sync_resend_s`` of real
time, the DSP re-sends the state and ``Sync(k)`` (the command may have been rejected, e.g. on an
E2E counter resync after a controller restart) and keeps doing so until ``reply_timeout_s``,
after which the period counts as missing and the physics advances with the held torque (so the
watchdog can trip in simulation time). Until the first command of a run arrives, the DSP waits
for the controller indefinitely (re-announcing period 0), so the start-up order of the processes
cannot change a lockstep run. Re-sends never change the physics: a run stays deterministic.

Between runs of one set of processes the harness asks for a scenario reset on the
simulator-control channel (:mod:`hal.sim_control`, :meth:`LockstepDsp.request_reset`): the
world starts again from the scenario's start, as in a freshly started emulator.
"""

from __future__ import annotations

import math
import secrets
import threading
import time
from typing import Any

import numpy as np

from hal.can_frames import TorqueCommand
from hal.drive_state import DriveState, FaultReason
from plant_emulator.arm import Encoder
from plant_emulator.dsp_node import DspNode, DspStats

SYNC_RESEND_S = 0.04
"""Real time without the period's command after which state and Sync(k) are re-sent."""


class LockstepDsp(DspNode):
    """The DSP clocked by the controller's answers: one control period per answered Sync."""

    lockstep = True

    def __init__(
        self,
        cfg: Any,
        bus: Any,
        *,
        reply_timeout_s: float | None = None,
        sync_resend_s: float = SYNC_RESEND_S,
        wait_for_controller: bool = True,
        **kwargs: Any,
    ) -> None:
        """``reply_timeout_s`` (default ``dsp.lockstep_reply_timeout_s``), ``sync_resend_s``: the
        waits for a period's command (real time, see the module docstring);
        ``wait_for_controller``: hold period 0 until the first command arrives (``False``
        counts it missing after ``reply_timeout_s`` like any other); the other options are
        :class:`~plant_emulator.dsp_node.DspNode`'s."""
        super().__init__(cfg, bus, **kwargs)
        self.reply_timeout_s = (
            cfg.dsp.lockstep_reply_timeout_s if reply_timeout_s is None else reply_timeout_s
        )
        self.sync_resend_s = sync_resend_s
        self.sync_tick = 0
        self._awaiting_controller = wait_for_controller
        self._start_seed = self.world.seed
        self._missing_since_command = 0  # missing periods not yet followed by a command
        self._reset_request: tuple[int | None] | None = None
        """A scenario reset asked for (its camera noise seed; None: the seed at start), applied
        between periods (:meth:`reset_scenario`); set by :meth:`request_reset` on any thread."""

    @property
    def scenario_started(self) -> bool:
        """Always: the scenario's clock is the periods answered."""
        return True

    def _take_torque(self, frame: TorqueCommand, now_ns: int) -> bool:
        if frame.tick != self.sync_tick % 65536:  # answers another Sync than the current one
            self.stats.late_commands += 1
            return False
        return super()._take_torque(frame, now_ns)

    def send_sync(self) -> None:
        self._send(self.codec.encode_sync(self.sync_tick))
        self.stats.syncs += 1

    def republish_pose(self) -> None:
        """The period's pose again (same ``seq``), so the vision process answers it again: an
        answer lost on its way (published before the controller's subscription reached the
        hub, say) costs a re-send, not the period's features."""
        if self.pose_sink is not None and self._last_pose is not None:
            self.pose_sink(*self._last_pose)
            self.stats.pose_resends += 1

    def _announce(self) -> None:
        """The state of the current period, then Sync(k)."""
        self.send_state()
        self.send_sync()

    def _await_command(self, stop: threading.Event) -> bool:
        """Wait for the command of the current period; re-send Sync while waiting."""
        start = time.monotonic()
        resend_at = start + self.sync_resend_s
        deadline = None if self._awaiting_controller else start + self.reply_timeout_s
        while not stop.is_set():
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                return False
            if now >= resend_at:
                self.republish_pose()
                self._announce()
                self.stats.sync_resends += 1
                if self._awaiting_controller:
                    self.send_status()
                resend_at = now + self.sync_resend_s
            wait = resend_at - now if deadline is None else min(resend_at, deadline) - now
            msg = self.bus.recv(timeout=min(max(wait, 0.0), 0.05))
            if msg is not None and self.handle(msg, self._sim_ns()) is not None:
                self._awaiting_controller = False
                return True
            if self._reset_request is not None:
                return False
        return False

    def _await_enable(self, stop: threading.Event) -> bool:
        """Before period 0: publish the joint state (no pose, no Sync) until the
        controller arms the DSP, so every subscriber is in place when period 0 starts."""
        resend_at = 0.0
        while not stop.is_set() and not self.armed:
            if self._reset_request is not None:
                self.reset_scenario()
            now = time.monotonic()
            if now >= resend_at:
                self.send_state()
                self.send_status()
                resend_at = now + self.sync_resend_s
            msg = self.bus.recv(timeout=min(max(resend_at - now, 0.0), 0.05))
            if msg is not None:
                self.handle(msg, self._sim_ns())
        return self.armed

    def lockstep_period(self, stop: threading.Event) -> bool:
        """Publish pose, state and Sync(k); wait for the answer; advance one control period.

        Returns ``False`` (without advancing) when ``stop`` was set before the period's command
        arrived.
        """
        if self._awaiting_controller and not self._await_enable(stop):
            return False
        self.publish_pose()
        self._announce()
        answered = self._await_command(stop)
        if self._reset_request is not None:  # the period is void: next is period 0 of a new run
            self.reset_scenario()
            return True
        if not answered:
            if stop.is_set():
                return False
            self.stats.missing_periods += 1
            self._missing_since_command += 1
        else:
            self.stats.skipped_periods += self._missing_since_command
            self.stats.skipped_by_run[-1] += self._missing_since_command
            self._missing_since_command = 0
        self.check_watchdog(self._sim_ns())
        self.advance_period()
        self.sync_tick += 1
        return True

    def advance_period(self) -> None:
        """One control period of physics and sensors in one compiled call."""
        k0 = self.world.step_index
        self.world.hold(self.applied_torque(), self.substeps, self.encoder)
        self.stats.physics_steps += self.substeps
        self.check_limits()  # lockstep: at the end of each control period
        if self.world.step_index // self.status_every != k0 // self.status_every:
            self.send_status()

    def _sim_ns(self) -> int:
        return round(self.world.t * 1e9)

    def request_reset(self, seed: int | None = None) -> bool:
        """Ask for a scenario reset (the simulator-control channel, :mod:`hal.sim_control`;
        any thread): applied at the next period boundary, whatever the drive state, as a
        restarted emulator would. ``seed``: the new run's camera noise seed (None: the one at
        start)."""
        self._reset_request = (seed,)
        return True

    def reset_scenario(self) -> None:
        """Apply the requested scenario reset. The world goes back to the scenario's start
        (simulation time 0, the configured initial state) with fresh sensors, the DSP takes a
        new session id, its drive goes to switch-on disabled (a fault cleared) and it holds
        period 0 until the controller arms it again, as a freshly started emulator does; its
        DspStatus (drive state switch-on disabled, Tick 0, the new session) tells the
        controller that every frame after it is of the new run. Codec counters and the
        freshness values go on (replay protection spans runs). The world's camera noise
        restarts from the seed the reset named (else the one at start), and ``on_reset`` hands
        that seed on to the vision link."""
        request, self._reset_request = self._reset_request, None
        seed = None if request is None else request[0]
        self.world.seed = self._start_seed if seed is None else seed
        self.world.reset()
        self.drive.state, self.drive.fault_reason = DriveState.SWITCH_ON_DISABLED, FaultReason.NONE
        self.encoder = Encoder(self.world.q, self.world.dq, self.encoder_lsb, self.filter_gain)
        self.tau_cmd = np.zeros(2)
        self.last_cmd_ns = None
        self.last_cmd_tick = -1
        self.sync_tick = 0
        self._missing_since_command = 0
        self.pose_seq = 0
        self._last_pose = None
        self._awaiting_controller = True
        old = self.session
        while self.session == old:
            self.session = secrets.randbelow(0xFFFF) + 1
        self.stats.session = self.session
        self.stats.scenario_resets += 1
        self.stats.skipped_by_run.append(0)
        if self.on_reset is not None:
            self.on_reset(seed)
        self.send_status()

    def run(self, stop: threading.Event, duration_s: float = 0.0) -> DspStats:
        """Control periods back to back on the simulation clock (the watchdog counts periods).

        ``duration_s`` is simulated time (0 = until ``stop``).
        """
        periods = math.floor(duration_s * self.cfg.rates.control_hz + 1e-9) if duration_s else None
        while not stop.is_set() and (periods is None or self.sync_tick < periods):
            if not self.lockstep_period(stop):
                break
        self._finish()
        return self.stats


__all__ = ["SYNC_RESEND_S", "LockstepDsp"]
