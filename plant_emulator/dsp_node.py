"""The emulated DSP node: arm physics behind the rig's CAN interface.

It applies the latest valid :class:`~hal.can_frames.TorqueCommand` (saturated by the amplifier),
publishes quantised joint angles and a filtered velocity estimate, reports :class:`DspStatus`,
and runs a watchdog that removes torque when commands stop. Two clock modes:

* **realtime**: the world holds its initial state (simulation time 0, joint state, status and
  camera pose still published at their rates) until the first TorqueCommand that applies
  torque (Enable = 1, drive *operation enabled*): the scenario's t = 0 is the controller's
  first law tick, however long it took to start, as in lockstep. From then on physics follows
  ``time.monotonic_ns()`` at ``rates.physics_hz`` (a re-arm after a fault continues the run,
  it never restarts the scenario); the joint
  state goes out once per control period, ``dsp.state_lead_us`` before the
  controller's next tick (:class:`CommandPhase` learns the controller's phase from when its
  torque commands arrive, less the delay after its release each one carries in ``Tick``), as a
  DSP synchronised to its master's cycle would send them, or with
  ``dsp.state_sync = free`` at ``rates.state_hz`` on the DSP's own clock;
* **lockstep**: once per control period the DSP sends ``Sync(k)`` and advances the physics by
  one period only after the controller's command for period ``k`` arrived, so a run is
  deterministic and as fast as the processes allow.

Watchdog: a trip (FAULT, reason WATCHDOG) happens when ``dsp.watchdog_periods`` control
periods passed since the last valid command (TorqueCommand or DspControl ENABLE), on the DSP's
own clock: in realtime it is evaluated at the scheduled time of every physics step (so a
descheduled emulator process still removes the torque at the right physics step), in lockstep on
the simulation clock at the start of each period. Every change of DriveState, FaultReason or
TorqueSaturated sends a DspStatus at once (besides the periodic ones), and
:attr:`DspStats.last_trip_latency_ns` records how long after its last command the DSP tripped.

Drive state (``hal.drive_state``, CiA 402 style): the node boots in SWITCH_ON_DISABLED with a
random ``session`` id (``DspStatus.Session``); torque reaches the arm only in OPERATION_ENABLED.
A watchdog trip, a joint beyond ``dsp.q_min``/``dsp.q_max`` or faster than ``dsp.dq_max`` (with
operation enabled) or an encoder value the CAN frame cannot carry (any state) puts the drive in
FAULT with that reason: torque off at once, a DspStatus goes out, ENABLE is refused until
FAULT_RESET. Out-of-frame joint states are withheld, never pinned. Limits are checked after each
physics step in realtime and at the end of each control period in lockstep.

Lockstep details: if the command of period ``k`` does not come within ``sync_resend_s`` of real
time, the DSP re-sends the state and ``Sync(k)`` (the command may have been rejected, e.g. on an
E2E counter resync after a controller restart) and keeps doing so until ``reply_timeout_s``,
after which the period counts as missing and the physics advances with the held torque (so the
watchdog can trip in simulation time). Until the first command of a run arrives, the DSP waits
for the controller indefinitely (re-announcing period 0), so the start-up order of the processes
cannot change a lockstep run. Re-sends never change the physics: a run stays deterministic.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from hal.can_codec import DspCodec
from hal.can_database import signal_range
from hal.can_frames import (
    RAD_PER_COUNT,
    RELEASE_DELAY_SATURATED,
    DspControl,
    DspStatus,
    TorqueCommand,
)
from hal.config import RigConfig
from hal.drive_state import Drive, DriveState, DspCommand, FaultReason
from hal.joint_client import DRAIN_MAX_FRAMES
from hal.secoc import rig_key
from plant_emulator.arm import Encoder
from plant_emulator.camera import CameraPose
from plant_emulator.world import World

PoseSink = Callable[[int, int, CameraPose, bool], None]
"""Called with (seq, sim_time_ns, pose, lockstep) whenever the camera pose is published."""

LOCKSTEP_REPLY_TIMEOUT_S = 0.5
"""Real time the lockstep DSP waits for the command of one period before counting it missing."""
SYNC_RESEND_S = 0.04
"""Lockstep: real time without the period's command after which state and Sync(k) are re-sent."""


@dataclass
class DspStats:
    """Counters of one DSP run."""

    physics_steps: int = 0
    commands: int = 0
    state_frames: int = 0
    status_frames: int = 0
    syncs: int = 0
    watchdog_trips: int = 0
    sync_resends: int = 0
    """Lockstep: Sync frames sent again because the period's command had not arrived."""
    pose_resends: int = 0
    """Lockstep: camera poses published again with their Sync (the vision process answers
    each again)."""
    late_commands: int = 0
    """Lockstep: commands answering another Sync than the current one (ignored)."""
    missing_periods: int = 0
    """Lockstep: periods with no command before the reply timeout."""
    send_errors: int = 0
    drains_cut: int = 0
    """Drains that stopped at ``DRAIN_MAX_FRAMES`` frames (a bus that had not run dry: a
    flood cannot hold the physics)."""
    last_command_ns: int | None = None
    """DSP clock (monotonic ns in realtime, simulation ns in lockstep) of the last valid command."""
    last_trip_ns: int | None = None
    """DSP clock of the last watchdog trip."""
    last_trip_latency_ns: int | None = None
    """Time from the last valid command to the watchdog trip that followed it (DSP clock): how
    long the arm kept its last torque after the commands stopped."""
    last_command_sim_s: float | None = None
    """Scenario time (the world's clock) of the last valid command."""
    last_trip_sim_s: float | None = None
    """Scenario time of the last watchdog trip (torque off)."""
    max_lateness_ns: int = 0
    """Realtime: the most a physics step ran after its scheduled time (host scheduling)."""
    rejected: dict[str, int] = field(default_factory=dict)
    """Receive verdicts of the DSP's codec (filled in when the run ends)."""
    session: int = 0
    """This DSP process's random id (``DspStatus.Session``)."""
    drive_state: str = DriveState.SWITCH_ON_DISABLED.label
    """Drive state at the end of the run (``operation_enabled``, ``fault``, ...)."""
    fault_reason: str = FaultReason.NONE.label
    """Reason of the fault the run ended in (``none`` when it did not end in FAULT)."""
    faults: dict[str, int] = field(default_factory=dict)
    """Faults entered, by reason (``watchdog``, ``position_limit``, ``velocity_limit``,
    ``encoder``)."""
    last_fault: str | None = None
    """The latest fault in one line (reason, joint, value, limit), for logs."""
    refused_commands: int = 0
    """DspControl commands the drive state refused (e.g. ENABLE in FAULT)."""
    states_withheld: int = 0
    """Joint states not sent because the frame could not carry them (encoder fault)."""
    states_late: int = 0
    """Realtime: joint states that fell due while this process was behind schedule; each went
    out after the catch-up, as a sample of the latest step (a real DSP samples when it sends),
    not as the old sample of the step it was due at."""
    states_merged: int = 0
    """Due states that such a catch-up sample stood in for beyond the first (a catch-up over
    more than one due step sends one state)."""
    scenario_resets: int = 0
    """Lockstep: scenario resets applied (the world back to its start, new session)."""
    resets_refused: int = 0
    """Scenario resets asked of a realtime DSP (refused: a realtime arm is not rewound)."""
    held_states: int = 0
    """Realtime: joint states sent while the world held its initial state (before the
    scenario started; the initial state of :meth:`DspNode.start_realtime` not included)."""
    scenario_start_ns: int | None = None
    """Realtime: the DSP clock at which the scenario's t = 0 fell (the release of the first
    command that applied torque); None while the world still holds its initial state."""

    def as_dict(self) -> dict[str, Any]:
        """Plain counters for ``--json`` (latencies also in ms)."""
        out = dataclasses.asdict(self)
        lat = self.last_trip_latency_ns
        out["last_trip_latency_ms"] = None if lat is None else lat * 1e-6
        out["max_lateness_ms"] = self.max_lateness_ns * 1e-6
        return out


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
        reply_timeout_s: float = LOCKSTEP_REPLY_TIMEOUT_S,
        sync_resend_s: float = SYNC_RESEND_S,
        wait_for_controller: bool = True,
        session: int | None = None,
        key: bytes | None = None,
        on_reset: Callable[[int | None], None] | None = None,
        on_fault: Callable[[str], None] | None = None,
    ) -> None:
        """``reply_timeout_s``, ``sync_resend_s``: lockstep waits (real time, see the module
        docstring); ``wait_for_controller``: in lockstep, hold period 0 until the first command
        arrives (``False`` counts it missing after ``reply_timeout_s`` like any other);
        ``session``: the id reported in ``DspStatus.Session`` (default: random, non-zero);
        ``key``: the rig key (default: ``cfg.transport.key_file``, else this process's
        ephemeral key, see :mod:`hal.secoc`); ``on_reset``: called with the new run's camera
        noise seed (None when the reset named none) when a scenario reset
        (:meth:`request_reset`) is applied, e.g. to give the pose link a new source id and the seed;
        ``on_fault``: called with :attr:`DspStats.last_fault` (one line) when the drive enters
        FAULT, e.g. to say so on stderr the moment it happens."""
        self.cfg = cfg
        self.bus = bus
        self.lockstep = lockstep
        self.pose_sink = pose_sink
        self.on_reset = on_reset
        self.on_fault = on_fault
        self._reset_request: tuple[int | None] | None = None
        """A scenario reset asked for (its camera noise seed; None: the seed at start), applied
        between periods (:meth:`reset_scenario`); set by :meth:`request_reset` on any thread."""
        self.world = world or World(cfg)
        self._start_seed = self.world.seed
        self.codec = DspCodec(key=key if key is not None else rig_key(cfg))
        self.stats = DspStats()
        rates = cfg.rates
        self.substeps = rates.substeps
        self.control_period_ns = rates.control_period_ns
        self.physics_period_ns = round(1e9 / rates.physics_hz)
        self.state_every = max(1, round(rates.physics_hz / rates.state_hz))
        self.status_every = max(1, round(rates.physics_hz / rates.status_hz))
        self.pose_every = self.state_every
        self.state_sync = cfg.dsp.state_sync == "command"
        self.state_lead_ns = round(cfg.dsp.state_lead_us * 1e3)
        self._states_owed = 0
        """States due during a catch-up not yet sent (:meth:`physics_step`)."""
        self.phase = CommandPhase(self.control_period_ns)
        self.watchdog_ns = round(cfg.dsp.watchdog_periods * self.control_period_ns)
        self.encoder_lsb = 2 * math.pi / cfg.dsp.encoder_counts
        fc = cfg.dsp.velocity_filter_hz
        dt = 1.0 / rates.physics_hz
        self.filter_gain = 1.0 - math.exp(-2 * math.pi * fc * dt) if fc > 0 else 1.0
        # Drive state machine, amplifier and watchdog state.
        self.drive = Drive()
        self.session = secrets.randbelow(0xFFFF) + 1 if session is None else int(session)
        self.stats.session = self.session
        self.tau_cmd = np.zeros(2)
        d = cfg.dsp
        self.q_min, self.q_max = np.array(d.q_min, float), np.array(d.q_max, float)
        self.dq_max = np.array(d.dq_max, float)
        self._q_frame = signal_range("JointPosition", "Q1")
        self._dq_frame = signal_range("JointVelocity", "Dq1")
        self._tau_max = np.array(cfg.robot.tau_max, dtype=float)
        self.last_cmd_ns: int | None = None
        self.last_cmd_tick = -1
        self.sync_tick = 0
        self.pose_seq = 0
        self._last_pose: tuple[int, int, CameraPose, bool] | None = None
        """The last pose published (:meth:`republish_pose` sends it again)."""
        self.reply_timeout_s = reply_timeout_s
        self.sync_resend_s = sync_resend_s
        self._awaiting_controller = lockstep and wait_for_controller
        self._t0_ns = 0
        self._held_steps = 0
        """Realtime: physics periods passed while the world held its initial state."""
        self.encoder = Encoder(self.world.q, self.world.dq, self.encoder_lsb, self.filter_gain)

    # --- sensors ----------------------------------------------------------------------------
    # --- CAN --------------------------------------------------------------------------------
    def _send(self, msg: can.Message) -> None:
        try:
            self.bus.send(msg)
        except (can.CanError, OSError):  # a full queue or a vanished peer must not stop the DSP
            self.stats.send_errors += 1

    def send_state(self) -> None:
        """The encoder's angles and velocity estimate; withheld (and the drive faulted with
        ENCODER) when the frame cannot carry them, never pinned to the frame's range."""
        if not self._sensors_in_range():
            self.stats.states_withheld += 1
            return
        sample = self.world.step_index % 16
        q = (float(self.encoder.q[0]), float(self.encoder.q[1]))
        dq = (float(self.encoder.dq[0]), float(self.encoder.dq[1]))
        for msg in self.codec.encode_state(q, dq, sample):
            self._send(msg)
        self.stats.state_frames += 1

    def send_status(self) -> None:
        st = self.codec.stats
        status = DspStatus(
            torque_enabled=self.torque_enabled,
            watchdog_tripped=self.tripped,
            torque_saturated=self.torque_saturated,
            lockstep=self.lockstep,
            rejected_frames=min(st.rejected, 255),
            watchdog_trips=min(self.stats.watchdog_trips, 15),
            tick=self.world.step_index,
            drive_state=self.drive.state,
            fault_reason=self.drive.fault_reason,
            session=self.session,
        )
        self._send(self.codec.encode_status(status))
        self.stats.status_frames += 1

    def send_sync(self) -> None:
        self._send(self.codec.encode_sync(self.sync_tick))
        self.stats.syncs += 1

    def publish_pose(self) -> None:
        if self.pose_sink is not None:
            sim_ns = round(self.world.t * 1e9)
            self._last_pose = (self.pose_seq, sim_ns, self.world.pose(), self.lockstep)
            self.pose_sink(*self._last_pose)
            self.pose_seq += 1

    def republish_pose(self) -> None:
        """Lockstep: the period's pose again (same ``seq``), so the vision process answers it
        again: an answer lost on its way (published before the controller's subscription
        reached the hub, say) costs a re-send, not the period's features."""
        if self.pose_sink is not None and self._last_pose is not None:
            self.pose_sink(*self._last_pose)
            self.stats.pose_resends += 1

    @property
    def torque_enabled(self) -> bool:
        """Drive state OPERATION_ENABLED: the held command reaches the arm."""
        return self.drive.torque_allowed

    @property
    def armed(self) -> bool:
        """Same as :attr:`torque_enabled` (setting it forces the drive state, for tests:
        True -> OPERATION_ENABLED, and a realtime scenario still held starts now;
        False -> READY_TO_SWITCH_ON unless in FAULT)."""
        return self.drive.torque_allowed

    @armed.setter
    def armed(self, value: bool) -> None:
        if value:
            self.drive.state, self.drive.fault_reason = (
                DriveState.OPERATION_ENABLED,
                FaultReason.NONE,
            )
            if not self.scenario_started:  # forced on: the held world starts now
                self.start_scenario(self._t0_ns + self._held_steps * self.physics_period_ns)
        elif self.drive.state is not DriveState.FAULT:
            self.drive.state = DriveState.READY_TO_SWITCH_ON
        if not self.drive.torque_allowed:
            self.tau_cmd = np.zeros(2)

    @property
    def tripped(self) -> bool:
        """In FAULT because of the watchdog (``DspStatus.WatchdogTripped``)."""
        return (
            self.drive.state is DriveState.FAULT and self.drive.fault_reason is FaultReason.WATCHDOG
        )

    @property
    def torque_saturated(self) -> bool:
        """Whether the held command exceeds ``robot.tau_max`` on a joint (the amplifier clips)."""
        return bool(np.any(np.abs(self.tau_cmd) > self._tau_max))

    def _flags(self) -> tuple[object, ...]:
        d = self.drive
        return (d.state, d.fault_reason, self.torque_saturated)

    def handle(self, msg: can.Message, now_ns: int) -> TorqueCommand | None:
        """Apply one received frame; returns the torque command it carried (if valid).

        ``now_ns`` is the DSP clock (monotonic ns in realtime, simulation ns in lockstep). A
        change of a status flag (TorqueEnabled, WatchdogTripped, TorqueSaturated) sends a
        DspStatus right away. Never raises for a bad frame (the codec counts it).
        """
        frame = self.codec.decode_command(msg, now_ns)
        if frame is None:
            return None
        before = self._flags()
        accepted: TorqueCommand | None = None
        if isinstance(frame, DspControl):
            accepted_cmd = self.drive.command(frame.command)
            self.stats.refused_commands = self.drive.refused
            if accepted_cmd and frame.command is DspCommand.ENABLE:
                self._command_seen(now_ns)
                self.check_limits()  # enabling beyond a limit faults at once
            if not self.torque_enabled:
                self.tau_cmd = np.zeros(2)
        else:
            self.stats.commands += 1
            if self.lockstep and frame.tick != self.sync_tick % 65536:
                self.stats.late_commands += 1
            else:
                self._command_seen(now_ns)
                if not self.lockstep and frame.tick < RELEASE_DELAY_SATURATED:
                    # realtime Tick: how long after the controller's release it was sent
                    self.phase.observe(now_ns - frame.tick * 1000)
                self.last_cmd_tick = frame.tick
                self.tau_cmd = np.array([frame.tau1, frame.tau2]) if frame.enable else np.zeros(2)
                if frame.enable and self.torque_enabled and not self.scenario_started:
                    # t = 0 at the command's release (Tick: how long after it the frame left)
                    delay_ns = frame.tick * 1000 if frame.tick < RELEASE_DELAY_SATURATED else 0
                    self.start_scenario(max(self._t0_ns, self.phase.snap(now_ns - delay_ns)))
                accepted = frame
        if self._flags() != before:
            self.send_status()
        return accepted

    def _command_seen(self, now_ns: int) -> None:
        self.last_cmd_ns = now_ns
        self.stats.last_command_ns = now_ns
        self.stats.last_command_sim_s = self.world.t

    def drain(self, now_ns: int) -> None:
        """Handle every frame already waiting on the bus, at most ``DRAIN_MAX_FRAMES``."""
        for _ in range(DRAIN_MAX_FRAMES):
            msg = self.bus.recv(timeout=0)
            if msg is None:
                return
            self.handle(msg, now_ns)
        self.stats.drains_cut += 1

    def check_watchdog(self, now_ns: int) -> bool:
        """Trip when ``dsp.watchdog_periods`` control periods passed without a valid command.

        ``now_ns`` is the DSP clock. Returns whether it tripped now (a DspStatus went out).
        """
        if not self.torque_enabled or self.last_cmd_ns is None:
            return False
        if now_ns - self.last_cmd_ns < self.watchdog_ns:
            return False
        self.stats.watchdog_trips += 1
        self.stats.last_trip_ns = now_ns
        self.stats.last_trip_latency_ns = latency = now_ns - self.last_cmd_ns
        self.stats.last_trip_sim_s = self.world.t
        self.fault(
            FaultReason.WATCHDOG, f"torque off {latency * 1e-6:.1f} ms after the last valid command"
        )
        return True

    def fault(self, reason: FaultReason, detail: str = "") -> bool:
        """Enter FAULT (torque off at once, a DspStatus goes out); False if already faulted."""
        if not self.drive.fault(reason):
            return False
        self.tau_cmd = np.zeros(2)
        self.stats.faults = dict(self.drive.faults)
        self.stats.last_fault = (
            f"{reason.label} at physics step {self.world.step_index} "
            f"(t = {self.world.t:.3f} s): {detail}"
        )
        self.send_status()
        if self.on_fault is not None:
            self.on_fault(self.stats.last_fault)
        return True

    def _sensors_in_range(self) -> bool:
        """Whether the CAN frames can carry the encoder's angles and velocity; if not, the
        drive faults with ENCODER (in any state: a sensor fault, not a motion limit)."""
        q, dq = self.encoder.q, self.encoder.dq
        (qlo, qhi), (vlo, vhi) = self._q_frame, self._dq_frame
        for j in range(2):
            if not qlo <= q[j] <= qhi:
                self.fault(FaultReason.ENCODER, f"q{j + 1} = {q[j]:.4f} rad beyond +-8 rev")
                return False
            if not vlo <= dq[j] <= vhi:
                self.fault(FaultReason.ENCODER, f"dq{j + 1} = {dq[j]:.3f} rad/s beyond the frame")
                return False
        return True

    def check_limits(self) -> bool:
        """Fault on an encoder out of the frame's range (any state) or, with operation enabled,
        a joint beyond ``dsp.q_min``/``dsp.q_max`` or faster than ``dsp.dq_max`` (measured by
        the DSP's own encoder). Returns whether it faulted now."""
        if self.drive.state is DriveState.FAULT:
            return False
        if not self._sensors_in_range():
            return True
        if not self.drive.torque_allowed:
            return False
        q, dq = self.encoder.q, self.encoder.dq
        for j in range(2):
            if not self.q_min[j] <= q[j] <= self.q_max[j]:
                lim = f"[{self.q_min[j]:g}, {self.q_max[j]:g}]"
                return self.fault(
                    FaultReason.POSITION_LIMIT, f"q{j + 1} = {q[j]:.4f} rad not in {lim}"
                )
            if abs(dq[j]) > self.dq_max[j]:
                detail = f"|dq{j + 1}| = {abs(dq[j]):.3f} rad/s > {self.dq_max[j]:g}"
                return self.fault(FaultReason.VELOCITY_LIMIT, detail)
        return False

    def applied_torque(self) -> np.ndarray:
        return self.tau_cmd if self.torque_enabled else np.zeros(2)

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
        if not self.lockstep:
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

    # --- clock modes ------------------------------------------------------------------------
    @property
    def scenario_started(self) -> bool:
        """Lockstep always; realtime once a command applied torque (the scenario's t = 0)."""
        return self.lockstep or self.stats.scenario_start_ns is not None

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

    def warm_up(self) -> None:
        """Compile/load the physics kernels on a throw-away world, so the clock's first step is
        not late by the JIT time (seconds under user-mode Linux)."""
        world = World(self.cfg)
        world.hold(np.zeros(2), 1, Encoder(world.q, world.dq, self.encoder_lsb, self.filter_gain))

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

    def run_realtime(self, stop: threading.Event, duration_s: float = 0.0) -> DspStats:
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

    def _announce(self) -> None:
        """Lockstep: the state of the current period, then Sync(k)."""
        self.send_state()
        self.send_sync()

    def _await_command(self, stop: threading.Event) -> bool:
        """Lockstep: wait for the command of the current period; re-send Sync while waiting."""
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
        """Lockstep, before period 0: publish the joint state (no pose, no Sync) until the
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
        self.check_watchdog(self._sim_ns())
        self.advance_period()
        self.sync_tick += 1
        return True

    def advance_period(self) -> None:
        """Lockstep: one control period of physics and sensors in one compiled call."""
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
        any thread): a lockstep DSP applies it at the next period boundary, whatever its drive
        state, as a restarted emulator would; a realtime DSP refuses (counted) and returns
        False. ``seed``: the new run's camera noise seed (None: the one at start)."""
        if not self.lockstep:
            self.stats.resets_refused += 1
            return False
        self._reset_request = (seed,)
        return True

    def reset_scenario(self) -> None:
        """Lockstep: apply the requested scenario reset. The world goes back to the scenario's
        start (simulation time 0, the configured initial state) with fresh sensors, the DSP
        takes a new session id, its drive goes to switch-on disabled (a fault cleared) and it
        holds period 0 until the controller arms it again, as a freshly started emulator does;
        its DspStatus (drive state switch-on disabled, Tick 0,
        the new session) tells the controller that every frame after it is of the new run.
        Codec counters and the freshness values go on (replay protection spans runs). The
        world's camera noise restarts from the seed the reset named (else the one at start),
        and ``on_reset`` hands that seed on to the vision link."""
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
        self.pose_seq = 0
        self._last_pose = None
        self._states_owed = 0
        self.phase.reset()
        self._awaiting_controller = True
        old = self.session
        while self.session == old:
            self.session = secrets.randbelow(0xFFFF) + 1
        self.stats.session = self.session
        self.stats.scenario_resets += 1
        if self.on_reset is not None:
            self.on_reset(seed)
        self.send_status()

    def run_lockstep(self, stop: threading.Event, duration_s: float = 0.0) -> DspStats:
        """Control periods back to back on the simulation clock (the watchdog counts periods).

        ``duration_s`` is simulated time (0 = until ``stop``).
        """
        periods = math.floor(duration_s * self.cfg.rates.control_hz + 1e-9) if duration_s else None
        while not stop.is_set() and (periods is None or self.sync_tick < periods):
            if not self.lockstep_period(stop):
                break
        self._finish()
        return self.stats

    def run(self, stop: threading.Event, duration_s: float = 0.0) -> DspStats:
        runner = self.run_lockstep if self.lockstep else self.run_realtime
        return runner(stop, duration_s)

    def _finish(self) -> None:
        """Torque off and a last status frame."""
        if self.drive.state is not DriveState.FAULT:
            self.drive.state = DriveState.SWITCH_ON_DISABLED
        self.tau_cmd = np.zeros(2)
        self.send_status()
        self.stats.rejected = self.codec.stats.as_dict()
        self.stats.drive_state = self.drive.state.label
        self.stats.fault_reason = self.drive.fault_reason.label
        self.stats.faults = dict(self.drive.faults)
        self.stats.refused_commands = self.drive.refused


__all__ = ["LOCKSTEP_REPLY_TIMEOUT_S", "RAD_PER_COUNT", "SYNC_RESEND_S", "DspNode", "DspStats"]
