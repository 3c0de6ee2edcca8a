"""Drive state machine (hal.drive_state, pure) and the DSP emulator's drive behaviour.

The DSP is driven with a fake clock (``RealtimeDsp.service``) and fed frames through
``RealtimeDsp.handle``; nothing asserts wall-clock timings.
"""

from __future__ import annotations

import math

import can
import numpy as np
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import ControllerCodec
from hal.can_database import signal_range
from hal.can_frames import DspStatus, JointPosition
from hal.config import RigConfig
from hal.drive_state import (
    MODE_DISARMED,
    MODE_DSP_RESTARTED,
    MODE_ENABLED,
    MODE_FAULT,
    MODE_NO_STATUS,
    Drive,
    DriveEvent,
    DriveMonitor,
    DriveState,
    DspCommand,
    FaultReason,
    next_state,
)
from plant_emulator.dsp_realtime import RealtimeDsp

S = DriveState
C = DspCommand
MS = 1_000_000
T0 = 1_000_000_000_000

# ------------------------------------------------------------------------------ pure rules


@pytest.mark.parametrize(
    ("state", "command", "expected"),
    [
        (S.SWITCH_ON_DISABLED, C.ENABLE, S.OPERATION_ENABLED),
        (S.READY_TO_SWITCH_ON, C.ENABLE, S.OPERATION_ENABLED),
        (S.OPERATION_ENABLED, C.ENABLE, S.OPERATION_ENABLED),
        (S.OPERATION_ENABLED, C.DISABLE, S.READY_TO_SWITCH_ON),
        (S.SWITCH_ON_DISABLED, C.DISABLE, S.READY_TO_SWITCH_ON),
        (S.OPERATION_ENABLED, C.DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),
        (S.READY_TO_SWITCH_ON, C.DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),
        (S.OPERATION_ENABLED, C.FAULT_RESET, S.OPERATION_ENABLED),
        (S.FAULT, C.FAULT_RESET, S.SWITCH_ON_DISABLED),
        (S.FAULT, C.ENABLE, None),
        (S.FAULT, C.DISABLE, None),
        (S.FAULT, C.DISABLE_VOLTAGE, None),
        (S.NOT_READY, C.ENABLE, None),
    ],
)
def test_transition_table(state: DriveState, command: DspCommand, expected: DriveState | None):
    assert next_state(state, command) == expected


def test_every_state_command_pair_is_defined_and_torque_only_when_enabled():
    for state in DriveState:
        for command in DspCommand:
            new = next_state(state, command)
            assert new is None or isinstance(new, DriveState)
            drive = Drive(state=state)
            drive.command(command)
            assert drive.torque_allowed == (drive.state is S.OPERATION_ENABLED)


def test_drive_fault_latches_first_reason_until_reset():
    d = Drive()
    assert d.command(C.ENABLE) and d.torque_allowed
    assert d.fault(FaultReason.POSITION_LIMIT)
    assert not d.fault(FaultReason.WATCHDOG)  # the first reason stays
    assert (d.state, d.fault_reason) == (S.FAULT, FaultReason.POSITION_LIMIT)
    assert not d.command(C.ENABLE) and d.refused == 1 and not d.torque_allowed
    assert d.command(C.FAULT_RESET)
    assert (d.state, d.fault_reason) == (S.SWITCH_ON_DISABLED, FaultReason.NONE)
    assert d.command(C.ENABLE) and d.torque_allowed
    assert d.faults == {"position_limit": 1}


def status(state: DriveState, session: int = 7, reason=FaultReason.NONE) -> DspStatus:
    return DspStatus(
        state is S.OPERATION_ENABLED,
        reason is FaultReason.WATCHDOG,
        drive_state=state,
        fault_reason=reason,
        session=session,
    )


def test_monitor_modes_and_events():
    m = DriveMonitor()
    assert m.update(None).mode == MODE_NO_STATUS
    u = m.update(status(S.SWITCH_ON_DISABLED))
    assert u.mode == MODE_DISARMED and u.events == (DriveEvent.FIRST_STATUS,)
    u = m.update(status(S.OPERATION_ENABLED))
    assert u.mode == MODE_ENABLED and u.may_apply_torque
    assert set(u.events) == {DriveEvent.STATE_CHANGED, DriveEvent.ENABLED}
    same = status(S.OPERATION_ENABLED)
    assert m.update(same).events == () and m.update(same).events == ()
    # a DISABLE from anywhere
    u = m.update(status(S.READY_TO_SWITCH_ON))
    assert u.mode == MODE_DISARMED and DriveEvent.DISARMED in u.events
    m.update(status(S.OPERATION_ENABLED))
    u = m.update(status(S.FAULT, reason=FaultReason.VELOCITY_LIMIT))
    assert u.mode == MODE_FAULT and u.fault is FaultReason.VELOCITY_LIMIT
    assert DriveEvent.FAULT in u.events and DriveEvent.DISARMED not in u.events
    u = m.update(status(S.SWITCH_ON_DISABLED))
    assert DriveEvent.FAULT_CLEARED in u.events and u.fault is FaultReason.NONE
    # a restarted DSP (new session) latches dsp_restarted until acknowledged
    u = m.update(status(S.SWITCH_ON_DISABLED, session=8))
    assert u.mode == MODE_DSP_RESTARTED and DriveEvent.DSP_RESTARTED in u.events
    assert m.update(status(S.OPERATION_ENABLED, session=8)).mode == MODE_DSP_RESTARTED
    m.acknowledge_restart()
    assert m.update(status(S.OPERATION_ENABLED, session=8)).mode == MODE_ENABLED
    assert m.as_dict() == {
        "first_status": 1,
        "state_changed": 6,
        "enabled": 3,
        "disarmed": 1,
        "fault": 1,
        "fault.velocity_limit": 1,
        "fault_cleared": 1,
        "dsp_restarted": 1,
    }


def test_status_flags_imply_drive_state_for_legacy_construction():
    assert DspStatus(True, False).drive_state is S.OPERATION_ENABLED
    tripped = DspStatus(False, True)
    assert (tripped.drive_state, tripped.fault_reason) == (S.FAULT, FaultReason.WATCHDOG)
    assert DspStatus(False, False).drive_state is S.SWITCH_ON_DISABLED


# ------------------------------------------------------------------------- DSP emulator


class Rig:
    """A RealtimeDsp on a private bus, fed controller frames directly, on a fake clock."""

    def __init__(self, cfg: RigConfig, bus: can.BusABC, tap: can.BusABC, **kw: object) -> None:
        self.node = RealtimeDsp(cfg, bus, session=4242, **kw)  # type: ignore[arg-type]
        self.ctl = ControllerCodec()
        self.tap = tap
        self.now = T0
        self.period_ns = self.node.control_period_ns
        self.node.start_realtime(T0)

    def send(self, command: DspCommand) -> None:
        self.node.handle(self.ctl.encode_control(command), self.now)

    def torque(self, tau: tuple[float, float]) -> None:
        self.node.handle(self.ctl.encode_torque(*tau), self.now)

    def advance(self, ms: float) -> None:
        end = self.now + round(ms * MS)
        while self.now < end:
            self.now = min(end, self.now + self.node.physics_period_ns)
            self.node.service(self.now)

    def run(self, periods: int, tau: tuple[float, float]) -> None:
        """Command ``tau`` every control period (the watchdog stays quiet)."""
        for _ in range(periods):
            self.torque(tau)
            self.advance(self.period_ns / MS)

    def statuses(self) -> list[DspStatus]:
        out = []
        while (msg := self.tap.recv(timeout=0)) is not None:
            frame = self.ctl.decode(msg, self.now)
            if isinstance(frame, DspStatus):
                out.append(frame)
        return out


@pytest.fixture
def rig(cfg: RigConfig):
    def make(config: RigConfig = cfg, **kw: object) -> Rig:
        spec = isolated_spec("virtual")
        bus, tap = open_bus(spec), open_bus(spec)
        opened.extend([bus, tap])
        return Rig(config, bus, tap, **kw)

    opened: list[can.BusABC] = []
    yield make
    for bus in opened:
        bus.shutdown()


def test_dsp_boots_disabled_with_its_session_and_applies_no_torque(rig):
    r = rig()
    r.run(3, (3.0, 0.3))
    assert r.node.drive.state is S.SWITCH_ON_DISABLED
    assert np.array_equal(r.node.world.tau_applied, np.zeros(2))
    first = r.statuses()[0]
    assert first.drive_state is S.SWITCH_ON_DISABLED and first.session == 4242
    assert RealtimeDsp(r.node.cfg, r.node.bus).session != 0  # random, non-zero by default


def test_disable_mid_run_goes_ready_and_removes_torque(rig):
    r = rig()
    r.send(C.ENABLE)
    r.run(3, (3.0, 0.3))
    assert np.allclose(r.node.world.tau_applied, (3.0, 0.3))
    r.statuses()
    r.send(C.DISABLE)
    assert r.node.drive.state is S.READY_TO_SWITCH_ON and not r.node.torque_enabled
    r.run(3, (3.0, 0.3))  # commands keep coming: still no torque
    assert np.array_equal(r.node.world.tau_applied, np.zeros(2))
    sent = r.statuses()
    assert sent[0].drive_state is S.READY_TO_SWITCH_ON and not sent[0].torque_enabled
    assert all(s.drive_state is S.READY_TO_SWITCH_ON for s in sent)
    assert r.node.stats.watchdog_trips == 0


def test_watchdog_faults_until_fault_reset(rig):
    r = rig()
    r.send(C.ENABLE)
    r.run(3, (3.0, 0.3))
    r.statuses()
    r.advance(10 * r.period_ns / MS)  # the controller goes silent
    assert r.node.drive.state is S.FAULT and r.node.drive.fault_reason is FaultReason.WATCHDOG
    trip = next(s for s in r.statuses() if s.fault)
    assert trip.watchdog_tripped and not trip.torque_enabled
    assert trip.fault_reason is FaultReason.WATCHDOG and trip.watchdog_trips == 1
    # commands and ENABLE alone do not leave FAULT
    r.send(C.ENABLE)
    r.run(3, (3.0, 0.3))
    assert r.node.drive.state is S.FAULT and r.node.stats.refused_commands == 1
    assert np.array_equal(r.node.world.tau_applied, np.zeros(2))
    r.send(C.FAULT_RESET)
    assert r.node.drive.state is S.SWITCH_ON_DISABLED and not r.node.torque_enabled
    r.send(C.ENABLE)
    r.run(2, (3.0, 0.3))
    assert r.node.torque_enabled and np.allclose(r.node.world.tau_applied, (3.0, 0.3))
    assert r.node.stats.faults == {"watchdog": 1}


def test_joint_position_limit_faults_with_reason(cfg: RigConfig, rig):
    tight = cfg.with_overrides({"dsp.q_max": [cfg.scenario.q0[0] + 0.05, 2.6]})
    r = rig(tight)
    r.send(C.ENABLE)
    for _ in range(200):
        r.run(1, (20.0, 0.0))
        if r.node.drive.state is S.FAULT:
            break
    node = r.node
    assert node.drive.fault_reason is FaultReason.POSITION_LIMIT
    assert node.stats.faults == {"position_limit": 1} and "q1" in node.stats.last_fault
    # the step that crossed was the last one with torque; from then on none
    assert node.encoder.q[0] > tight.dsp.q_max[0]
    r.run(2, (20.0, 0.0))
    assert np.array_equal(node.world.tau_applied, np.zeros(2))
    fault = next(s for s in r.statuses() if s.fault)
    assert fault.fault_reason is FaultReason.POSITION_LIMIT and not fault.watchdog_tripped


def test_velocity_limit_faults_with_reason(cfg: RigConfig, rig):
    r = rig(cfg.with_overrides({"dsp.dq_max": [0.5, 8.0]}))
    r.send(C.ENABLE)
    for _ in range(200):
        r.run(1, (20.0, 0.0))
        if r.node.drive.state is S.FAULT:
            break
    assert r.node.drive.fault_reason is FaultReason.VELOCITY_LIMIT
    assert abs(r.node.encoder.dq[0]) > 0.5
    assert any(s.fault_reason is FaultReason.VELOCITY_LIMIT for s in r.statuses())


def test_enable_beyond_a_limit_faults_at_once(cfg: RigConfig, rig):
    r = rig(cfg.with_overrides({"dsp.q_max": [math.pi, 2.6]}))
    r.node.world.q[0] = r.node.encoder.q[0] = 3.2  # pushed there while disabled: no fault yet
    r.advance(5)
    assert r.node.drive.state is S.SWITCH_ON_DISABLED
    r.send(C.ENABLE)
    assert r.node.drive.fault_reason is FaultReason.POSITION_LIMIT


def test_encoder_beyond_eight_turns_is_never_pinned(rig):
    """Joint 1 coasts (torque off, no friction) past +8 rev: the DSP faults with ENCODER, in any
    drive state, and stops sending joint state instead of a reading stuck at the frame's end."""
    r = rig()
    hi = signal_range("JointPosition", "Q1")[1]
    node = r.node
    node.world.q[0] = node.encoder.q[0] = hi - 0.05
    node.world.dq[0] = node.encoder.dq[0] = 5.0
    node.start_scenario(r.now)  # the world moves from now on, with no torque command
    positions: list[float] = []
    for _ in range(20):
        r.run(1, (0.0, 0.0))
        while (msg := r.tap.recv(timeout=0)) is not None:
            frame = r.ctl.decode(msg, r.now)
            if isinstance(frame, JointPosition):
                positions.append(frame.q1)
            elif isinstance(frame, DspStatus) and frame.fault:
                assert frame.fault_reason is FaultReason.ENCODER
    assert node.drive.state is S.FAULT and node.drive.fault_reason is FaultReason.ENCODER
    assert node.world.q[0] > hi  # the arm went on turning ...
    assert positions and max(positions) <= hi  # ... every reported angle was a true one
    assert node.stats.states_withheld > 0
    # a fault reset does not bring the lie back: still out of range, still faulted
    r.send(C.FAULT_RESET)
    r.advance(5)
    assert node.drive.fault_reason is FaultReason.ENCODER and node.drive.faults["encoder"] == 2


# ------------------------------------------------------------- realtime scenario clock


def test_realtime_world_holds_its_initial_state_until_the_first_torque(rig):
    """The realtime scenario's t = 0 is the first command that applies torque, however long
    after the emulator's start it comes: until then the world stays at simulation time 0 (the
    joint state still goes out at its rate); ENABLE and zero torques with Enable = 0 (arming)
    do not start it; a command's t = 0 is its release (``Tick``: microseconds after it)."""
    r = rig()
    node = r.node
    r.advance(4000)  # past the scenario's jump time on the emulator's own clock
    assert node.world.t == 0.0 and node.world.step_index == 0
    assert node.stats.held_states >= 4000 * node.cfg.rates.control_hz / 1e3 - 1  # one a period
    r.send(C.ENABLE)
    for _ in range(3):  # arming: a cyclic stream that applies no torque
        node.handle(r.ctl.encode_torque(0.0, 0.0, enable=False, tick=150), r.now)
        r.advance(r.period_ns / MS)
    assert node.torque_enabled and node.world.t == 0.0 and not node.stats.watchdog_trips
    release = r.now - 400_000
    node.handle(r.ctl.encode_torque(1.0, 0.1, tick=400), r.now)  # sent 400 us after release
    assert node.stats.scenario_start_ns == release
    r.advance(1000)
    assert node.world.step_index == (r.now - release) // node.physics_period_ns
    assert node.world.q[1] != node.cfg.scenario.q0[1]  # the torque moved the arm


def test_realtime_frames_are_dated_by_their_arrival_not_the_next_step(rig):
    """Between physics steps the DSP takes frames as they arrive: a command that arrives
    0.3 ms into a step and left 0.1 ms after its release starts the scenario 0.2 ms into that
    step, not when the next step is due (which shifted every torque of the run)."""
    r = rig()
    node = r.node
    r.send(C.ENABLE)
    r.advance(1)
    arrival = r.now + 300_000
    r.tap.send(r.ctl.encode_torque(1.0, 0.1, tick=100))
    node.idle(r.now + node.physics_period_ns, clock=lambda: arrival)
    assert node.stats.scenario_start_ns == arrival - 100_000


def test_the_realtime_scenario_starts_on_the_controllers_release_grid(rig):
    """t = 0 is the first torque's release on the phase the arming commands taught: a first
    command whose send took 0.45 ms longer than its reported delay says (a cold send path)
    does not start the world late, which would delay every torque of the run by as much."""
    r = rig()
    node = r.node
    r.send(C.ENABLE)
    for _ in range(5):  # arming: each arrives 150 us after its release and says so
        node.handle(r.ctl.encode_torque(0.0, 0.0, enable=False, tick=150), r.now)
        r.advance(r.period_ns / MS)
    release = r.now - 150_000
    node.handle(r.ctl.encode_torque(1.0, 0.1, tick=150), r.now + 450_000)
    assert node.stats.scenario_start_ns == release


def test_a_rearm_after_a_watchdog_trip_continues_the_realtime_scenario(rig):
    r = rig()
    node = r.node
    r.send(C.ENABLE)
    r.run(10, (0.5, 0.05))
    start, steps = node.stats.scenario_start_ns, node.world.step_index
    r.advance(200)  # no commands: the watchdog trips, the world goes on
    assert node.stats.watchdog_trips == 1 and node.world.step_index > steps
    r.send(C.FAULT_RESET)
    r.send(C.ENABLE)
    r.run(10, (0.5, 0.05))
    assert node.stats.scenario_start_ns == start
    assert node.world.step_index == (r.now - start) // node.physics_period_ns
