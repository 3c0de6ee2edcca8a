"""The emulated DSP's lockstep clock (Sync per period, the command answers it, re-sends, the
watchdog in periods, the wait for the controller) against a real
JointClient on real in-process buses. Receive timeouts are generous; nothing asserts wall-clock
timings.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest

from hal.config import RigConfig, config_from_dict
from tests.support.dsp import (
    RECV_TIMEOUT_S,
    TRANSPORTS,
    free_state_sync,
    lockstep_run,
    rig,
    wait_for,
)


@pytest.fixture
def cfg(cfg: RigConfig) -> RigConfig:
    """These tests read the joint state after every physics step (:func:`free_state_sync`)."""
    return free_state_sync(cfg)


# -------------------------------------------------------------------------------- lockstep


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
        assert node.stats.skipped_periods == 0  # not yet: the controller may have ended
        assert node.stats.sync_resends >= 1
        assert node.world.step_index == steps + node.substeps  # still one period per Sync
        assert np.allclose(node.tau_cmd, (4.0, 0.4)), "a late command changed the torque"
        # Period 2 answered again with a new torque.
        client.send_torque(1.0, 0.1, tick=2)
        assert node.lockstep_period(stop)
        assert node.stats.missing_periods == 1
        assert node.stats.skipped_periods == 1  # a command followed: the run went on without it
        assert np.allclose(node.tau_cmd, (1.0, 0.1))
        assert node.last_cmd_tick == 2
        # Period 3 unanswered, and nothing after it: the run's end, not a skipped period.
        assert node.lockstep_period(stop)
        assert (node.stats.missing_periods, node.stats.skipped_periods) == (2, 1)
        # A scenario reset starts the next run of a plan: its skipped periods count apart.
        node.request_reset()
        assert node.lockstep_period(stop)
        assert node.stats.scenario_resets == 1
        assert (node.stats.skipped_periods, node.stats.skipped_by_run) == (1, [1, 0])


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_lockstep_watchdog_counts_periods(cfg: RigConfig, transport: str) -> None:
    """Commands for periods 0..4 only: the DSP trips at period 7 (3 periods of silence). The
    wait for each missing period is the configuration's ``dsp.lockstep_reply_timeout_s``."""
    data = cfg.to_dict()
    data["dsp"]["lockstep_reply_timeout_s"] = 0.05
    cfg = config_from_dict(data)
    with rig(cfg, transport, lockstep=True, sync_resend_s=0.02) as (node, client):
        assert node.reply_timeout_s == 0.05
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
