"""The image pipeline as a process over zenoh: camera frames in (hal.camera_frame, as the
emulated camera sends them), one features message per lockstep frame out, measured f."""

from __future__ import annotations

import threading

import numpy as np

from hal.camera_frame import encode_frame
from hal.config import RigConfig
from hal.secoc import rig_key
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import KEY_CAMERA_FRAME, KEY_FEATURES, open_session
from tests.support.synthetic_frames import frame
from vision.intrinsics import intrinsics_from_config
from vision.process import run_live

PERIOD_NS = 20_000_000


def test_lockstep_frames_over_zenoh_are_answered_once_each(endpoint):
    cfg = RigConfig()
    k = intrinsics_from_config(cfg)
    stop, ready, out = threading.Event(), threading.Event(), {}

    def serve() -> None:
        out["stats"] = run_live(
            cfg, "emulated", stop_event=stop, endpoint=endpoint, listen=True, ready=ready
        )

    th = threading.Thread(target=serve)
    th.start()
    try:
        assert ready.wait(20)
        with open_session(listen=False, endpoint=endpoint) as s:
            decoder = FeatureDecoder(max_age_ns=None)
            s.subscribe(KEY_FEATURES, decoder.feed)
            pub = s.publisher(KEY_CAMERA_FRAME)
            key = rig_key(cfg)
            path = [(-120.0 + 3 * i, -160.0 + 4 * i) for i in range(30)]

            def send(i: int, pixels: np.ndarray) -> None:
                pub.put(
                    encode_frame(
                        pixels,
                        seq=i,
                        stamp_ns=i,
                        sim_time_ns=i * PERIOD_NS,
                        exposure_ns=4_000_000,
                        period=i,
                        lockstep=True,
                        key=key,
                    )
                )

            # the subscription may take a moment: re-send frame 0 (a re-send is re-answered)
            for _ in range(100):
                send(0, frame(k, path[0], radius_px=20.0))
                if decoder.wait_pose_seq(0, 0.2) is not None:
                    break
            got = {}
            for i in range(1, len(path)):
                pixels = frame(k, path[i], radius_px=20.0)
                if i == 10:
                    pixels = np.full_like(pixels, 200)  # the target is gone: answered invalid
                send(i, pixels)
                msg = decoder.wait_pose_seq(i, 10.0)
                assert msg is not None and msg.pose_seq == i
                got[i] = msg
    finally:
        stop.set()
        th.join(20)
    assert not got[10].valid
    err = [np.subtract(got[i].f, path[i]) for i in got if i != 10]
    assert np.abs(err).max() < 0.05  # the synthetic frames go through the default true lens
    stats = out["stats"]
    assert stats.pipeline["rejected"]["not_found"] == 1
    assert stats.frames == len(path) and stats.invalid == 1
