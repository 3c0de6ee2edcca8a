"""The emulated DSP node (plant_emulator.dsp_node) against a real JointClient on real buses.

Everything runs in-process on ``virtual`` and host-local ``udp_multicast`` buses (isolated per
test). Realtime behaviour is driven with a fake clock through ``DspNode.start_realtime`` /
``DspNode.service``, so no test depends on the host's speed; lockstep runs use the real node
loop. Receive timeouts are generous; nothing asserts wall-clock timings.
"""

from __future__ import annotations

import math
import random
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import can
import cantools
import numpy as np
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import (
    DBC_PATH,
    RAD_PER_COUNT,
    ControllerCodec,
    DspCommand,
    DspStatus,
    JointPosition,
    JointVelocity,
)
from hal.config import RigConfig
from hal.e2e import DEFAULT_MAX_DELTA, DEFAULT_REINIT_AFTER_NS
from hal.errors import HalTimeoutError
from hal.joint_client import DRAIN_MAX_FRAMES, JointClient
from plant_emulator.dsp_node import DspNode
from tests.support import SecocReference, command_is_malformed, e2e_crc_reference
from tests.support.joint import TripRearm, read_for

RECV_TIMEOUT_S = 10.0
MS = 1_000_000
T0 = 1_000_000_000_000
"""Fake monotonic start time of realtime runs (ns)."""

TRANSPORTS = ["virtual", "udp_multicast"]


@pytest.fixture
def cfg(cfg: RigConfig) -> RigConfig:
    """These tests read the joint state after every physics step: the DSP's own clock at
    ``rates.state_hz`` (the command-synchronised default is tested in test_state_sync.py)."""
    return cfg.with_overrides({"dsp.state_sync": "free"})


def wait_for(cond: Callable[[], bool], what: str, poll: Callable[[], object] | None = None) -> None:
    """Spin until ``cond()``; ``poll()`` in between (e.g. the node or the client reads its bus)."""
    deadline = time.monotonic() + RECV_TIMEOUT_S
    while not cond():
        if poll is not None:
            poll()
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.001)


@contextmanager
def rig(
    cfg: RigConfig, transport: str, **node_kwargs: object
) -> Iterator[tuple[DspNode, JointClient]]:
    """A DspNode on its own bus and a JointClient (controller side) on the same bus."""
    spec = isolated_spec(transport)
    with open_bus(spec) as bus, JointClient.open(spec, cfg) as client:
        yield DspNode(cfg, bus, **node_kwargs), client  # type: ignore[arg-type]


class FakeClock:
    """Drives a realtime node: ``now`` in ns, ``advance`` runs the steps that became due."""

    def __init__(self, node: DspNode) -> None:
        self.node = node
        self.now = T0
        node.start_realtime(T0)

    def pump(self) -> None:
        """Handle frames that arrived, without advancing time."""
        self.node.service(self.now)

    def advance(self, ms: float) -> None:
        end = self.now + round(ms * MS)
        while self.now < end:  # one physics step at a time, like the real loop when on time
            self.now = min(end, self.now + self.node.physics_period_ns)
            self.node.service(self.now)

    def command(self, client: JointClient, tau: tuple[float, float]) -> None:
        """The client sends one torque command; the node receives it at ``now``."""
        n = self.node.stats.commands
        client.send_torque(*tau)
        wait_for(lambda: self.node.stats.commands > n, "the torque command", self.pump)


def enable(clock: FakeClock, client: JointClient) -> None:
    client.enable()
    wait_for(lambda: clock.node.torque_enabled, "ENABLE", clock.pump)


def first_status(raw: list[can.Message], pred: Callable[[DspStatus], bool]) -> DspStatus:
    """The first DspStatus among raw received frames that satisfies ``pred``."""
    codec = ControllerCodec()
    for msg in list(raw):
        frame = codec.decode(msg, 0)
        if isinstance(frame, DspStatus) and pred(frame):
            return frame
    pytest.fail("no such DspStatus received")


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
        client.frame_hook = raw.append
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


# -------------------------------------------------------------------------------- lockstep


def pd_torque(q: tuple[float, float], dq: tuple[float, float]) -> tuple[float, float]:
    """A feedback law, so a lockstep run depends on the states it received."""
    ref = (0.9, 0.4)
    return (
        40.0 * (ref[0] - q[0]) - 4.0 * dq[0],
        6.0 * (ref[1] - q[1]) - 0.6 * dq[1],
    )


class Responder:
    """A lockstep controller in a thread: answers every Sync with the PD law of the state.

    ``spoil`` is a set of ticks whose *first* answer is corrupted (bad CRC), as if it had been
    lost or rejected; the DSP must re-send Sync(k) and take the second answer.
    """

    def __init__(self, client: JointClient, spoil: frozenset[int] = frozenset()) -> None:
        self.client = client
        self.spoil = set(spoil)
        self.answers: Counter[int] = Counter()
        self.states: dict[int, tuple[tuple[float, float], tuple[float, float]]] = {}
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="lockstep-responder")

    def _run(self) -> None:
        client = self.client
        while not self.stop.is_set():
            try:
                k = client.wait_sync(timeout=0.05)
            except HalTimeoutError:
                continue
            state = client.latest_state(max_age_s=1e9)
            self.states.setdefault(k, (state.q, state.dq))  # a re-sent Sync(k) may race k+1
            self.answers[k] += 1
            tau = pd_torque(state.q, state.dq)
            if k in self.spoil:
                self.spoil.discard(k)
                msg = client._codec.encode_torque(*tau, enable=True, tick=k)
                msg.data[0] ^= 0x5A  # corrupted: the DSP rejects it (bad MAC)
                client.bus.send(msg)
                continue
            client.send_torque(*tau, tick=k)

    def __enter__(self) -> Responder:
        self.client.enable()
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(timeout=RECV_TIMEOUT_S)


def lockstep_run(
    cfg: RigConfig,
    transport: str,
    periods: int,
    spoil: frozenset[int] = frozenset(),
    pose_sink: Any = None,
) -> tuple[DspNode, Responder]:
    spec = isolated_spec(transport)
    with open_bus(spec) as bus, JointClient.open(spec, cfg) as client:
        node = DspNode(
            cfg, bus, lockstep=True, sync_resend_s=0.02, reply_timeout_s=5.0, pose_sink=pose_sink
        )
        with Responder(client, spoil) as responder:
            node.run(threading.Event(), duration_s=periods / cfg.rates.control_hz)
    return node, responder


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_lockstep_one_period_per_answered_sync_and_deterministic(
    cfg: RigConfig, transport: str
) -> None:
    periods = 40
    a, resp_a = lockstep_run(cfg, transport, periods)
    assert a.sync_tick == periods
    assert a.stats.missing_periods == 0
    assert a.stats.physics_steps == a.world.step_index == periods * a.substeps
    assert sorted(resp_a.states) == list(range(periods))
    assert a.world.q[0] > 0.6, "the PD law did not move joint 1 towards 0.9 rad"
    # Same run again: bit-identical, although real-time scheduling differs between the runs.
    b, resp_b = lockstep_run(cfg, transport, periods)
    assert a.world.q.tobytes() == b.world.q.tobytes()
    assert a.world.dq.tobytes() == b.world.dq.tobytes()
    assert resp_a.states == resp_b.states


def test_lockstep_resends_sync_when_the_answer_is_lost(cfg: RigConfig) -> None:
    periods = 20
    clean, _ = lockstep_run(cfg, "virtual", periods)
    spoiled, responder = lockstep_run(cfg, "virtual", periods, spoil=frozenset({3, 11}))
    assert spoiled.stats.missing_periods == 0
    assert spoiled.stats.sync_resends >= 2
    assert spoiled.codec.stats.bad_mac == 2  # corrupted in transit: the MAC catches it first
    assert responder.answers[3] >= 2 and responder.answers[11] >= 2
    # The re-sends changed nothing in the physics.
    assert spoiled.world.q.tobytes() == clean.world.q.tobytes()
    assert spoiled.world.dq.tobytes() == clean.world.dq.tobytes()


def test_lockstep_resends_the_period_s_pose_with_its_sync(cfg: RigConfig) -> None:
    """While the DSP waits for a command it publishes the period's camera pose again, the same
    one, so the vision process answers again (an answer lost on its way, say)."""
    poses: list[tuple[int, int, tuple[float, float, float], bool]] = []

    def sink(seq: int, sim_ns: int, pose: Any, lockstep: bool) -> None:
        poses.append((seq, sim_ns, (pose.x, pose.y, pose.phi), lockstep))

    node, responder = lockstep_run(cfg, "virtual", 8, spoil=frozenset({3}), pose_sink=sink)
    assert responder.answers[3] >= 2 and node.stats.pose_resends >= 1
    seqs = [p[0] for p in poses]
    assert sorted(set(seqs)) == list(range(8))  # one pose per period
    assert seqs.count(3) == 1 + node.stats.pose_resends
    assert len({p for p in poses if p[0] == 3}) == 1  # sent again unchanged


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_lockstep_ignores_late_and_wrong_tick_commands(cfg: RigConfig, transport: str) -> None:
    with rig(cfg, transport, lockstep=True, reply_timeout_s=0.2, sync_resend_s=0.05) as (
        node,
        client,
    ):
        stop = threading.Event()
        client.enable()
        client.send_torque(4.0, 0.4, tick=0)
        assert node.lockstep_period(stop)  # period 0: answered (the frames were queued)
        assert node.stats.missing_periods == 0
        assert np.allclose(node.tau_cmd, (4.0, 0.4))
        # Period 1: only a late answer (tick 0) and one from the future (tick 7) arrive.
        client.send_torque(-9.0, -0.9, tick=0)
        client.send_torque(-8.0, -0.8, tick=7)
        steps = node.world.step_index
        assert node.lockstep_period(stop)
        assert node.stats.late_commands == 2
        assert node.stats.missing_periods == 1
        assert node.stats.sync_resends >= 1
        assert node.world.step_index == steps + node.substeps  # still one period per Sync
        assert np.allclose(node.tau_cmd, (4.0, 0.4)), "a late command changed the torque"
        # Period 2 answered again with a new torque.
        client.send_torque(1.0, 0.1, tick=2)
        assert node.lockstep_period(stop)
        assert node.stats.missing_periods == 1
        assert np.allclose(node.tau_cmd, (1.0, 0.1))
        assert node.last_cmd_tick == 2


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_lockstep_watchdog_counts_periods(cfg: RigConfig, transport: str) -> None:
    """Commands for periods 0..4 only: the DSP trips at period 7 (3 periods of silence)."""
    with rig(cfg, transport, lockstep=True, reply_timeout_s=0.05, sync_resend_s=0.02) as (
        node,
        client,
    ):
        client.enable()
        for k in range(5):
            client.send_torque(3.0, 0.3, tick=k)
        node.run(threading.Event(), duration_s=10 / cfg.rates.control_hz)
        assert node.stats.physics_steps == 10 * node.substeps
        assert node.stats.missing_periods == 5
        period_ns = node.control_period_ns
        assert node.stats.last_command_ns == 4 * period_ns
        assert node.stats.last_trip_latency_ns == 3 * period_ns
        assert node.stats.last_trip_ns == 7 * period_ns
        wait_for(
            lambda: client.status is not None and client.status.watchdog_tripped,
            "WatchdogTripped",
            client.drain,
        )
        assert client.status.lockstep  # type: ignore[union-attr]


def test_lockstep_waits_for_the_controller_to_arm(cfg: RigConfig) -> None:
    """A late-starting controller does not change the run: period 0 starts when it arms the
    DSP; until then only the joint state is published (no pose, no Sync)."""
    with rig(cfg, "virtual", lockstep=True, reply_timeout_s=0.05, sync_resend_s=0.01) as (
        node,
        client,
    ):
        stop = threading.Event()

        def arm_and_answer() -> None:
            client.enable()
            client.wait_sync(timeout=RECV_TIMEOUT_S)
            client.send_torque(1.0, 0.1, tick=0)

        timer = threading.Timer(0.3, arm_and_answer)
        timer.start()
        try:
            assert node.lockstep_period(stop)
        finally:
            timer.cancel()
            timer.join()
        assert node.stats.missing_periods == 0
        assert node.stats.state_frames >= 5  # the state was published while waiting
        assert client.sync_tick == 0
        # After the first answer, silence counts periods as missing again.
        assert node.lockstep_period(stop)
        assert node.stats.missing_periods == 1


# ---------------------------------------------------------------------- scenario reset


def _answer_periods(client: JointClient, periods: int) -> dict[int, tuple]:
    """Poll-mode controller: arm, answer Sync 0 .. periods-1 with the PD law, disarm."""
    client.enable()
    seen: dict[int, tuple] = {}
    while len(seen) < periods:
        k = client.wait_sync(timeout=RECV_TIMEOUT_S)
        state = client.latest_state(max_age_s=1e9)
        seen.setdefault(k, (state.q, state.dq))
        client.send_torque(*pd_torque(state.q, state.dq), tick=k)
    client.disable()
    return seen


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_a_scenario_reset_runs_again_exactly_as_a_fresh_dsp(cfg: RigConfig, transport: str):
    """RESET_SCENARIO between two runs on one running DSP: the second run sees the same
    states as the first and as a freshly started DSP, under a new session; nothing of the
    first run (states, Syncs) reaches the second. The camera noise seed the reset names goes
    to the world's camera and to ``on_reset`` (the pose link)."""
    periods = 30
    _, fresh = lockstep_run(cfg, transport, periods)
    spec = isolated_spec(transport)
    resets: list[tuple[int, int | None]] = []
    with open_bus(spec) as bus, JointClient.open(spec, cfg) as client:
        node = DspNode(
            cfg,
            bus,
            lockstep=True,
            sync_resend_s=0.02,
            reply_timeout_s=5.0,
            on_reset=lambda seed: resets.append((node.session, seed)),
        )
        stop = threading.Event()
        thread = threading.Thread(target=node.run, args=(stop,), name="dsp")
        thread.start()
        try:
            first = _answer_periods(client, periods)
            session = node.session
            status = client.reset_scenario(RECV_TIMEOUT_S, seed=7)
            assert status.session == node.session != session
            assert client.sync_tick is None and client.take_statuses() == [status]
            second = _answer_periods(client, periods)
        finally:
            stop.set()
            thread.join(RECV_TIMEOUT_S)
    assert first == second == {k: fresh.states[k] for k in range(periods)}
    assert node.stats.scenario_resets == 1 and resets == [(node.session, 7)]
    assert node.world.seed == 7  # the world's camera noise restarted from the reset's seed
    assert node.stats.missing_periods == 0


def test_a_scenario_reset_is_refused_while_enabled_and_by_a_realtime_dsp(cfg: RigConfig):
    with rig(cfg, "virtual", lockstep=True, sync_resend_s=0.01) as (node, client):
        client.enable()
        stop = threading.Event()
        thread = threading.Thread(target=node.lockstep_period, args=(stop,), name="dsp")
        thread.start()
        try:
            wait_for(lambda: node.torque_enabled, "ENABLE")
            client.send_command(DspCommand.RESET_SCENARIO, repeat=1)
            wait_for(lambda: node.drive.refused == 1, "the refusal")
        finally:
            stop.set()
            thread.join(RECV_TIMEOUT_S)
        assert node.stats.scenario_resets == 0 and node.torque_enabled
    with rig(cfg, "virtual") as (node, client):
        clock = FakeClock(node)
        clock.advance(40)
        q, steps, session = node.world.q.copy(), node.world.step_index, node.session
        client.send_command(DspCommand.RESET_SCENARIO, repeat=1)
        wait_for(lambda: node.drive.refused == 1, "the refusal", clock.pump)
        assert (node.world.step_index, node.session) == (steps, session)
        assert np.array_equal(node.world.q, q) and node.stats.scenario_resets == 0


def test_reset_scenario_times_out_with_a_clear_error_when_no_dsp_confirms(cfg: RigConfig):
    spec = isolated_spec("virtual")
    with (
        JointClient.open(spec, cfg) as client,
        pytest.raises(HalTimeoutError, match="did not confirm a scenario reset"),
    ):
        client.reset_scenario(0.1)


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
        node, tap = DspNode(cfg, bus), StateTap(tap_bus)
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
        node, tap = DspNode(cfg, bus), StateTap(tap_bus)
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


# ------------------------------------------------------------------------------- fuzz

N_FRAMES = 10_000
RAW_DB = cantools.database.load_file(str(DBC_PATH))
DATA_IDS = {m.frame_id: int(m.dbc.attributes["E2EDataID"].value) for m in RAW_DB.messages}
SENDER = {m.frame_id: m.senders[0] for m in RAW_DB.messages}
TORQUE_ID = RAW_DB.get_message_by_name("TorqueCommand").frame_id
CONTROL_ID = RAW_DB.get_message_by_name("DspControl").frame_id


def sign(fid: int, data: bytearray) -> bytes:
    data_id = DATA_IDS[fid]
    data[0] = e2e_crc_reference(data_id, data)
    return bytes(data)


class DspOracle:
    """The verdict the DSP must give each frame (E2E order of checks, counter and re-init)."""

    def __init__(self) -> None:
        self.last: dict[int, tuple[int, int]] = {}
        self.secoc = SecocReference()
        self.tally: Counter[str] = Counter()
        self.torques = 0

    def verdict(self, msg: can.Message, t_ns: int) -> str:
        if msg.is_error_frame:
            return "error_frame"
        fid = msg.arbitration_id
        if msg.is_extended_id or fid not in DATA_IDS:
            return "unknown_id"
        if SENDER[fid] == "DSP":
            return "ignored"
        data = bytes(msg.data or b"")
        if msg.is_remote_frame or len(data) != 16:
            return "wrong_length"
        failed = self.secoc.verdict(fid, SENDER[fid], DATA_IDS[fid], data)
        if failed:
            return failed
        if sign(fid, bytearray(data)) != data:
            return "bad_crc"
        counter, last = data[1] & 0xF, self.last.get(fid)
        self.last[fid] = (counter, t_ns)
        if last is not None and t_ns - last[1] <= DEFAULT_REINIT_AFTER_NS:
            delta = (counter - last[0]) % 16
            if delta == 0:
                self.last[fid] = last
                return "repeated_counter"
            if delta > DEFAULT_MAX_DELTA:
                return "counter_jump"
        if fid == CONTROL_ID and command_is_malformed(data):
            return "decode_error"
        return "accepted"

    def expect(self, msg: can.Message, t_ns: int) -> str:
        kind = self.verdict(msg, t_ns)
        self.tally[kind] += 1
        if kind == "accepted" and msg.arbitration_id == TORQUE_ID:
            self.torques += 1
        return kind


def fuzz_frames(rng: random.Random) -> Iterator[can.Message]:
    """Valid controller frames, their mutations, random junk and the DSP's own ids."""
    ctl = ControllerCodec()
    history: list[can.Message] = []

    def valid() -> can.Message:
        if rng.random() < 0.85:
            msg = ctl.encode_torque(
                rng.uniform(-200, 200), rng.uniform(-20, 20), enable=rng.random() < 0.7
            )
        else:
            msg = ctl.encode_control(rng.choice(list(DspCommand)))
        history.append(msg)
        return msg

    def copy(msg: can.Message, **kw: object) -> can.Message:
        fields = {"arbitration_id": msg.arbitration_id, "is_extended_id": msg.is_extended_id}
        fields["is_fd"] = msg.is_fd
        fields["data"] = bytes(msg.data)
        fields.update(kw)
        return can.Message(**fields)  # type: ignore[arg-type]

    def flip() -> can.Message:
        data = bytearray(valid().data)
        for _ in range(rng.randint(1, 6)):
            bit = rng.randrange(64)
            data[bit // 8] ^= 1 << (bit % 8)
        flipped = copy(history[-1], data=bytes(data))
        # half of them signed by a rig member (a bug, not an attack): the CRC/counter catch it
        return ctl.sign(flipped) if rng.random() < 0.5 else flipped

    def resigned() -> can.Message:
        """Random payload with a valid CRC: reaches the counter check and the decoder."""
        fid = rng.choice([TORQUE_ID, CONTROL_ID])
        data = bytearray(rng.getrandbits(8) for _ in range(8))
        return ctl.sign(can.Message(arbitration_id=fid, is_extended_id=False, data=sign(fid, data)))

    def junk() -> can.Message:
        ext = rng.random() < 0.3
        fid = rng.randrange(1 << 29) if ext else rng.randrange(0x800)
        data = bytes(rng.getrandbits(8) for _ in range(rng.choice([*range(9), 12, 16])))
        return can.Message(arbitration_id=fid, is_extended_id=ext, data=data, is_fd=len(data) > 8)

    def replay() -> can.Message:
        return copy(rng.choice(history[-30:])) if history else valid()

    def resize() -> can.Message:
        return copy(valid(), data=bytes(history[-1].data)[: rng.choice([0, 1, 5, 7])])

    def own_id() -> can.Message:
        fid = rng.choice([f for f, s in SENDER.items() if s == "DSP"])
        return can.Message(arbitration_id=fid, is_extended_id=False, data=bytes(8))

    def odd() -> can.Message:
        kind = rng.randrange(3)
        if kind == 0:
            return can.Message(is_error_frame=True)
        if kind == 1:
            return can.Message(arbitration_id=TORQUE_ID, is_extended_id=False,
                               is_remote_frame=True, dlc=8)  # fmt: skip
        return can.Message(arbitration_id=CONTROL_ID, is_extended_id=False, is_fd=True,
                           data=bytes(16))  # fmt: skip

    choices = [valid, valid, valid, flip, resigned, junk, replay, resize, own_id, odd]
    for _ in range(N_FRAMES):
        yield rng.choice(choices)()


@pytest.mark.parametrize("seed", [11, 12])
def test_fuzz_into_the_dsp_receive_path(cfg: RigConfig, seed: int) -> None:
    rng = random.Random(seed)
    oracle = DspOracle()
    with open_bus(isolated_spec("virtual")) as bus:
        node = DspNode(cfg, bus)
        node.start_realtime(0)
        for i, msg in enumerate(fuzz_frames(rng)):
            t_ns = i * 100_000  # 0.1 ms per frame: 1 s in all, re-init and watchdog reachable
            before = node.codec.stats.as_dict()
            node.handle(msg, t_ns)
            kind = oracle.expect(msg, t_ns)
            after = node.codec.stats.as_dict()
            assert after[kind] == before[kind] + 1, f"frame {i} {msg}: expected {kind}"
            if i % 10 == 9:  # the physics runs on (1 kHz), with whatever torque got through
                node.check_watchdog(t_ns)
                node.physics_step()
                assert np.all(np.isfinite(node.world.q)) and np.all(np.isfinite(node.world.dq))
        stats = node.codec.stats.as_dict()
    for kind, expected in oracle.tally.items():
        assert stats[kind] == expected, f"{kind}: {stats} vs {dict(oracle.tally)}"
    bad = sum(n for k, n in oracle.tally.items() if k not in ("accepted", "ignored"))
    assert stats["rejected"] == bad > N_FRAMES // 4
    assert sum(oracle.tally.values()) == N_FRAMES
    for kind in ("bad_crc", "repeated_counter", "counter_jump", "wrong_length", "unknown_id",
                 "decode_error", "error_frame", "ignored", "bad_mac",
                 "stale_freshness"):  # fmt: skip
        assert oracle.tally[kind] > 0, f"the fuzz never produced {kind}"
    assert node.stats.commands == oracle.torques > 1000
    assert node.stats.physics_steps == N_FRAMES // 10
    assert np.all(np.isfinite(node.world.q)) and np.all(np.isfinite(node.encoder.dq))
    assert np.all(np.abs(node.world.tau_applied) <= np.array(cfg.robot.tau_max))


def test_fuzz_through_the_bus_into_the_running_node(cfg: RigConfig) -> None:
    """2000 fuzz frames over a bus into the node's own realtime loop (thread)."""
    frames = list(fuzz_frames(random.Random(13)))[:2000]
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus, open_bus(spec) as tx:
        node = DspNode(cfg, bus)
        stop = threading.Event()
        runner = threading.Thread(target=node.run, args=(stop,), name="dsp-node")
        runner.start()
        try:
            for msg in frames:
                tx.send(msg)

            def seen() -> int:
                st = node.codec.stats.as_dict()
                return sum(v for k, v in st.items() if k not in ("rejected", "lost"))

            wait_for(lambda: seen() == len(frames), "every frame counted")
        finally:
            stop.set()
            runner.join(timeout=RECV_TIMEOUT_S)
    assert not runner.is_alive()
    assert node.stats.rejected["rejected"] > 0
    assert np.all(np.isfinite(node.world.q)) and np.all(np.isfinite(node.world.dq))


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
