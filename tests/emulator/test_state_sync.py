"""``dsp.state_sync = command``: one joint state per control period, ``state_lead_us`` before
the controller's tick, the phase learnt from when its commands arrive less the delay after the
release each reports (fake clock, no sleeps)."""

from __future__ import annotations

import can
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import ControllerCodec
from hal.can_frames import JointPosition
from hal.config import RigConfig
from plant_emulator.dsp_realtime import CommandPhase, RealtimeDsp

MS = 1_000_000
T0 = 1_000_000_000_000
PERIOD = 20 * MS


def test_phase_is_the_earliest_arrival_of_recent_commands() -> None:
    ph = CommandPhase(PERIOD, window=4)
    assert ph.residue_ns is None
    for k, delay in enumerate((900_000, 400_000, 1_300_000)):
        ph.observe(T0 + 7 * MS + k * PERIOD + delay)
    assert ph.residue_ns == (T0 + 7 * MS + 400_000) % PERIOD
    ph.reset()
    assert ph.residue_ns is None


def test_phase_near_the_period_boundary_does_not_wrap() -> None:
    """Ticks at 19.9 ms into the period: arrivals land on both sides of the boundary."""
    ph = CommandPhase(PERIOD, window=8)
    base = T0 - (T0 % PERIOD) + PERIOD - 100_000
    for k, delay in enumerate((50_000, 300_000, 120_000, 500_000)):
        ph.observe(base + k * PERIOD + delay)
    assert ph.residue_ns == (base + 50_000) % PERIOD


def _node(cfg: RigConfig, bus: can.BusABC, **dsp: object) -> RealtimeDsp:
    return RealtimeDsp(cfg.with_overrides({f"dsp.{k}": v for k, v in dsp.items()}), bus)


def test_the_phase_is_learnt_from_arrival_less_the_delay_each_command_reports(
    cfg: RigConfig,
) -> None:
    """Realtime ``Tick`` = µs from the controller's release to the command: a command sent 4 ms
    after its release (it waited for its input) places the release where it was; a saturated
    delay (65535 µs or more) teaches nothing."""
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus, open_bus(spec) as ctl_bus:
        node = _node(cfg, bus)
        node.start_realtime(T0)
        codec = ControllerCodec()
        release = T0 + 7 * MS
        for k in range(3):
            ctl_bus.send(codec.encode_torque(0.0, 0.0, enable=False, tick=4000))
            node.drain(release + k * PERIOD + 4 * MS + 300_000)  # seen 0.3 ms after sending
        assert node.phase.residue_ns == (release + 300_000) % PERIOD
        ctl_bus.send(codec.encode_torque(0.0, 0.0, enable=False, tick=0xFFFF))
        node.drain(release + 3 * PERIOD + 1 * MS)  # would be the earliest if it counted
        assert node.phase.residue_ns == (release + 300_000) % PERIOD
        assert node.stats.commands == 4


def test_one_state_per_period_lead_before_the_commanded_tick(cfg: RigConfig) -> None:
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus, open_bus(spec) as ctl_bus:
        node = _node(cfg, bus, state_lead_us=3000.0)
        node.start_realtime(T0)
        codec = ControllerCodec()
        # Until a command arrives: on the DSP's own control-period clock.
        due = [k for k in range(1, 61) if node.state_due(k)]
        assert due == [20, 40, 60]
        # The controller ticks 7 ms into each period; its commands arrive 0.5-1 ms later.
        tick_offset = 7 * MS
        for k in range(3):
            t_cmd = T0 + k * PERIOD + tick_offset + (500_000 if k else 1_000_000)
            ctl_bus.send(codec.encode_torque(0.0, 0.0, enable=False))
            node.drain(t_cmd)
        assert node.phase.residue_ns == (T0 + tick_offset + 500_000) % PERIOD
        assert node.stats.commands == 3
        node.last_cmd_ns = T0 + 3 * PERIOD  # keep the "commands stopped" rule out of the way
        k0 = 3 * PERIOD // MS
        due = [k for k in range(k0, k0 + 40) if node.state_due(k)]
        assert len(due) == 2  # once per period
        for k in due:
            t = T0 + k * MS
            to_tick = (T0 + tick_offset + 500_000 - t) % PERIOD
            assert 2 * MS < to_tick <= 3 * MS  # sampled a lead (within a step) before the tick


def test_commands_that_stopped_fall_back_to_the_dsp_clock(cfg: RigConfig) -> None:
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus:
        node = _node(cfg, bus)
        node.start_realtime(T0)
        node.phase.observe(T0 + 7 * MS)
        node.last_cmd_ns = T0 + 7 * MS
        late = round(node.watchdog_ns / MS) + 40
        due = [k for k in range(late, late + 40) if node.state_due(k)]
        assert due == [k for k in range(late, late + 40) if k % node.substeps == 0]


def test_a_period_of_one_physics_step_gets_a_state_after_every_step(cfg: RigConfig) -> None:
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus:
        node = RealtimeDsp(cfg.with_overrides({"rates.control_hz": 1000.0}), bus)
        node.start_realtime(T0)
        node.phase.observe(T0)
        node.last_cmd_ns = T0
        assert all(node.state_due(k) for k in range(1, 10))


def test_a_period_shorter_than_the_lead_still_gets_one_state_per_period(cfg: RigConfig) -> None:
    """500 Hz (2 ms, two physics steps) with the default 3 ms lead: one state per period, the
    lead taken modulo the period (1 ms before the tick). It used to be one after every step,
    twice the frames for the controller to decode on its tick for no fresher a sample."""
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus:
        node = RealtimeDsp(cfg.with_overrides({"rates.control_hz": 500.0}), bus)
        assert node.state_lead_ns == 3 * MS
        node.start_realtime(T0)
        tick = T0 + 7 * MS  # the controller's ticks: T0 + 1 ms (mod 2 ms)
        node.phase.observe(tick)
        node.last_cmd_ns = T0 + 100 * MS
        due = [k for k in range(100, 140) if node.state_due(k)]
        assert len(due) == 20  # one per 2 ms period
        assert all((T0 + k * MS - (tick - MS)) % (2 * MS) == 0 for k in due)  # 1 ms before


def test_free_mode_keeps_the_configured_state_rate(cfg: RigConfig) -> None:
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus, open_bus(spec) as tap:
        node = RealtimeDsp(cfg.with_overrides({"dsp.state_sync": "free"}), bus)
        node.start_realtime(T0)
        for i in range(10):
            node.service(T0 + (i + 1) * MS)
        states = 0
        codec = ControllerCodec()
        while (msg := tap.recv(timeout=0)) is not None:
            states += isinstance(codec.decode(msg), JointPosition)
        assert states == 11  # the initial one and one per physics step at 1000 Hz


@pytest.mark.parametrize("lead_us", [0.0, 500.0, 3000.0, 18_000.0])
def test_every_lead_gives_exactly_one_state_per_period(cfg: RigConfig, lead_us: float) -> None:
    """Leads from below one physics step (0: at the tick) to a period less a step: one state
    per period, at the step that lies within one step after (tick - lead). The window test
    once sent nothing at all for a lead below one step. (A lead of a period less a step or
    more wraps around modulo the period, see ``state_due``.)"""
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus:
        node = _node(cfg, bus, state_lead_us=lead_us)
        node.start_realtime(T0)
        tick = T0 + 7 * MS + 500_000
        node.phase.observe(tick)
        node.last_cmd_ns = T0 + 20 * PERIOD  # commands keep coming
        due = [k for k in range(200, 400) if node.state_due(k)]
        assert len(due) == 10
        lead = round(lead_us * 1e3)
        for k in due:
            since = (T0 + k * MS - (tick - lead)) % PERIOD  # after (tick - lead), mod period
            assert 0 <= since < MS


def test_a_dsp_that_ran_late_sends_the_state_of_now_not_of_the_step_that_was_due(
    cfg: RigConfig,
) -> None:
    """The emulator's process was descheduled for 15 ms across a state's due step: it catches
    up on physics and then sends one state, of the latest step. A state of the due step, sent
    15 ms late, would reach the controller looking fresh (its age is judged by arrival) while
    it shows the arm as it was, and the controller would act on it as on the present."""
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus, open_bus(spec) as tap:
        node = _node(cfg, bus, state_lead_us=3000.0)
        node.start_realtime(T0)
        node.start_scenario(T0)  # the world moves from T0 on, with no torque command
        node.world.dq[:] = (1.0, -2.0)  # moving, so the sample's time shows in its angles
        codec = ControllerCodec()
        while tap.recv(timeout=0) is not None:  # the initial state and status
            pass
        node.service(T0 + 5 * MS)  # steps 1..5 on time: no state due yet (step 20 is)
        node.service(T0 + 35 * MS)  # late: steps 6..35 at once; step 20 was due
        states = []
        while (msg := tap.recv(timeout=0)) is not None:
            frame = codec.decode(msg)
            if isinstance(frame, JointPosition):
                states.append(frame)
        assert node.world.step_index == 35
        assert len(states) == 1
        assert states[0].sample == 35 % 16
        assert (node.stats.states_late, node.stats.states_merged) == (1, 0)
