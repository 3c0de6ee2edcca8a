"""Fuzz: 10 000 random and mutated frames into the client's and the DSP's receive paths.

An independent oracle (its own SecOC MAC and freshness model, bitwise CRC, its own counter
model, ids and data ids read with plain cantools) predicts the verdict of every frame; the
receivers must never raise and must count every frame exactly as the oracle says, kind by kind.
"""

from __future__ import annotations

import random
from collections import Counter
from collections.abc import Callable, Iterator

import can
import cantools
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import CanEndpoint, ControllerCodec, DspCodec, DspCommand
from hal.can_database import DBC_PATH
from hal.can_frames import (
    DspControl,
    DspStatus,
    Frame,
    JointPosition,
    JointVelocity,
    Sync,
    TorqueCommand,
)
from hal.drive_state import DriveState, FaultReason
from hal.e2e import DEFAULT_MAX_DELTA
from hal.joint_client import JointClient
from tests.support import SecocReference, command_is_malformed, e2e_crc_reference
from tests.support.joint import read_until

N_FRAMES = 10_000
RAW_DB = cantools.database.load_file(str(DBC_PATH))
DATA_IDS = {m.frame_id: m.dbc.attributes["E2EDataID"].value for m in RAW_DB.messages}
SENDERS = {m.frame_id: m.senders[0] for m in RAW_DB.messages}
COMMAND_ID = RAW_DB.get_message_by_name("DspControl").frame_id
STATUS_ID = RAW_DB.get_message_by_name("DspStatus").frame_id


class Oracle:
    """Expected verdict of each frame for a receiving ``node`` (no re-init: time stands still)."""

    def __init__(self, node: str) -> None:
        self.node = node
        self.last: dict[int, int] = {}
        self.secoc = SecocReference()
        self.tally: Counter[str] = Counter()

    def verdict(self, msg: can.Message) -> str:
        if msg.is_error_frame:
            return "error_frame"
        fid = msg.arbitration_id
        if msg.is_extended_id or fid not in DATA_IDS:
            return "unknown_id"
        if SENDERS[fid] == self.node:
            return "ignored"
        data = bytes(msg.data or b"")
        if msg.is_remote_frame or len(data) != 16:
            return "wrong_length"
        failed = self.secoc.verdict(fid, SENDERS[fid], DATA_IDS[fid], data)
        if failed:
            return failed
        data_id = DATA_IDS[fid]
        if e2e_crc_reference(data_id, data) != data[0]:
            return "bad_crc"
        counter, last = data[1] & 0xF, self.last.get(fid)
        self.last[fid] = counter
        if last is not None:
            delta = (counter - last) % 16
            if delta == 0:
                self.last[fid] = last
                return "repeated_counter"
            if delta > DEFAULT_MAX_DELTA:
                return "counter_jump"
        if fid == COMMAND_ID and command_is_malformed(data):
            return "decode_error"
        # DspStatus: DriveState (bits 24..26) and FaultReason (27..30) outside their enums
        if fid == STATUS_ID and (
            data[3] & 7 not in {int(s) for s in DriveState}
            or (data[3] >> 3) & 0xF not in {int(r) for r in FaultReason}
        ):
            return "decode_error"
        return "accepted"

    def expect(self, msg: can.Message) -> str:
        kind = self.verdict(msg)
        self.tally[kind] += 1
        return kind


class FrameSource:
    """Valid frames from a peer codec, and mutations of them, chosen by a seeded RNG."""

    def __init__(self, rng: random.Random, peer: CanEndpoint, make: Callable[[], Frame]) -> None:
        self.rng, self.peer, self.make = rng, peer, make
        self.history: list[can.Message] = []

    def valid(self) -> can.Message:
        msg = self.peer.encode(self.make())
        self.history.append(msg)
        return msg

    def __iter__(self) -> Iterator[can.Message]:
        rng = self.rng
        mutations: list[Callable[[], can.Message]] = [
            self.valid,
            self.valid,
            self.flip_bits,
            self.flip_bits_signed,
            self.random_frame,
            self.replay,
            self.resize,
            self.retarget,
            self.recounter,
            self.odd_frame,
        ]
        for _ in range(N_FRAMES):
            yield rng.choice(mutations)()

    def _copy(self, msg: can.Message, **changes: object) -> can.Message:
        fields = {
            "arbitration_id": msg.arbitration_id,
            "is_extended_id": msg.is_extended_id,
            "data": bytes(msg.data),
            "is_fd": msg.is_fd,
        }
        fields.update(changes)
        return can.Message(**fields)  # type: ignore[arg-type]

    def flip_bits(self) -> can.Message:
        data = bytearray(self.valid().data)
        for _ in range(self.rng.randint(1, 4)):
            bit = self.rng.randrange(64)
            data[bit // 8] ^= 1 << (bit % 8)
        return self._copy(self.history[-1], data=bytes(data))

    def flip_bits_signed(self) -> can.Message:
        """Bits flipped in bytes 0..7 by an authentic sender (a rig member's bug): the CRC, the
        counter or the decode catches it."""
        return self.peer.sign(self.flip_bits())

    def random_frame(self) -> can.Message:
        rng = self.rng
        extended = rng.random() < 0.2
        known = rng.random() < 0.6
        fid = rng.choice(list(DATA_IDS)) if known else rng.randrange(0x800)
        if extended:
            fid = rng.randrange(1 << 29) if not known else fid
        length = rng.choice([16, 16, 8, rng.choice([*range(9), 12])])
        data = bytes(rng.getrandbits(8) for _ in range(length))
        fd = length > 8 or rng.random() < 0.5
        return can.Message(arbitration_id=fid, is_extended_id=extended, data=data, is_fd=fd)

    def replay(self) -> can.Message:
        if not self.history:
            return self.valid()
        return self._copy(self.rng.choice(self.history[-40:]))

    def resize(self) -> can.Message:
        data = bytes(self.valid().data)
        length = self.rng.choice([0, 1, 4, 7, 8, 12])
        return self._copy(self.history[-1], data=data[:length])

    def retarget(self) -> can.Message:
        return self._copy(self.valid(), arbitration_id=self.rng.choice(list(DATA_IDS)))

    def recounter(self) -> can.Message:
        """A frame with a valid CRC but an arbitrary counter (and, for commands, any command)."""
        data = bytearray(self.valid().data)
        fid = self.history[-1].arbitration_id
        data[1] = (data[1] & 0xF0) | self.rng.randrange(16)
        if fid == COMMAND_ID and self.rng.random() < 0.5:
            data[2] = self.rng.randrange(256)
        data_id = DATA_IDS[fid]
        data[0] = e2e_crc_reference(data_id, data)
        return self.peer.sign(self._copy(self.history[-1], data=bytes(data)))  # authentic

    def odd_frame(self) -> can.Message:
        fid = self.rng.choice(list(DATA_IDS))
        kind = self.rng.randrange(3)
        if kind == 0:
            return can.Message(is_error_frame=True)
        if kind == 1:
            return can.Message(
                arbitration_id=fid, is_extended_id=False, is_remote_frame=True, dlc=8
            )
        return can.Message(arbitration_id=fid, is_extended_id=False, is_fd=True, data=bytes(12))


def dsp_frames(rng: random.Random) -> Callable[[], Frame]:
    def make() -> Frame:
        pick = rng.randrange(4)
        if pick == 0:
            return JointPosition(rng.uniform(-50, 50), rng.uniform(-4, 4), rng.randrange(16))
        if pick == 1:
            return JointVelocity(rng.uniform(-80, 80), rng.uniform(-1, 1), rng.randrange(16))
        if pick == 2:
            return DspStatus(*(rng.random() < 0.5 for _ in range(4)), rng.randrange(300))
        return Sync(rng.getrandbits(32))

    return make


def controller_frames(rng: random.Random) -> Callable[[], Frame]:
    def make() -> Frame:
        if rng.random() < 0.8:
            return TorqueCommand(rng.uniform(-200, 200), rng.uniform(-20, 20), rng.random() < 0.5)
        return DspControl(rng.choice(list(DspCommand)))

    return make


def assert_counts_match(stats_dict: dict[str, int], oracle: Oracle) -> None:
    for kind, expected in oracle.tally.items():
        assert stats_dict[kind] == expected, f"{kind}: {stats_dict} vs {dict(oracle.tally)}"
    bad = sum(n for k, n in oracle.tally.items() if k not in ("accepted", "ignored"))
    assert stats_dict["rejected"] == bad
    assert bad > N_FRAMES // 4  # the fuzz really exercised the rejection paths


@pytest.mark.parametrize("seed", [1, 2])
def test_client_receive_path_counts_every_frame(seed: int) -> None:
    rng = random.Random(seed)
    oracle = Oracle("Controller")
    with (
        open_bus(isolated_spec("virtual")) as bus,
        JointClient(bus) as client,
    ):
        for i, msg in enumerate(FrameSource(rng, DspCodec(), dsp_frames(rng))):
            before = client.stats.e2e.as_dict()
            client.process_frame(msg, t_ns=i)
            after = client.stats.e2e.as_dict()
            kind = oracle.expect(msg)
            assert after[kind] == before[kind] + 1, f"frame {i} {msg}: expected {kind}"
        stats = client.stats
    assert_counts_match(stats.e2e.as_dict(), oracle)
    assert stats.frames == N_FRAMES
    assert oracle.tally["accepted"] > 1000


@pytest.mark.parametrize("seed", [3, 4])
def test_dsp_receive_path_counts_every_frame(seed: int) -> None:
    rng = random.Random(seed)
    oracle = Oracle("DSP")
    dsp = DspCodec()
    for i, msg in enumerate(FrameSource(rng, ControllerCodec(), controller_frames(rng))):
        before = dsp.stats.as_dict()
        frame = dsp.decode_command(msg, t_ns=i)
        kind = oracle.expect(msg)
        assert dsp.stats.as_dict()[kind] == before[kind] + 1, f"frame {i} {msg}: expected {kind}"
        assert (frame is not None) == (kind == "accepted")
    assert_counts_match(dsp.stats.as_dict(), oracle)
    assert oracle.tally["decode_error"] > 0


def test_fuzz_through_a_bus_into_the_running_client() -> None:
    """The same mix through a real (virtual) bus, read by the client's ``drain``."""
    rng = random.Random(5)
    oracle = Oracle("Controller")
    frames = list(FrameSource(rng, DspCodec(), dsp_frames(rng)))[:2000]
    spec = isolated_spec("virtual")
    with open_bus(spec) as tx, JointClient.open(spec, reinit_after_s=None) as client:
        for msg in frames:
            oracle.expect(msg)
            tx.send(msg)
        read_until(client, lambda: client.stats.frames >= len(frames), 30.0)
        stats = client.stats
    assert stats.frames == len(frames)
    for kind, expected in oracle.tally.items():
        assert stats.e2e.as_dict()[kind] == expected, kind
    assert stats.transport_errors == 0
