"""The image pipeline as a process over zenoh: camera frames in (hal.camera_frame, as the
emulated camera sends them), one features message per lockstep frame out, measured f."""

from __future__ import annotations

import numpy as np

from hal.config import RigConfig
from tests.support.live_grabber import live_grabber
from tests.support.synthetic_frames import frame
from vision.intrinsics import intrinsics_from_config


def test_lockstep_frames_over_zenoh_are_answered_once_each(endpoint):
    cfg = RigConfig()
    k = intrinsics_from_config(cfg)
    path = [(-120.0 + 3 * i, -160.0 + 4 * i) for i in range(30)]
    out: dict = {}
    got = {}
    with live_grabber(cfg, endpoint, out) as grabber:
        grabber.first(frame(k, path[0], radius_px=20.0))
        for i in range(1, len(path)):
            pixels = frame(k, path[i], radius_px=20.0)
            if i == 10:
                pixels = np.full_like(pixels, 200)  # the target is gone: answered invalid
            grabber.send(i, pixels)
            msg = grabber.answer(i)
            assert msg is not None and msg.pose_seq == i
            got[i] = msg
    assert not got[10].valid
    err = [np.subtract(got[i].f, path[i]) for i in got if i != 10]
    assert np.abs(err).max() < 0.05  # the synthetic frames go through the default true lens
    stats = out["stats"]
    assert stats.pipeline["rejected"]["not_found"] == 1
    assert stats.frames == len(path) and stats.invalid == 1
