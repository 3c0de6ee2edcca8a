"""A CAN backend whose receive stamps are not on the wall clock (PCAN without the ``uptime``
package stamps from boot) must not make the rig reject the DSP's frames: a stamp an hour or
more away from the wall clock is taken as no stamp (the frame is judged on arrival) and
counted, so freshness and the state's age stay right."""

from __future__ import annotations

import math
import time
from collections import deque

import can

from hal.can_codec import DspCodec
from hal.joint_client import JointClient

KEY = bytes(range(32))


class StampedBus(can.BusABC):
    """Hands out the frames given to it, each with the receive stamp given."""

    def __init__(self, frames: list[can.Message]) -> None:
        super().__init__(channel="stamped")
        self.frames = deque(frames)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        pass

    def _recv_internal(self, timeout: float | None):
        return (self.frames.popleft(), False) if self.frames else (None, False)


def _state_frames(stamp: float, key: bytes = KEY) -> list[can.Message]:
    frames = list(DspCodec(key=key).encode_state((0.1, 0.2), (0.0, 0.0), sample=1))
    for msg in frames:
        msg.timestamp = stamp
    return frames


def test_boot_relative_stamps_are_taken_as_none_and_counted() -> None:
    bus = StampedBus(_state_frames(5_000.0))  # stamped 5000 s since boot
    client = JointClient(bus, key=KEY, owns_bus=True)
    client.drain(timestamps=True)
    assert client.states_received == 1
    assert client.stats.foreign_stamps == 2
    age = client.state_age_s()
    assert age is not None and 0.0 <= age < 3600.0
    client.close()


def test_wall_clock_stamps_are_kept() -> None:
    stamp = time.time() - 0.25  # arrived a quarter of a second ago
    client = JointClient(StampedBus(_state_frames(stamp)), key=KEY, owns_bus=True)
    client.drain(timestamps=True)
    assert client.states_received == 1 and client.stats.foreign_stamps == 0
    state = client.latest_state(max_age_s=math.inf)
    assert state.t_ns <= time.monotonic_ns() - 200_000_000  # the stamp, not the drain's time
    client.close()
