"""Shared helpers of the emulated DSP's tests: a DSP and a JointClient on one isolated bus, a
fake clock for realtime nodes, a threaded lockstep controller (PD law) and a lockstep run."""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import can
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import ControllerCodec
from hal.can_frames import DspStatus
from hal.config import RigConfig
from hal.errors import HalTimeoutError
from hal.joint_client import JointClient
from hal.secoc import rig_key
from plant_emulator.dsp import make_dsp
from plant_emulator.dsp_lockstep import LockstepDsp
from plant_emulator.dsp_node import DspNode
from plant_emulator.dsp_realtime import RealtimeDsp

RECV_TIMEOUT_S = 10.0
MS = 1_000_000
T0 = 1_000_000_000_000
"""Fake monotonic start time of realtime runs (ns)."""

TRANSPORTS = ["virtual", "udp_multicast"]


def free_state_sync(cfg: RigConfig) -> RigConfig:
    """The joint state after every physics step, on the DSP's own clock at ``rates.state_hz``
    (the command-synchronised default is tested in test_state_sync.py)."""
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
    """A DSP (``lockstep=True``: the lockstep runner) on its own bus and a JointClient
    (controller side) on the same bus."""
    spec = isolated_spec(transport)
    with open_bus(spec) as bus, JointClient.open(spec, cfg) as client:
        yield make_dsp(cfg, bus, **node_kwargs), client  # type: ignore[arg-type]


class FakeClock:
    """Drives a realtime node: ``now`` in ns, ``advance`` runs the steps that became due."""

    def __init__(self, node: RealtimeDsp) -> None:
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
                msg = ControllerCodec(key=rig_key(client.cfg)).encode_torque(
                    *tau, enable=True, tick=k
                )
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
) -> tuple[LockstepDsp, Responder]:
    spec = isolated_spec(transport)
    with open_bus(spec) as bus, JointClient.open(spec, cfg) as client:
        node = LockstepDsp(cfg, bus, sync_resend_s=0.02, reply_timeout_s=5.0, pose_sink=pose_sink)
        with Responder(client, spoil) as responder:
            node.run(threading.Event(), duration_s=periods / cfg.rates.control_hz)
    return node, responder
