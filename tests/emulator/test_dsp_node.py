"""The emulated DSP node (plant_emulator.dsp_node) against a real JointClient on real buses.

Everything runs in-process on ``virtual`` and host-local ``udp_multicast`` buses (isolated per
test). Realtime behaviour is driven with a fake clock through ``RealtimeDsp.start_realtime`` /
``RealtimeDsp.service``, so no test depends on the host's speed; lockstep runs use the real node
loop. Receive timeouts are generous; nothing asserts wall-clock timings.
"""

from __future__ import annotations

import math
import threading
import time

import can
import numpy as np
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import ControllerCodec
from hal.can_frames import RAD_PER_COUNT, JointPosition, JointVelocity
from hal.config import RigConfig
from hal.joint_client import DRAIN_MAX_FRAMES
from plant_emulator.dsp_realtime import RealtimeDsp
from tests.support.dsp import (
    MS,
    RECV_TIMEOUT_S,
    T0,
    TRANSPORTS,
    FakeClock,
    enable,
    first_status,
    free_state_sync,
    rig,
    wait_for,
)
from tests.support.joint import TripRearm, read_for


@pytest.fixture
def cfg(cfg: RigConfig) -> RigConfig:
    """These tests read the joint state after every physics step (:func:`free_state_sync`)."""
    return free_state_sync(cfg)


# ------------------------------------------------------------------------ enable / disable


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_enable_applies_torque_and_disable_removes_it(cfg: RigConfig, transport: str) -> None:
    with rig(cfg, transport) as (node, client):
        clock = FakeClock(node)
        q0 = node.world.q.copy()
        # Not armed: a command is received but no torque reaches the arm.
        clock.command(client, (5.0, 0.5))
        clock.advance(20)
        assert not node.torque_enabled
        assert np.array_equal(node.world.tau_applied, np.zeros(2))
        assert np.array_equal(node.world.q, q0)

        enable(clock, client)
        wait_for(
            lambda: client.status is not None and client.status.torque_enabled,
            "status",
            client.drain,
        )
        for _ in range(10):  # 10 control periods with torque
            clock.command(client, (5.0, 0.5))
            clock.advance(20)
        assert np.allclose(node.world.tau_applied, (5.0, 0.5))
        assert node.world.q[0] > q0[0] + 1e-3, "joint 1 did not move under +5 N·m"
        assert node.world.dq[0] > 0
        wait_for(
            lambda: client.latest_state(max_age_s=1e9).q[0] > q0[0] + 1e-3,
            "moved state",
            client.drain,
        )

        client.disable()
        wait_for(lambda: not node.armed, "DISABLE", clock.pump)
        dq_before = node.world.dq.copy()
        clock.advance(40)
        assert np.array_equal(node.applied_torque(), np.zeros(2))
        assert np.array_equal(node.world.tau_applied, np.zeros(2))
        # No friction by default: without torque the arm coasts.
        assert node.world.dq[0] == pytest.approx(dq_before[0], rel=0.05)
        wait_for(lambda: not client.status.torque_enabled, "disabled status", client.drain)  # type: ignore[union-attr]
        assert not client.status.watchdog_tripped  # type: ignore[union-attr]


def test_torque_is_saturated_to_the_amplifier_limits(cfg: RigConfig) -> None:
    with rig(cfg, "virtual") as (node, client):
        clock = FakeClock(node)
        enable(clock, client)
        clock.command(client, (160.0, -16.0))  # inside the frame range, beyond tau_max
        clock.advance(5)
        assert np.array_equal(node.world.tau_applied, (150.0, -15.0))
        wait_for(
            lambda: client.status is not None and client.status.torque_saturated,
            "sat",
            client.drain,
        )


# -------------------------------------------------------------------------------- watchdog


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_watchdog_trips_within_three_periods_and_latches(cfg: RigConfig, transport: str) -> None:
    period_ms = 1e3 / cfg.rates.control_hz
    limit_ns = round(cfg.dsp.watchdog_periods * period_ms * MS)
    with rig(cfg, transport) as (node, client):
        raw: list[can.Message] = []
        client.bus.rx_hook = raw.append
        clock = FakeClock(node)
        enable(clock, client)
        for _ in range(5):
            clock.command(client, (3.0, 0.3))
            clock.advance(period_ms)
        last_cmd = node.last_cmd_ns
        assert last_cmd == clock.now - round(period_ms * MS)
        # The controller stops sending: advance millisecond by millisecond until the trip.
        while not node.tripped:
            clock.advance(1)
            assert clock.now - last_cmd <= limit_ns + 2 * MS, "watchdog did not trip in time"
        latency = node.stats.last_trip_latency_ns
        assert latency is not None
        assert limit_ns <= latency <= limit_ns + node.physics_period_ns
        assert node.stats.watchdog_trips == 1
        assert np.array_equal(node.applied_torque(), np.zeros(2))
        trip_step = node.world.step_index - 1  # the step that ran with the torque removed
        assert np.array_equal(node.world.tau_applied, np.zeros(2))

        # The controller side learns it from the DspStatus sent at the trip itself.
        wait_for(
            lambda: client.status is not None and client.status.watchdog_tripped,
            "WatchdogTripped",
            client.drain,
        )
        status = first_status(raw, lambda s: s.watchdog_tripped)
        assert not status.torque_enabled
        assert status.watchdog_trips == 1
        # DspStatus.Tick is the DSP's physics tick: the trip is reported at the trip's step,
        # 3 control periods (+ at most one physics step) after the last command.
        assert status.tick == trip_step
        trip_ns = T0 + status.tick * node.physics_period_ns
        assert limit_ns <= trip_ns - last_cmd <= limit_ns + node.physics_period_ns

        # Commands alone do not clear the trip ...
        for _ in range(5):
            clock.command(client, (3.0, 0.3))
            clock.advance(period_ms)
            assert node.tripped
            assert np.array_equal(node.world.tau_applied, np.zeros(2))
        assert client.status.watchdog_tripped
        # ... an explicit ENABLE does.
        enable(clock, client)
        assert not node.tripped
        clock.command(client, (3.0, 0.3))
        clock.advance(period_ms)
        assert np.allclose(node.world.tau_applied, (3.0, 0.3))
        wait_for(lambda: not client.status.watchdog_tripped, "re-enabled status", client.drain)  # type: ignore[union-attr]
        assert client.status.torque_enabled  # type: ignore[union-attr]


def test_trip_rearm_re_arms_each_trip_once_also_past_the_saturated_trip_count(
    cfg: RigConfig,
) -> None:
    """:class:`~tests.support.joint.TripRearm` (the re-arm rule of the vcan tests' streaming
    clients) against the DSP: one re-arm per watchdog trip, none for a status still saying
    tripped before the DSP handled the re-arm, and the same past 15 trips, where
    ``DspStatus.WatchdogTrips`` stays at 15 (a client comparing trip counts stopped there)."""
    stall_ms = 2 * cfg.dsp.watchdog_periods * 1e3 / cfg.rates.control_hz
    rearm = TripRearm()
    with rig(cfg, "virtual") as (node, client):
        clock = FakeClock(node)
        enable(clock, client)
        for trip in range(1, 21):
            clock.command(client, (0.0, 0.0))
            clock.advance(stall_ms)  # the client stalls past the watchdog
            assert node.stats.watchdog_trips == trip
            client.drain()
            statuses = client.take_statuses()
            assert statuses[-1].watchdog_tripped
            assert statuses[-1].watchdog_trips == min(trip, 15)
            assert rearm.new_trip(statuses), f"trip {trip} not re-armed"
            client.enable()  # the re-arm, not handled by the DSP yet ...
            node.send_status()  # ... which meanwhile still says tripped: the same trip
            client.drain()
            assert not rearm.new_trip(client.take_statuses()), f"trip {trip} re-armed twice"
            wait_for(lambda: node.torque_enabled, "the re-arm", clock.pump)
            client.drain()
            assert not rearm.new_trip(client.take_statuses())
        assert node.stats.watchdog_trips == 20


def test_watchdog_on_the_real_clock(cfg: RigConfig) -> None:
    """The node's own realtime loop in a thread; the client sends at 50 Hz, then stops."""
    with rig(cfg, "udp_multicast") as (node, client):
        stop = threading.Event()
        runner = threading.Thread(target=node.run, args=(stop,), name="dsp-node")
        runner.start()
        try:
            client.enable()
            for _ in range(15):
                client.send_torque(2.0, 0.2)
                read_for(client, 0.02)  # reads the bus meanwhile, like a controller
            stopped = time.monotonic()
            wait_for(
                lambda: client.status is not None and client.status.watchdog_tripped,
                "WatchdogTripped",
                client.drain,
            )
            seen_after_s = time.monotonic() - stopped
        finally:
            stop.set()
            runner.join(timeout=RECV_TIMEOUT_S)
        assert not runner.is_alive()
        latency = node.stats.last_trip_latency_ns
        assert latency is not None
        limit = node.watchdog_ns
        # On the DSP's own clock: 3 control periods after the last command, at physics-step
        # granularity (the host's scheduling cannot stretch it).
        assert limit <= latency <= limit + node.physics_period_ns
        assert node.stats.watchdog_trips == 1
        print(
            f"\nwatchdog: DSP trip {latency / 1e6:.3f} ms after the last command; client saw it "
            f"{seen_after_s * 1e3:.1f} ms after it stopped sending"
        )


# ----------------------------------------------------------------------------- sensors


class StateTap:
    """A controller-side listener that pairs JointPosition/JointVelocity frames in order."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.codec = ControllerCodec()

    def next_state(self) -> tuple[JointPosition, JointVelocity]:
        pos: JointPosition | None = None
        deadline = time.monotonic() + RECV_TIMEOUT_S
        while time.monotonic() < deadline:
            msg = self.bus.recv(timeout=0.1)
            frame = None if msg is None else self.codec.decode(msg)
            if isinstance(frame, JointPosition):
                pos = frame
            elif isinstance(frame, JointVelocity) and pos is not None:
                assert frame.sample == pos.sample
                return pos, frame
        pytest.fail("no joint state received")


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_reported_angles_are_whole_encoder_counts(cfg: RigConfig, transport: str) -> None:
    spec = isolated_spec(transport)
    with open_bus(spec) as bus, open_bus(spec) as tap_bus:
        node, tap = RealtimeDsp(cfg, bus), StateTap(tap_bus)
        node.start_realtime(T0)
        tap.next_state()  # the initial state
        node.armed, node.tau_cmd = True, np.array([7.0, -0.7])
        node.last_cmd_ns = T0 + 10**12  # keep the watchdog quiet in this sensor test
        for i in range(300):
            node.service(T0 + (i + 1) * MS)
            pos, _vel = tap.next_state()
            for q_rep, q_true in zip((pos.q1, pos.q2), node.world.q, strict=True):
                counts = q_rep / RAD_PER_COUNT
                assert abs(counts - round(counts)) < 1e-6, f"{q_rep} is not a whole count"
                assert abs(q_rep - q_true) <= RAD_PER_COUNT / 2 + 1e-12
        assert node.world.q[0] - cfg.scenario.q0[0] > 0.01  # it moved over many counts


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_velocity_estimate_tracks_true_velocity(cfg: RigConfig, transport: str) -> None:
    spec = isolated_spec(transport)
    fc = cfg.dsp.velocity_filter_hz
    lag_s = 1.0 / (2 * math.pi * fc)  # first-order filter delay
    with open_bus(spec) as bus, open_bus(spec) as tap_bus:
        node, tap = RealtimeDsp(cfg, bus), StateTap(tap_bus)
        node.start_realtime(T0)
        tap.next_state()
        node.armed = True
        node.last_cmd_ns = T0 + 10**12
        errors = []
        for i in range(600):  # +torque for 0.3 s, then reversed (sign change of acceleration)
            node.tau_cmd = np.array([6.0, 0.6]) if i < 300 else np.array([-6.0, -0.6])
            dq_prev = node.world.dq.copy()
            node.service(T0 + (i + 1) * MS)
            _pos, vel = tap.next_state()
            if i % 300 < 30:  # let the filter settle after each torque step
                continue
            accel = (node.world.dq - dq_prev) / node.world.dt
            tol = np.abs(accel) * lag_s * 1.5 + 2 * RAD_PER_COUNT / node.world.dt
            err = np.abs(np.array([vel.dq1, vel.dq2]) - node.world.dq)
            errors.append(float(np.max(err)))
            assert np.all(err <= tol), f"step {i}: estimate {vel} vs true {node.world.dq}"
        assert abs(node.world.dq[0]) > 0.05
        print(f"\nvelocity estimate: max |error| {max(errors):.4g} rad/s")


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_frames_waiting_when_the_node_stops_are_handled_and_counted(
    cfg: RigConfig, transport: str
) -> None:
    """A stop (SIGTERM) while commands sit in the receive queue: none is lost from the count."""
    with rig(cfg, transport) as (node, client):
        for _ in range(5):
            client.send_torque(0.0, 0.0)
        raw = node.bus.recv(timeout=RECV_TIMEOUT_S)  # the first one has arrived ...
        assert raw is not None
        node.handle(raw, T0)  # the others are queued (both buses deliver during send)
        stop = threading.Event()
        stop.set()  # the node is told to stop before its loop ever drains
        stats = node.run(stop)
        assert stats.commands == 5


def test_a_bus_that_never_runs_dry_cannot_hold_the_dsp(
    cfg: RigConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A flood always has a frame waiting: the DSP's drain stops after ``DRAIN_MAX_FRAMES``
    (its physics steps go on) and counts the cut; each frame is handled, none is lost."""
    sender = ControllerCodec()
    served = [0]

    with rig(cfg, "virtual") as (node, _client):

        def always(timeout: float | None = None) -> can.Message | None:
            served[0] += 1
            return None if served[0] > 10 * DRAIN_MAX_FRAMES else sender.encode_torque(0.0, 0.0)

        monkeypatch.setattr(node.bus, "recv", always)
        node.drain(T0)
        assert node.stats.drains_cut == 1 and served[0] == DRAIN_MAX_FRAMES
        assert node.stats.commands == DRAIN_MAX_FRAMES  # every frame taken was handled
