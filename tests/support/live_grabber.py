"""The image pipeline as a live process over zenoh, for tests: ``run_live`` on a thread, a
client that sends lockstep camera frames (``hal.camera_frame``, as the emulated camera does)
and waits for each frame's features."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from hal.camera_frame import encode_frame
from hal.config import RigConfig
from hal.secoc import rig_key
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import KEY_CAMERA_FRAME, KEY_FEATURES, open_session
from vision.process import run_live

PERIOD_NS = 20_000_000


class GrabberClient:
    """Sends frame ``i`` as period ``i`` of a lockstep run and reads the answers."""

    def __init__(self, session: Any, cfg: RigConfig) -> None:
        self.decoder = FeatureDecoder(max_age_ns=None)
        session.subscribe(KEY_FEATURES, self.decoder.feed)
        self._pub = session.publisher(KEY_CAMERA_FRAME)
        self._key = rig_key(cfg)

    def send(self, i: int, pixels: np.ndarray) -> None:
        frame = encode_frame(
            pixels,
            seq=i,
            stamp_ns=i,
            sim_time_ns=i * PERIOD_NS,
            exposure_ns=4_000_000,
            period=i,
            lockstep=True,
            key=self._key,
        )
        self._pub.put(frame)

    def answer(self, i: int, timeout_s: float = 10.0) -> Any:
        """The features message answering frame ``i``, or None after ``timeout_s``."""
        return self.decoder.wait_pose_seq(i, timeout_s)

    def first(self, pixels: np.ndarray) -> Any:
        """Frame 0, re-sent until answered: the subscription may take a moment."""
        for _ in range(100):
            self.send(0, pixels)
            msg = self.answer(0, 0.2)
            if msg is not None:
                return msg
        raise AssertionError("the grabber never answered frame 0")


@contextmanager
def live_grabber(cfg: RigConfig, endpoint: str, out: dict[str, Any]) -> Iterator[GrabberClient]:
    """``run_live(cfg, "emulated")`` listening on ``endpoint`` while the block runs; its stats
    land in ``out["stats"]`` when the block ends."""
    stop, ready = threading.Event(), threading.Event()

    def serve() -> None:
        out["stats"] = run_live(
            cfg, "emulated", stop_event=stop, endpoint=endpoint, listen=True, ready=ready
        )

    th = threading.Thread(target=serve)
    th.start()
    try:
        assert ready.wait(20), "the grabber did not start"
        with open_session(listen=False, endpoint=endpoint) as s:
            yield GrabberClient(s, cfg)
    finally:
        stop.set()
        th.join(20)
