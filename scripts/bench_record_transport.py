"""Which transport should carry the run's records to the recorder? One JSON line per transport.

Sends ``--ticks`` ticks of the rig's records (per tick: a ``/controller/cycle`` dict, three CAN
frames received and one sent, a vision payload; every fifth tick a 166 kB camera image, the
soak's mix) from this process to a reader process, and reports the sender's CPU time per tick
(median, p99; what the control thread pays after the write; ``encode only`` is the JSON
encoding both pay), the wall time of the whole send and
how many records arrived:

- ``zenoh``: each record encoded, then one ``put`` per record on its topic's key (reliable,
  ``BLOCK`` as lockstep needs), to a subscriber session in the reader over loopback TCP;
- ``pipe``: each record encoded into an MCAP message record (mcap's own ``Writer`` without
  chunks, so the wire format is MCAP) and one ``write`` per tick to the reader's pipe, which
  reads it with mcap's ``StreamReader``.

Usage::

    python scripts/bench_record_transport.py [--ticks 1000]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import time

import numpy as np

from rt_controller.runtime.recorder import encode_json

KEYS = ["cycle", "can_rx", "can_tx", "vision", "image"]
READER = r"""
import sys, time, json
mode, arg = sys.argv[1], sys.argv[2]
n = 0
if mode == "zenoh":
    import zenoh, threading
    from hal.zenoh_session import loopback_config_dict
    s = zenoh.open(zenoh.Config.from_json5(json.dumps(loopback_config_dict(arg, listen=False))))
    lock = threading.Lock()
    def cb(sample):
        global n
        sample.payload.to_bytes()
        with lock:
            n += 1
    sub = s.declare_subscriber("bench/rec/**", cb)
    print("ready", flush=True)
    sys.stdin.readline()  # the sender says how many it sent
    time.sleep(1.0)
    print(n, flush=True)
    import os
    os._exit(0)
else:
    from mcap.stream_reader import StreamReader
    from mcap.records import Message
    fd = int(arg)
    with open(fd, "rb", buffering=0) as f:
        print("ready", flush=True)
        for rec in StreamReader(f, skip_magic=False).records:
            if isinstance(rec, Message):
                n += 1
    print(n, flush=True)
"""


def tick_records(k: int, cycle: dict, image: bytes) -> list[tuple[str, object]]:
    out: list[tuple[str, object]] = [("cycle", {**cycle, "tick": k})]
    frame = {"t_ns": k, "arbitration_id": 0x101, "dlc": 8, "data": "00" * 16, "is_fd": False}
    out += [("can_rx", frame)] * 3 + [("can_tx", frame), ("vision", {"t_ns": k, "data": "x" * 80})]
    if k % 5 == 0:
        out.append(("image", image))
    return out


def encoded(obj: object) -> bytes:
    return obj if isinstance(obj, bytes) else encode_json(obj)


def run_zenoh(ticks: int, cycle: dict, image: bytes) -> dict:
    import zenoh

    from hal.zenoh_session import free_loopback_port, loopback_config_dict

    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    hub = zenoh.open(zenoh.Config.from_json5(json.dumps(loopback_config_dict(ep, listen=True))))
    reader = subprocess.Popen(
        [sys.executable, "-c", READER, "zenoh", ep], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )
    reader.stdout.readline()
    pubs = {
        k: hub.declare_publisher(
            f"bench/rec/{k}", express=True, congestion_control=zenoh.CongestionControl.BLOCK
        )
        for k in KEYS
    }
    time.sleep(1.0)
    cpu, sent, t0 = [], 0, time.perf_counter()
    for k in range(ticks):
        c0 = time.thread_time_ns()
        for key, obj in tick_records(k, cycle, image):
            pubs[key].put(encoded(obj))
            sent += 1
        cpu.append(time.thread_time_ns() - c0)
        time.sleep(0.002)
    wall = time.perf_counter() - t0
    reader.stdin.write(b"done\n")
    reader.stdin.flush()
    got = int(reader.stdout.readline())
    reader.wait()
    hub.close()
    return summary("zenoh", cpu, wall, sent, got)


def run_pipe(ticks: int, cycle: dict, image: bytes) -> dict:
    from mcap.writer import Writer

    r, w = os.pipe()
    reader = subprocess.Popen(
        [sys.executable, "-c", READER, "pipe", str(r)], stdout=subprocess.PIPE, pass_fds=(r,)
    )
    os.close(r)
    reader.stdout.readline()
    buf = io.BytesIO()
    writer = Writer(buf, use_chunking=False)
    writer.start()
    sid = writer.register_schema("s", "jsonschema", b"{}")
    chans = {k: writer.register_channel(f"/{k}", "json", sid) for k in KEYS}
    cpu, sent, t0 = [], 0, time.perf_counter()
    for k in range(ticks):
        c0 = time.thread_time_ns()
        for key, obj in tick_records(k, cycle, image):
            writer.add_message(chans[key], k, encoded(obj), k)
            sent += 1
        data = buf.getbuffer()
        view = memoryview(data)
        while view:
            view = view[os.write(w, view) :]
        del view, data
        buf.seek(0)
        buf.truncate()
        cpu.append(time.thread_time_ns() - c0)
        time.sleep(0.002)
    writer.finish()
    os.write(w, buf.getvalue())
    os.close(w)
    wall = time.perf_counter() - t0
    got = int(reader.stdout.readline())
    reader.wait()
    return summary("pipe", cpu, wall, sent, got)


def run_encode(ticks: int, cycle: dict, image: bytes) -> dict:
    """The encoding alone (both transports pay it): the baseline."""
    cpu, sent, t0 = [], 0, time.perf_counter()
    for k in range(ticks):
        c0 = time.thread_time_ns()
        for _key, obj in tick_records(k, cycle, image):
            encoded(obj)
            sent += 1
        cpu.append(time.thread_time_ns() - c0)
        time.sleep(0.002)
    return summary("encode only", cpu, time.perf_counter() - t0, sent, sent)


def summary(name: str, cpu: list[int], wall: float, sent: int, got: int) -> dict:
    us = np.array(cpu) / 1e3
    return {
        "transport": name,
        "ticks": len(cpu),
        "cpu_us_per_tick_median": round(float(np.median(us)), 1),
        "cpu_us_per_tick_p99": round(float(np.percentile(us, 99)), 1),
        "wall_s": round(wall, 3),
        "records_sent": sent,
        "records_arrived": got,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=1000)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, 166_000, dtype=np.uint8).tobytes()
    cycle = {f"field{i}": float(rng.standard_normal()) for i in range(40)}
    for run in (run_encode, run_zenoh, run_pipe):
        print(json.dumps(run(args.ticks, cycle, image)), flush=True)


if __name__ == "__main__":
    main()
