"""What does ``/hal/canopen`` cost the recorder process? One JSON line.

The file's writer (:class:`~rt_controller.runtime.recorder.CycleRecorder`, in a run the
recorder's process) decodes each CAN frame record of a ``cia402`` log and writes it again on
``/hal/canopen``. This feeds it ``--periods`` periods of the profile's bus (2 RPDOs, a SYNC and
4 TPDOs each), already encoded as the stream's records, as the recorder process does, once
with the ``dsp`` profile (raw frames only) and once with ``cia402`` (raw and decoded), for
``--rounds`` rounds, and reports the microseconds per frame (each round and the median) and
their difference, the decoding's cost per frame. The control process pays none of it.

Usage::

    python scripts/bench_canopen_decode.py [--periods 3000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import struct
import tempfile
import time
from pathlib import Path

import can

from hal.config import RigConfig
from rt_controller.runtime.recorder import CAN_RX, CAN_TX, CycleRecorder, encode_record

PERIOD = (
    (CAN_TX, 0x201, struct.pack("<Hh", 0x0F, -300)),
    (CAN_TX, 0x202, struct.pack("<Hh", 0x0F, 120)),
    (CAN_TX, 0x080, b""),
    (CAN_RX, 0x181, struct.pack("<Hi", 0x0637, 123456)),
    (CAN_RX, 0x281, struct.pack("<ih", -7000, -300)),
    (CAN_RX, 0x182, struct.pack("<Hi", 0x0637, -5000)),
    (CAN_RX, 0x282, struct.pack("<ih", 300, 120)),
)
"""One period of the cia402 bus (COB-ID, payload as the profile's PDO maps lay it out)."""


def stream_records(periods: int) -> list[tuple[int, int, bytes]]:
    """``(kind, t_ns, message bytes)`` of ``periods`` periods, 20 ms apart."""
    out = []
    for i in range(periods):
        for j, (kind, cob_id, data) in enumerate(PERIOD):
            t_ns = 1_000_000_000 + i * 20_000_000 + j * 1_000
            msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
            out.append((kind, t_ns, encode_record(kind, t_ns, msg)))
    return out


def us_per_frame(profile: str, records: list[tuple[int, int, bytes]], folder: Path) -> float:
    cfg = RigConfig().with_overrides({"hardware.profile": profile})
    with CycleRecorder(folder / f"{profile}.mcap", cfg) as rec:
        start = time.perf_counter_ns()
        for kind, t_ns, data in records:
            rec.add(kind, t_ns, data)
        elapsed = time.perf_counter_ns() - start
    return elapsed / len(records) / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--periods", type=int, default=3000, help="bus periods per round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds per profile")
    args = parser.parse_args()
    records = stream_records(args.periods)
    rounds: dict[str, list[float]] = {"dsp": [], "cia402": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.rounds):
            for profile, times in rounds.items():
                times.append(us_per_frame(profile, records, Path(tmp)))
    median = {profile: statistics.median(times) for profile, times in rounds.items()}
    out = {
        profile: {"us_per_frame": [round(t, 2) for t in times], "median": round(median[profile], 2)}
        for profile, times in rounds.items()
    }
    decode = round(median["cia402"] - median["dsp"], 2)
    print(json.dumps({"frames_per_round": len(records), **out, "decode_us_per_frame": decode}))


if __name__ == "__main__":
    main()
