"""The emulated DSP: arm physics behind the rig's CAN interface, the device logic both clock
modes share.

It applies the latest valid :class:`~hal.can_frames.TorqueCommand` (saturated by the amplifier),
publishes quantised joint angles and a filtered velocity estimate, reports :class:`DspStatus`,
and runs a watchdog that removes torque when commands stop. :class:`DspNode` is that device;
what paces it is one runner per clock mode, as the controller has one pacer per mode:

* :class:`~plant_emulator.dsp_realtime.RealtimeDsp`: its own frame clock (physics on
  ``time.monotonic_ns()``, the joint state in step with the controller's cycle);
* :class:`~plant_emulator.dsp_lockstep.LockstepDsp`: steps on Sync (one control period per
  answered ``Sync(k)``; the harness's scenario reset, :mod:`hal.sim_control`).

:func:`plant_emulator.dsp.make_dsp` picks the runner for a clock mode.

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
"""

from __future__ import annotations

import dataclasses
import math
import secrets
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from hal.can_codec import DspCodec
from hal.can_database import signal_range
from hal.can_frames import RAD_PER_COUNT, DspControl, DspStatus, TorqueCommand
from hal.config import RigConfig
from hal.drive_state import Drive, DriveState, DspCommand, FaultReason
from hal.joint_client import DRAIN_MAX_FRAMES
from hal.secoc import rig_key
from plant_emulator.arm import Encoder
from plant_emulator.camera import CameraPose
from plant_emulator.world import World

PoseSink = Callable[[int, int, CameraPose, bool], None]
"""Called with (seq, sim_time_ns, pose, lockstep) whenever the camera pose is published."""


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
    skipped_periods: int = 0
    """Lockstep: the missing periods that a later command of the run followed: the physics
    advanced with the held torque while the controller was still running (a host too slow
    for the reply timeout), so the run is not the deterministic one. Those after the run's
    last command (it had ended, or died: the watchdog tells) are not in it."""
    skipped_by_run: list[int] = field(default_factory=lambda: [0])
    """Lockstep: ``skipped_periods`` by run of a plan, the first run's first (one entry per
    scenario: a reset starts the next), so a plan names the run that was not deterministic."""
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


class DspNode:
    """The emulated DSP's device logic; a clock mode's runner (a subclass) paces it with
    :meth:`run`. Not thread-safe (but :meth:`request_reset`): drive it from a single thread."""

    lockstep = False
    """The clock mode (``DspStatus.Lockstep``, the camera poses' lockstep flag)."""

    def __init__(
        self,
        cfg: RigConfig,
        bus: can.BusABC,
        *,
        pose_sink: PoseSink | None = None,
        world: World | None = None,
        session: int | None = None,
        key: bytes | None = None,
        on_reset: Callable[[int | None], None] | None = None,
        on_fault: Callable[[str], None] | None = None,
    ) -> None:
        """``session``: the id reported in ``DspStatus.Session`` (default: random, non-zero);
        ``key``: the rig key (default: ``cfg.transport.key_file``, else this process's
        ephemeral key, see :mod:`hal.secoc`); ``on_reset``: called with the new run's camera
        noise seed (None when the reset named none) when a scenario reset
        (:meth:`request_reset`) is applied, e.g. to give the pose link a new source id and the
        seed; ``on_fault``: called with :attr:`DspStats.last_fault` (one line) when the drive
        enters FAULT, e.g. to say so on stderr the moment it happens."""
        self.cfg = cfg
        self.bus = bus
        self.pose_sink = pose_sink
        self.on_reset = on_reset
        self.on_fault = on_fault
        self.world = world or World(cfg)
        self.codec = DspCodec(key=key if key is not None else rig_key(cfg))
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
        self.pose_seq = 0
        self._last_pose: tuple[int, int, CameraPose, bool] | None = None
        """The last pose published (a lockstep re-send publishes it again)."""
        self.encoder = Encoder(self.world.q, self.world.dq, self.encoder_lsb, self.filter_gain)

    def run(self, stop: Any, duration_s: float = 0.0) -> DspStats:
        """Serve the arm until ``stop`` is set or ``duration_s`` passed; the runner's rule."""
        raise NotImplementedError

    @property
    def scenario_started(self) -> bool:
        """Whether the scenario's clock runs (the runner's rule)."""
        raise NotImplementedError

    def request_reset(self, seed: int | None = None) -> bool:
        """Ask for a scenario reset (the simulator-control channel, :mod:`hal.sim_control`;
        any thread). Refused here (counted, False): only the lockstep runner rewinds its world
        (:meth:`~plant_emulator.dsp_lockstep.LockstepDsp.request_reset`)."""
        self.stats.resets_refused += 1
        return False

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

    def publish_pose(self) -> None:
        if self.pose_sink is not None:
            sim_ns = round(self.world.t * 1e9)
            self._last_pose = (self.pose_seq, sim_ns, self.world.pose(), self.lockstep)
            self.pose_sink(*self._last_pose)
            self.pose_seq += 1

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
            self._forced_on()
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
            if self._take_torque(frame, now_ns):
                accepted = frame
        if self._flags() != before:
            self.send_status()
        return accepted

    def _take_torque(self, frame: TorqueCommand, now_ns: int) -> bool:
        """Hold an authentic torque command; whether it was taken (a runner may refuse one
        that answers no current period)."""
        self._command_seen(now_ns)
        self.last_cmd_tick = frame.tick
        self.tau_cmd = np.array([frame.tau1, frame.tau2]) if frame.enable else np.zeros(2)
        return True

    def _forced_on(self) -> None:
        """:attr:`armed` was forced on (tests); a runner may start its held world here."""

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

    def warm_up(self) -> None:
        """Compile/load the physics kernels on a throw-away world, so the clock's first step is
        not late by the JIT time (seconds under user-mode Linux)."""
        world = World(self.cfg)
        world.hold(np.zeros(2), 1, Encoder(world.q, world.dq, self.encoder_lsb, self.filter_gain))

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


__all__ = ["RAD_PER_COUNT", "DspNode", "DspStats", "PoseSink"]
