"""The simulator-control channel (hal.sim_control, zenoh ``hil/sim/control``): the harness's
scenario reset and camera seed, authenticated with the rig key, taken by the emulated DSP
between lockstep periods; a realtime DSP refuses it, a forged or replayed message changes
nothing and is counted."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from hal.bus import isolated_spec, open_bus
from hal.config import RigConfig
from hal.errors import HalCodecError, HalTimeoutError
from hal.joint_client import JointClient
from hal.secoc import now_us
from hal.sim_control import (
    FRESHNESS_WINDOW_US,
    SEED_MAX,
    SIZE,
    SimCommand,
    SimControl,
    SimControlReceiver,
    SimControlSender,
    encode,
)
from hal.zenoh_session import free_loopback_port, open_session
from plant_emulator.dsp_lockstep import LockstepDsp
from plant_emulator.dsp_realtime import RealtimeDsp
from plant_emulator.entry import serve_sim_control
from plant_emulator.pose_link import wait_until
from tests.support import session_key
from tests.support.dsp import (
    RECV_TIMEOUT_S,
    TRANSPORTS,
    FakeClock,
    free_state_sync,
    lockstep_run,
    pd_torque,
)

RESET = SimControl(SimCommand.RESET_SCENARIO, 7)


@pytest.fixture
def cfg(cfg: RigConfig) -> RigConfig:
    return free_state_sync(cfg)


# ---------------------------------------------------------------------------- the codec


def test_an_authentic_fresh_message_is_taken_once() -> None:
    taken: list[SimControl] = []
    rx = SimControlReceiver(taken.append, key=session_key())
    fv = now_us()
    assert rx.feed(encode(RESET, fv, session_key())) == RESET
    assert rx.feed(encode(SimControl(SimCommand.RESET_SCENARIO), fv + 1, session_key()))
    assert taken == [RESET, SimControl(SimCommand.RESET_SCENARIO, None)]
    assert rx.counts.as_dict()["accepted"] == 2 and rx.counts.rejected == 0


def test_forged_replayed_stale_and_malformed_messages_are_rejected_and_counted() -> None:
    taken: list[SimControl] = []
    rx = SimControlReceiver(taken.append, key=session_key())
    fv = now_us()
    assert rx.feed(encode(RESET, fv, b"x" * 32)) is None  # another rig's key
    good = encode(RESET, fv, session_key())
    assert rx.feed(good) == RESET
    assert rx.feed(good) is None  # the same message again: a replay
    old = encode(RESET, fv - FRESHNESS_WINDOW_US - 1, session_key())
    assert rx.feed(old) is None  # authentic but older than the last accepted: also a replay
    ahead = encode(RESET, fv + 2 * FRESHNESS_WINDOW_US, session_key())
    assert rx.feed(ahead) is None  # far from this clock: stale
    assert rx.feed(good[:-1]) is None and rx.feed(b"HS" + bytes(SIZE - 2)) is None
    tampered = bytearray(encode(RESET, fv + 5, session_key()))
    tampered[16] ^= 1  # the seed, under the MAC
    assert rx.feed(bytes(tampered)) is None
    assert taken == [RESET]
    assert rx.counts.as_dict() == {
        "accepted": 1,
        "bad_mac": 2,
        "malformed": 1,
        "bad_version": 1,
        "replayed": 2,
        "stale": 1,
        "rejected": 7,
    }


@pytest.mark.parametrize("seed", [-1, SEED_MAX + 1, True, 1.5])
def test_a_seed_that_cannot_be_sent_is_refused(seed: object) -> None:
    with pytest.raises(HalCodecError, match="seed"):
        encode(SimControl(SimCommand.RESET_SCENARIO, seed), now_us(), session_key())  # type: ignore[arg-type]


# ---------------------------------------------------------------- the DSP takes the reset


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


@contextmanager
def zenoh_pair() -> Iterator[tuple[object, object]]:
    """The emulator's hub session and a controller's client session on a private port."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    with (
        open_session(listen=True, endpoint=endpoint) as hub,
        open_session(listen=False, endpoint=endpoint, wait_s=RECV_TIMEOUT_S) as client,
    ):
        yield hub, client


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_a_reset_over_the_channel_runs_again_exactly_as_a_fresh_dsp(
    cfg: RigConfig, transport: str
) -> None:
    """A scenario reset sent on ``hil/sim/control`` between two runs on one running lockstep
    DSP: the second run sees the same states as the first and as a freshly started DSP, under
    a new session that the controller reads on CAN; nothing of the first run reaches the
    second. The seed goes to the world's camera and to ``on_reset`` (the pose link). A forged
    reset before it changed nothing and was counted."""
    periods = 30
    _, fresh = lockstep_run(cfg, transport, periods)
    spec = isolated_spec(transport)
    resets: list[tuple[int, int | None]] = []
    with (
        open_bus(spec) as bus,
        JointClient.open(spec, cfg) as client,
        zenoh_pair() as (hub, controller_session),
    ):
        node = LockstepDsp(
            cfg,
            bus,
            sync_resend_s=0.02,
            reply_timeout_s=5.0,
            on_reset=lambda seed: resets.append((node.session, seed)),
        )
        sender = SimControlSender(controller_session, key=session_key())
        forger = SimControlSender(controller_session, key=b"x" * 32)
        stop = threading.Event()
        thread = threading.Thread(target=node.run, args=(stop,), name="dsp")
        with serve_sim_control(hub, node, session_key()) as receiver:
            assert wait_until(sender.has_subscribers, RECV_TIMEOUT_S)
            thread.start()
            try:
                first = _answer_periods(client, periods)
                session = node.session
                with pytest.raises(HalTimeoutError, match="scenario reset"):
                    client.await_new_session(0.3, lambda: forger.reset_scenario(9))
                assert receiver.counts.bad_mac == 1 and node.session == session
                status = client.await_new_session(RECV_TIMEOUT_S, lambda: sender.reset_scenario(7))
                assert status.session == node.session != session
                assert client.sync_tick is None and client.take_statuses() == [status]
                second = _answer_periods(client, periods)
            finally:
                stop.set()
                thread.join(RECV_TIMEOUT_S)
    assert first == second == {k: fresh.states[k] for k in range(periods)}
    assert receiver.counts.as_dict()["accepted"] == 1 and receiver.counts.rejected == 1
    assert node.stats.scenario_resets == 1 and resets == [(node.session, 7)]
    assert node.world.seed == 7  # the world's camera noise restarted from the reset's seed
    assert node.stats.missing_periods == 0


def test_a_realtime_dsp_refuses_a_reset(cfg: RigConfig) -> None:
    spec = isolated_spec("virtual")
    with open_bus(spec) as bus:
        node = RealtimeDsp(cfg, bus)
        clock = FakeClock(node)
        clock.advance(40)
        q, steps, session = node.world.q.copy(), node.world.step_index, node.session
        assert not node.request_reset(3)
        clock.advance(40)
        assert node.stats.resets_refused == 1 and node.stats.scenario_resets == 0
        assert node.session == session and node.world.step_index >= steps
        assert np.array_equal(node.world.q, q)


def test_waiting_for_a_reset_times_out_with_a_clear_error_when_no_dsp_confirms(
    cfg: RigConfig,
) -> None:
    with (
        JointClient.open(isolated_spec("virtual"), cfg) as client,
        pytest.raises(HalTimeoutError, match="did not confirm a scenario reset"),
    ):
        client.await_new_session(0.1, lambda: None)
