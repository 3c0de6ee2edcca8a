"""Fuzzing the emulated DSP's receive path: random, corrupted and replayed frames, each given
the verdict an independent oracle (E2E order of checks, SecOC) expects; nothing gets through."""

from __future__ import annotations

import random
import threading
from collections import Counter
from collections.abc import Iterator

import can
import cantools
import numpy as np
import pytest

from hal.bus import isolated_spec, open_bus
from hal.can_codec import ControllerCodec, DspCommand
from hal.can_database import DBC_PATH
from hal.config import RigConfig
from hal.e2e import DEFAULT_MAX_DELTA, DEFAULT_REINIT_AFTER_NS
from plant_emulator.dsp_realtime import RealtimeDsp
from tests.support import SecocReference, command_is_malformed, e2e_crc_reference
from tests.support.dsp import (
    RECV_TIMEOUT_S,
    free_state_sync,
    wait_for,
)


@pytest.fixture
def cfg(cfg: RigConfig) -> RigConfig:
    """These tests read the joint state after every physics step (:func:`free_state_sync`)."""
    return free_state_sync(cfg)


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
        node = RealtimeDsp(cfg, bus)
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
        node = RealtimeDsp(cfg, bus)
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
