"""Does zenoh's shared memory pay for itself for camera frames? One JSON line per transport.

Publishes ``--frames`` payloads of one camera frame's size (640x480 mono8 with the
``hal.camera_frame`` header and MAC) from a hub session to a client session on loopback, the
rig's topology, once as bytes and once through a ``zenoh.shm.ShmProvider`` buffer, and reports
the put-to-callback latency (median, p99) and the publisher's CPU time per put. The SHM path
includes the copy of the frame into the SHM buffer (zenoh-python's ``ZShmMut`` exposes no
buffer protocol, so numpy cannot render into it). Usage::

    python scripts/bench_frame_shm.py [--frames 300] [--width 640 --height 480]
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import numpy as np
import zenoh
import zenoh.shm as shm

from hal.camera_frame import frame_size
from hal.zenoh_session import free_loopback_port, loopback_config_dict

KEY = "bench/camera/frame"


def _config(endpoint: str, listen: bool, use_shm: bool) -> zenoh.Config:
    doc = loopback_config_dict(endpoint, listen=listen)
    doc["transport"] = {"shared_memory": {"enabled": use_shm}}
    return zenoh.Config.from_json5(json.dumps(doc))


def run(use_shm: bool, frames: int, size: int) -> dict[str, object]:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    hub = zenoh.open(_config(endpoint, True, use_shm))
    client = zenoh.open(_config(endpoint, False, use_shm))
    arrived: list[int] = []
    via_shm: list[bool] = []
    cond = threading.Condition()

    def on_sample(sample: zenoh.Sample) -> None:
        now = time.perf_counter_ns()
        payload = sample.payload
        with cond:
            via_shm.append(payload.as_shm() is not None)
            payload.to_bytes()  # what the frame grabber does (its MAC reads bytes)
            arrived.append(now)
            cond.notify_all()

    sub = client.declare_subscriber(KEY, on_sample)
    pub = hub.declare_publisher(KEY, express=True, congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(0.5)
    frame = np.random.default_rng(0).integers(0, 256, size, dtype=np.uint8).tobytes()
    provider = shm.ShmProvider.default_backend(size * 8) if use_shm else None
    latency, cpu = [], []
    lost = 0
    for i in range(frames):
        t0, c0 = time.perf_counter_ns(), time.thread_time_ns()
        if provider is not None:
            buf = provider.alloc(size, policy=shm.BlockOn(shm.GarbageCollect()))
            buf[:] = frame
            pub.put(buf)
        else:
            pub.put(frame)
        cpu.append(time.thread_time_ns() - c0)
        with cond:
            want = i - lost
            if not cond.wait_for(lambda want=want: len(arrived) > want, 5.0):
                lost += 1
                continue
            latency.append(arrived[-1] - t0)
        time.sleep(0.005)
    sub.undeclare()
    pub.undeclare()
    client.close()
    hub.close()
    lat = np.array(latency[20:]) / 1e3
    put = np.array(cpu[20:]) / 1e3
    return {
        "transport": "shm" if use_shm else "bytes",
        "frame_bytes": size,
        "frames": frames,
        "lost": lost,
        "received_via_shm": bool(via_shm) and all(via_shm),
        "latency_us_median": float(np.median(lat)),
        "latency_us_p99": float(np.percentile(lat, 99)),
        "put_cpu_us_median": float(np.median(put)),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    args = p.parse_args()
    size = frame_size(args.width, args.height)
    for use_shm in (False, True):
        print(json.dumps(run(use_shm, args.frames, size)), flush=True)


if __name__ == "__main__":
    main()
