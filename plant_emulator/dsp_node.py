"""The emulated DSP node: arm physics behind the rig's CAN interface.

It applies the latest valid :class:`~hal.can_codec.TorqueCommand` (saturated by the amplifier),
publishes quantised joint angles and a filtered velocity estimate, reports :class:`DspStatus`,
and runs a watchdog that removes torque when commands stop. Two clock modes:

* **realtime**: physics follows ``time.monotonic_ns()`` at ``rates.physics_hz``;
* **lockstep**: once per control period the DSP sends ``Sync(k)`` and advances the physics by
  one period only after the controller's command for period ``k`` arrived, so a run is
  deterministic and as fast as the processes allow.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import can
import numpy as np

from hal.can_codec import RAD_PER_COUNT, DspCodec, DspCommand, DspControl, DspStatus, TorqueCommand
from hal.config import RigConfig
from plant_emulator.camera import CameraPose
from plant_emulator.world import World

PoseSink = Callable[[int, int, CameraPose, bool], None]
"""Called with (seq, sim_time_ns, pose, lockstep) whenever the camera pose is published."""

LOCKSTEP_REPLY_TIMEOUT_S = 0.5
"""Real time the lockstep DSP waits for the command of one period before counting it missing."""


@dataclass
class DspStats:
    """Counters of one DSP run."""

    physics_steps: int = 0
    commands: int = 0
    state_frames: int = 0
    status_frames: int = 0
    syncs: int = 0
    watchdog_trips: int = 0
    late_commands: int = 0
    """Lockstep: commands answering an older Sync (ignored)."""
    missing_periods: int = 0
    """Lockstep: periods with no command before the reply timeout."""
    send_errors: int = 0
    rejected: dict[str, int] = field(default_factory=dict)


class DspNode:
    """One emulated DSP on one bus. Not thread-safe: drive it from a single thread."""

    def __init__(
        self,
        cfg: RigConfig,
        bus: can.BusABC,
        *,
        lockstep: bool = False,
        pose_sink: PoseSink | None = None,
        world: World | None = None,
    ) -> None:
        self.cfg = cfg
        self.bus = bus
        self.lockstep = lockstep
        self.pose_sink = pose_sink
        self.world = world or World(cfg)
        self.codec = DspCodec()
        self.stats = DspStats()
        rates = cfg.rates
        self.substeps = rates.substeps
        self.control_period_ns = rates.control_period_ns
        self.physics_period_ns = round(1e9 / rates.physics_hz)
        self.state_every = max(1, round(rates.physics_hz / rates.state_hz))
        self.status_every = max(1, round(rates.physics_hz / rates.status_hz))
        self.pose_every = self.state_every
        self.watchdog_ns = round(cfg.dsp.watchdog_periods * self.control_period_ns)
        self.encoder_lsb = 2 * math.pi / cfg.dsp.encoder_counts
        fc = cfg.dsp.velocity_filter_hz
        dt = 1.0 / rates.physics_hz
        self.filter_gain = 1.0 - math.exp(-2 * math.pi * fc * dt) if fc > 0 else 1.0
        # Amplifier and watchdog state.
        self.armed = False
        self.tripped = False
        self.tau_cmd = np.zeros(2)
        self.last_cmd_ns: int | None = None
        self.last_cmd_tick = -1
        self.sync_tick = 0
        self.pose_seq = 0
        self._q_enc = self._encode_angles(self.world.q)
        self._dq_est = np.array(self.world.dq, dtype=float)

    # --- sensors ----------------------------------------------------------------------------
    def _encode_angles(self, q: np.ndarray) -> np.ndarray:
        return np.round(q / self.encoder_lsb) * self.encoder_lsb

    def _sample_sensors(self) -> None:
        """Encoder quantisation and the first-order filtered difference velocity estimate."""
        q_enc = self._encode_angles(self.world.q)
        raw = (q_enc - self._q_enc) / self.world.dt
        self._dq_est += self.filter_gain * (raw - self._dq_est)
        self._q_enc = q_enc

    # --- CAN --------------------------------------------------------------------------------
    def _send(self, msg: can.Message) -> None:
        try:
            self.bus.send(msg)
        except can.CanError:
            self.stats.send_errors += 1

    def send_state(self) -> None:
        sample = self.world.step_index % 16
        q = (float(self._q_enc[0]), float(self._q_enc[1]))
        dq = (float(self._dq_est[0]), float(self._dq_est[1]))
        for msg in self.codec.encode_state(q, dq, sample):
            self._send(msg)
        self.stats.state_frames += 1

    def send_status(self) -> None:
        st = self.codec.stats
        status = DspStatus(
            torque_enabled=self.torque_enabled,
            watchdog_tripped=self.tripped,
            torque_saturated=bool(np.any(np.abs(self.tau_cmd) > np.array(self.cfg.robot.tau_max))),
            lockstep=self.lockstep,
            rejected_frames=min(st.rejected, 255),
            watchdog_trips=min(self.stats.watchdog_trips, 255),
            tick=self.sync_tick,
        )
        self._send(self.codec.encode_status(status))
        self.stats.status_frames += 1

    def publish_pose(self) -> None:
        if self.pose_sink is not None:
            sim_ns = round(self.world.t * 1e9)
            self.pose_sink(self.pose_seq, sim_ns, self.world.pose(), self.lockstep)
            self.pose_seq += 1

    @property
    def torque_enabled(self) -> bool:
        return self.armed and not self.tripped

    def handle(self, msg: can.Message, now_ns: int) -> TorqueCommand | None:
        """Apply one received frame; returns the torque command it carried (if valid)."""
        frame = self.codec.decode_command(msg, now_ns)
        if isinstance(frame, DspControl):
            if frame.command is DspCommand.ENABLE:
                self.armed, self.tripped = True, False
                self.last_cmd_ns = now_ns
            else:
                self.armed = False
                self.tau_cmd = np.zeros(2)
            return None
        if isinstance(frame, TorqueCommand):
            self.stats.commands += 1
            if self.lockstep and frame.tick != self.sync_tick % 65536:
                self.stats.late_commands += 1
                return None
            self.last_cmd_ns = now_ns
            self.last_cmd_tick = frame.tick
            self.tau_cmd = np.array([frame.tau1, frame.tau2]) if frame.enable else np.zeros(2)
            return frame
        return None

    def drain(self, now_ns: int) -> None:
        """Handle every frame already waiting on the bus."""
        while True:
            msg = self.bus.recv(timeout=0)
            if msg is None:
                return
            self.handle(msg, now_ns)

    def check_watchdog(self, now_ns: int) -> None:
        """Trip when no valid command arrived for ``dsp.watchdog_periods`` control periods."""
        if not self.torque_enabled or self.last_cmd_ns is None:
            return
        if now_ns - self.last_cmd_ns > self.watchdog_ns:
            self.tripped = True
            self.tau_cmd = np.zeros(2)
            self.stats.watchdog_trips += 1

    def applied_torque(self) -> np.ndarray:
        return self.tau_cmd if self.torque_enabled else np.zeros(2)

    # --- physics ----------------------------------------------------------------------------
    def physics_step(self) -> None:
        """One physics step with the held torque, then sensors and periodic frames."""
        self.world.step(self.applied_torque())
        self._sample_sensors()
        self.stats.physics_steps += 1
        k = self.world.step_index
        if not self.lockstep:
            if k % self.state_every == 0:
                self.send_state()
            if k % self.pose_every == 0:
                self.publish_pose()
        if k % self.status_every == 0:
            self.send_status()

    # --- clock modes ------------------------------------------------------------------------
    def run_realtime(self, stop: threading.Event, duration_s: float = 0.0) -> DspStats:
        """Physics on the monotonic clock; behind schedule it catches up, never drifts."""
        start = time.monotonic_ns()
        self.send_state()
        self.publish_pose()
        end = start + round(duration_s * 1e9) if duration_s > 0 else None
        while not stop.is_set():
            now = time.monotonic_ns()
            if end is not None and now >= end:
                break
            self.drain(now)
            self.check_watchdog(now)
            due = (now - start) // self.physics_period_ns
            while self.world.step_index < due:
                self.physics_step()
            next_ns = start + (self.world.step_index + 1) * self.physics_period_ns
            delay = (next_ns - time.monotonic_ns()) / 1e9
            if delay > 0:
                time.sleep(delay)
        self._finish()
        return self.stats

    def lockstep_period(self, stop: threading.Event) -> None:
        """Publish pose, state and Sync(k); wait for the answer; advance one control period."""
        self.publish_pose()
        self.send_state()
        self._send(self.codec.encode_sync(self.sync_tick))
        self.stats.syncs += 1
        deadline = time.monotonic() + LOCKSTEP_REPLY_TIMEOUT_S
        answered = False
        while not answered and not stop.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            msg = self.bus.recv(timeout=min(remaining, 0.05))
            if msg is not None:
                answered = self.handle(msg, self._sim_ns()) is not None
        if not answered:
            self.stats.missing_periods += 1
        self.check_watchdog(self._sim_ns())
        for _ in range(self.substeps):
            self.physics_step()
        self.sync_tick += 1

    def _sim_ns(self) -> int:
        return round(self.world.t * 1e9)

    def run_lockstep(self, stop: threading.Event, duration_s: float = 0.0) -> DspStats:
        """Control periods back to back on the simulation clock (the watchdog counts periods)."""
        periods = math.floor(duration_s * self.cfg.rates.control_hz + 1e-9) if duration_s else None
        while not stop.is_set() and (periods is None or self.sync_tick < periods):
            self.lockstep_period(stop)
        self._finish()
        return self.stats

    def run(self, stop: threading.Event, duration_s: float = 0.0) -> DspStats:
        runner = self.run_lockstep if self.lockstep else self.run_realtime
        return runner(stop, duration_s)

    def _finish(self) -> None:
        """Torque off and a last status frame."""
        self.armed = False
        self.tau_cmd = np.zeros(2)
        self.send_status()
        self.stats.rejected = self.codec.stats.as_dict()


__all__ = ["RAD_PER_COUNT", "DspNode", "DspStats"]
