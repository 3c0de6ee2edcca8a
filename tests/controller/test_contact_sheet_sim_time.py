"""The contact sheet places each frame at the simulation time it shows: the sim time its
vision process sent with it on /vision/features (the same capture stamp), not the cycles' sim
time interpolated at its capture stamp, which put a lockstep frame of the world after the jump
(rendered before the controller's tick) on the "before" side, labelled a period early."""

from __future__ import annotations

import cv2
import numpy as np

from hal.config import RigConfig
from hal.vision_codec import FeatureMsg, encode_features
from hal.vision_image import VisionImage, encode_vision_image
from rt_controller.logtools.contact_sheet import frames_around
from rt_controller.logtools.reader import read_log
from rt_controller.runtime.recorder import IMAGE, CycleRecorder

PERIOD_NS = 20_000_000
T0 = 10**9


def _log(tmp_path, *, features: bool):
    path = tmp_path / "run.mcap"
    rec = CycleRecorder(path, RigConfig())
    for k in range(200):  # 4 s at 50 Hz, the jump at 3 s
        t_tick = T0 + k * PERIOD_NS
        rec.record_cycle({"tick": k, "t_ns": t_tick, "sim_time_s": k * 0.02})
        if k % 5 == 4:
            # lockstep: the world is already at tick k + 1 when its frame is rendered, captured
            # half a period before the controller's tick k + 1
            stamp = t_tick + PERIOD_NS // 2
            sim_ns = (k + 1) * PERIOD_NS
            pixels = np.full((48, 64), 200, np.uint8)
            cv2.circle(pixels, (10 + k // 5, 24), 4, 40, -1)
            _, png = cv2.imencode(".png", pixels)
            image = VisionImage(k + 1, stamp, sim_ns, True, None, (10.0, 24.0), (1.0, 2.0),
                                png.tobytes())  # fmt: skip
            rec.write(IMAGE, 0, encode_vision_image(image))
            if features:
                msg = FeatureMsg(k + 1, stamp, sim_ns, k + 1, (1.0, 2.0), image=True)
                rec.record_vision(encode_features(msg), stamp)
    rec.close()
    return read_log(path)


def test_frames_are_placed_at_the_sim_time_they_show(tmp_path):
    frames = frames_around(_log(tmp_path, features=True), 3.0)
    times = [round(f["t_s"], 3) for f in frames]
    assert times == [2.6, 2.7, 2.8, 2.9, 3.0, 3.1, 3.2, 3.3]  # 3.0: the first of the jump


def test_without_features_the_cycles_place_them(tmp_path):
    frames = frames_around(_log(tmp_path, features=False), 3.0)
    assert len(frames) == 8
    assert all(abs(f["t_s"] - round(f["t_s"] * 100) / 100) <= 0.011 for f in frames)
