"""One contract suite for every CAN transport (python-can style); the bus factory's tests are
in ``test_bus_factory.py``.

Every ``transport`` test runs on ``virtual`` (in-process), ``udp_multicast`` (host-local,
loopback only) and ``socketcan`` (a real vcan0; marked ``vcan``, run by scripts/vcan_pytest.py).
Receive timeouts are generous because user-mode Linux is slow; nothing asserts on timings.
The client reads the bus in the test's thread, as in the controller (it has no thread of its own).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import can
import can.util
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import ControllerCodec, DspCodec, DspCommand
from hal.can_frames import RAD_PER_COUNT, DspControl, DspStatus, Frame, JointState, TorqueCommand
from hal.config import RigConfig
from hal.errors import HalError, HalTimeoutError
from hal.joint_client import DRAIN_MAX_FRAMES, JointClient
from tests.support.joint import next_state, read_until
from tests.support.vcan import VCAN_CHANNEL, requires_vcan

RECV_TIMEOUT_S = 5.0

TRANSPORTS = [
    pytest.param("virtual", id="virtual"),
    pytest.param("udp_multicast", id="udp_multicast"),
    pytest.param("socketcan", id="socketcan", marks=[pytest.mark.vcan, requires_vcan]),
]


@pytest.fixture(params=TRANSPORTS)
def spec(request: pytest.FixtureRequest) -> str:
    if request.param == "socketcan":
        return f"socketcan:{VCAN_CHANNEL}"
    return isolated_spec(request.param)


@pytest.fixture
def dsp_bus(spec: str) -> Iterator[can.BusABC]:
    with open_bus(spec) as bus:
        yield bus


@pytest.fixture
def client(spec: str, cfg: RigConfig) -> Iterator[JointClient]:
    with JointClient.open(spec, cfg) as joint_client:
        yield joint_client


def recv_frames(bus: can.BusABC, codec: DspCodec, count: int) -> list[Frame]:
    """The next ``count`` frames that ``codec`` accepts (fails after RECV_TIMEOUT_S)."""
    frames: list[Frame] = []
    deadline = time.monotonic() + RECV_TIMEOUT_S
    while len(frames) < count:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"only {frames} received; codec stats {codec.stats}"
        msg = bus.recv(timeout=remaining)
        if msg is not None and (frame := codec.decode(msg)) is not None:
            frames.append(frame)
    return frames


def sends(bus: can.BusABC) -> bool:
    """Whether ``bus`` still sends a valid frame: once shut down, a python-can bus refuses
    (virtual, udp_multicast: :class:`can.CanOperationError`; socketcan: its closed socket's
    descriptor, -1, is refused by ``select`` with ValueError), an open one sends."""
    try:
        bus.send(can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False))
    except (can.CanOperationError, ValueError):
        return False
    return True


def send_state(bus: can.BusABC, dsp: DspCodec, q: tuple[float, float], sample: int) -> None:
    for msg in dsp.encode_state(q, (0.5, -0.25), sample):
        bus.send(msg)


# ------------------------------------------------------------------------------ contract


def test_bus_is_a_context_manager_and_shutdown_twice_is_safe(spec: str) -> None:
    with open_bus(spec) as bus:
        assert isinstance(bus, can.BusABC)
    bus.shutdown()


def test_frames_travel_unchanged_and_not_back_to_the_sender(spec: str) -> None:
    ctl, dsp = ControllerCodec(), DspCodec()
    sent = [
        ctl.encode_torque(3.0, -1.0, tick=5),
        ctl.encode_control(DspCommand.ENABLE),
        *dsp.encode_state((0.1, 0.2), (0.3, 0.4), 1),
        dsp.encode_status(DspStatus(True, False)),
        dsp.encode_sync(99),
    ]
    with open_bus(spec) as tx, open_bus(spec) as rx:
        for msg in sent:
            tx.send(msg)
        for msg in sent:
            got = rx.recv(timeout=RECV_TIMEOUT_S)
            assert got is not None, f"frame {msg.arbitration_id:#x} not received"
            assert got.arbitration_id == msg.arbitration_id
            assert not got.is_extended_id and not got.is_remote_frame
            assert bytes(got.data) == bytes(msg.data)
        assert tx.recv(timeout=0.05) is None


def test_receive_own_messages_when_asked(spec: str) -> None:
    msg = DspCodec().encode_sync(1)
    with open_bus(spec, receive_own_messages=True) as bus:
        bus.send(msg)
        got = bus.recv(timeout=RECV_TIMEOUT_S)
        assert got is not None and bytes(got.data) == bytes(msg.data)


def test_client_assembles_state_status_and_sync(dsp_bus: can.BusABC, client: JointClient) -> None:
    dsp = DspCodec()
    t0 = time.monotonic_ns()
    send_state(dsp_bus, dsp, (1000 * RAD_PER_COUNT, -0.5), 3)
    state = next_state(client, RECV_TIMEOUT_S)
    assert isinstance(state, JointState)
    assert state.q == (1000 * RAD_PER_COUNT, pytest.approx(-0.5, abs=RAD_PER_COUNT))
    assert state.dq == (pytest.approx(0.5), pytest.approx(-0.25))
    assert state.sample == 3 and state.t_ns > t0
    assert client.latest_state(max_age_s=60.0) == state
    assert client.state_age_s() is not None

    sent_ns = time.monotonic_ns()
    dsp_bus.send(dsp.encode_status(DspStatus(True, False, lockstep=True, tick=77)))
    dsp_bus.send(dsp.encode_sync(42))
    assert client.wait_sync(RECV_TIMEOUT_S) == 42
    read_ns = time.monotonic_ns()
    assert client.sync_tick == 42
    assert client.status == DspStatus(True, False, lockstep=True, tick=77)
    # the status arrived between its send and the end of the read: its age at the end of the
    # read is within that span, whatever the span was; and it grows with the clock given
    age = client.status_age_s_at(read_ns)
    assert 0 <= age <= (read_ns - sent_ns) * 1e-9
    assert client.status_age_s_at(read_ns + 10**9) == pytest.approx(age + 1.0, abs=1e-9)
    stats = client.stats
    assert (stats.states, stats.syncs, stats.statuses, stats.e2e.rejected) == (1, 1, 1, 0)


def test_client_commands_reach_the_dsp_in_order(dsp_bus: can.BusABC, client: JointClient) -> None:
    dsp = DspCodec()
    client.enable()
    client.send_torque(1.5, -0.25, tick=7)
    client.disable()
    frames = recv_frames(dsp_bus, dsp, 8)
    assert frames == [
        DspControl(DspCommand.FAULT_RESET),
        DspControl(DspCommand.FAULT_RESET),
        DspControl(DspCommand.ENABLE),
        DspControl(DspCommand.ENABLE),
        TorqueCommand(1.5, -0.25, True, 7),
        DspControl(DspCommand.DISABLE),
        DspControl(DspCommand.DISABLE),
        TorqueCommand(0.0, 0.0, False, 0),
    ]
    assert dsp.stats.rejected == 0


def test_realtime_commands_carry_their_delay_after_the_release(
    dsp_bus: can.BusABC, client: JointClient
) -> None:
    """``release_delay_us`` goes out in ``Tick`` (µs), clamped to [0, 65535]; it overrides the
    latest Sync tick (realtime has none)."""
    dsp = DspCodec()
    dsp_bus.send(dsp.encode_sync(9))
    assert client.wait_sync(RECV_TIMEOUT_S) == 9
    for delay, sent in ((0, 0), (1234, 1234), (-5, 0), (70_000, 65_535)):
        client.send_torque(0.5, 0.1, release_delay_us=delay)
        (command,) = recv_frames(dsp_bus, dsp, 1)
        assert isinstance(command, TorqueCommand) and command.tick == sent
    assert dsp.stats.rejected == 0


def test_every_status_since_the_last_take_comes_in_order(
    dsp_bus: can.BusABC, spec: str, cfg: RigConfig
) -> None:
    """A fault, its reset and the re-enable that arrive between two reads are all handed
    over, oldest first (the newest alone would look like "still in fault")."""
    from hal.drive_state import DriveState, FaultReason
    from hal.joint_client import STATUS_BACKLOG

    dsp = DspCodec()
    seq = [
        DspStatus(False, True, drive_state=DriveState.FAULT, fault_reason=FaultReason.WATCHDOG),
        DspStatus(False, False, drive_state=DriveState.SWITCH_ON_DISABLED),
        DspStatus(True, False, drive_state=DriveState.OPERATION_ENABLED),
    ]
    with JointClient.open(spec, cfg) as client:
        for st in seq:
            dsp_bus.send(dsp.encode_status(st))
        read_until(client, lambda: client.stats.statuses >= len(seq), RECV_TIMEOUT_S)
        got = client.take_statuses()
        assert [(g.drive_state, g.fault_reason) for g in got] == [
            (st.drive_state, st.fault_reason) for st in seq
        ]
        assert client.take_statuses() == [] and client.status == got[-1]
        for _ in range(STATUS_BACKLOG + 5):  # a backlog keeps the newest
            dsp_bus.send(dsp.encode_status(seq[0]))
        total = len(seq) + STATUS_BACKLOG + 5
        assert read_until(client, lambda: client.stats.statuses == total, RECV_TIMEOUT_S)
        assert len(client.take_statuses()) == STATUS_BACKLOG


def test_lockstep_exchange(dsp_bus: can.BusABC, client: JointClient) -> None:
    dsp = DspCodec()
    for k in range(20):
        send_state(dsp_bus, dsp, (0.01 * k, 0.0), k)
        dsp_bus.send(dsp.encode_sync(k))
        tick = client.wait_sync(RECV_TIMEOUT_S)
        assert tick == k
        assert client.latest_state(max_age_s=60.0).sample == k % 16
        client.send_torque(0.1 * k, -0.01 * k)  # tick defaults to the latest Sync
        (command,) = recv_frames(dsp_bus, dsp, 1)
        assert isinstance(command, TorqueCommand)
        assert command.tick == k and command.enable is False
    assert dsp.stats.rejected == 0 and client.stats.e2e.rejected == 0


def test_silent_dsp_raises_timeouts(client: JointClient) -> None:
    assert not client.wait_readable(0.05)
    assert client.drain() == 0
    with pytest.raises(HalTimeoutError, match="no joint state"):
        client.latest_state()
    with pytest.raises(HalTimeoutError, match="Sync"):
        client.wait_sync(0.05)
    assert client.status is None and client.sync_tick is None and client.state_age_s() is None
    assert client.status_age_s_at(time.monotonic_ns()) is None and client.take_statuses() == []
    assert client.stats.frames == client.stats.transport_errors == 0


def record_sleeps(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """From now on, ``time.sleep`` in this thread only records what it was asked (other
    threads still sleep)."""
    pauses: list[float] = []
    me, real_sleep = threading.get_ident(), time.sleep

    def sleep(seconds: float) -> None:
        if threading.get_ident() == me:
            pauses.append(seconds)
        else:
            real_sleep(seconds)

    monkeypatch.setattr(time, "sleep", sleep)
    return pauses


def test_a_frame_waiting_is_readable_and_drain_takes_it(
    dsp_bus: can.BusABC, client: JointClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``wait_readable`` reports a waiting frame without reading it (a bus without a file
    descriptor, ``virtual``, only pauses briefly and says no); ``drain`` reads all that wait and
    returns at once when none does."""
    send_state(dsp_bus, DspCodec(), (0.25, -0.25), 1)
    try:
        client.bus.fileno()
    except NotImplementedError:  # what it asks to wait, not how long the host took
        with monkeypatch.context() as patch:
            pauses = record_sleeps(patch)
            assert not client.wait_readable(RECV_TIMEOUT_S)
        assert len(pauses) == 1 and 0 < pauses[0] < RECV_TIMEOUT_S / 2, pauses
    else:
        assert client.wait_readable(RECV_TIMEOUT_S)
    assert client.stats.frames == 0  # nothing read yet
    assert read_until(client, lambda: client.stats.frames == 2, RECV_TIMEOUT_S)
    assert client.states_received == 1 and client.drain() == 0
    assert client.latest_state(max_age_s=60.0).q[0] == pytest.approx(0.25, abs=RAD_PER_COUNT)


def test_receive_errors_are_counted_and_read_as_no_frame(
    dsp_bus: can.BusABC, client: JointClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A driver error in ``bus.recv`` never reaches the caller of ``drain``, ``wait_sync`` or
    ``await_new_session``: each one is counted, and the client reads on afterwards."""

    def broken(timeout: float | None = None) -> can.Message | None:
        raise can.CanOperationError("driver says no")

    monkeypatch.setattr(client.bus, "recv", broken)
    assert client.drain() == 0
    with pytest.raises(HalTimeoutError, match="Sync"):
        client.wait_sync(0.01)
    with pytest.raises(HalTimeoutError, match="scenario reset"):
        client.await_new_session(0.01, lambda: None)
    errors = client.stats.transport_errors
    assert errors >= 3 and client.stats.frames == 0
    monkeypatch.undo()
    dsp_bus.send(DspCodec().encode_sync(5))
    assert client.wait_sync(RECV_TIMEOUT_S) == 5
    assert client.stats.transport_errors == errors


def test_a_bus_that_never_runs_dry_cannot_hold_drain(
    client: JointClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A flood (or a reader slower than the sender, as under user-mode Linux) always has a
    frame waiting: ``drain`` stops after ``DRAIN_MAX_FRAMES`` and counts the cut; the next
    drain goes on where it stopped."""
    flood = DspCodec()
    served = [0]

    def always(timeout: float | None = None) -> can.Message | None:
        served[0] += 1
        return None if served[0] > 10 * DRAIN_MAX_FRAMES else flood.encode_sync(served[0])

    monkeypatch.setattr(client.bus, "recv", always)
    assert client.drain() == DRAIN_MAX_FRAMES
    assert client.stats.drains_cut == 1 and client.stats.frames == DRAIN_MAX_FRAMES
    assert client.drain() == DRAIN_MAX_FRAMES and client.stats.drains_cut == 2
    assert client.stats.syncs == 2 * DRAIN_MAX_FRAMES  # every frame taken was decoded


def test_stale_state_raises_timeout(dsp_bus: can.BusABC, client: JointClient) -> None:
    send_state(dsp_bus, DspCodec(), (0.0, 0.0), 0)
    next_state(client, RECV_TIMEOUT_S)
    time.sleep(0.02)
    with pytest.raises(HalTimeoutError, match="DSP silent"):
        client.latest_state(max_age_s=0.001)
    with pytest.raises(TimeoutError):  # the builtin is catchable too
        client.latest_state(max_age_s=0.001)


def test_bad_frames_on_the_wire_are_counted_and_hooked(spec: str, dsp_bus: can.BusABC) -> None:
    dsp = DspCodec()
    seen: list[can.Message] = []
    good_pos, _ = dsp.encode_state((0.0, 0.0), (0.0, 0.0), 0)
    corrupted = bytearray(good_pos.data)
    corrupted[4] ^= 0x10
    bad = [
        can.Message(
            arbitration_id=good_pos.arbitration_id, data=corrupted, is_extended_id=False, is_fd=True
        ),
        good_pos,  # repeated counter (sent once before)
        can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False),
        can.Message(arbitration_id=good_pos.arbitration_id, data=bytes(4), is_extended_id=False),
    ]
    with JointClient.open(spec) as client:
        client.bus.rx_hook = seen.append  # every raw frame, before any check
        dsp_bus.send(good_pos)
        for msg in bad:
            dsp_bus.send(msg)
        dsp_bus.send(dsp.encode_sync(1))  # sentinel: frames arrive in order
        client.wait_sync(RECV_TIMEOUT_S)
        stats = client.stats
    e2e = stats.e2e
    # the corrupted frame fails its MAC, the repeat its freshness (SecOC checks come first)
    assert (e2e.bad_mac, e2e.stale_freshness, e2e.unknown_id, e2e.wrong_length) == (1, 1, 1, 1)
    assert e2e.rejected == 4 and e2e.accepted == 2
    assert [bytes(m.data) for m in seen[:5]] == [bytes(m.data) for m in (good_pos, *bad)]
    assert seen[5].arbitration_id == 0x080  # the Sync
    assert stats.frames == len(seen) == 6


def test_close_disarms_an_armed_dsp_and_is_idempotent(spec: str, dsp_bus: can.BusABC) -> None:
    client = JointClient.open(spec)
    client.enable()
    client.close()
    client.close()
    assert client.closed and not sends(client.bus)
    frames = recv_frames(dsp_bus, DspCodec(), 7)
    assert frames == [
        DspControl(DspCommand.FAULT_RESET),
        DspControl(DspCommand.FAULT_RESET),
        DspControl(DspCommand.ENABLE),
        DspControl(DspCommand.ENABLE),
        DspControl(DspCommand.DISABLE),
        DspControl(DspCommand.DISABLE),
        TorqueCommand(0.0, 0.0, False, 0),
    ]


def test_client_does_not_own_a_bus_it_was_given(spec: str) -> None:
    with open_bus(spec) as bus:
        with JointClient(bus) as client:
            client.send_torque(0.0, 0.0)
        assert sends(bus)  # still open: the caller's to close
        with pytest.raises(HalError, match="closed"):
            client.send_torque(0.0, 0.0)
