"""The decimated image stream: every ``1 / image_log_fps`` of capture time, a frame as PNG with
what the detector made of it, on ``hil/vision/image`` (:mod:`hal.vision_image`) for the log
and live views. Slots are in the frames' simulation time, so a lockstep run logs the same
frames every time."""

from __future__ import annotations

from collections.abc import Callable

import cv2

from hal.camera_frame import CameraFrame
from hal.vision_codec import FeatureMsg
from hal.vision_image import VisionImage
from vision.pipeline import Measurement

PNG_LEVEL = [cv2.IMWRITE_PNG_COMPRESSION, 1]
"""zlib level 1: about 2 ms for 640x480, a third of level 3's time for 10 % more bytes."""


def png(pixels) -> bytes:
    ok, buf = cv2.imencode(".png", pixels, PNG_LEVEL)
    if not ok:  # pragma: no cover - OpenCV encodes any 8-bit grey image
        raise ValueError("cv2.imencode failed")
    return buf.tobytes()


class ImageLog:
    """A grabber observer that hands every ``1 / fps``-th frame to ``publish``."""

    def __init__(self, fps: float, publish: Callable[[VisionImage], None], source_id: int):
        self.period_ns = round(1e9 / fps) if fps > 0 else 0
        self.publish = publish
        self.source_id = source_id
        self.sent = self.errors = 0
        self._next_ns: int | None = None
        self._last_ns: int | None = None

    def __call__(self, frame: CameraFrame, m: Measurement, msg: FeatureMsg) -> None:
        if self.period_ns <= 0:
            return
        t = frame.sim_time_ns
        if self._last_ns is not None and t < self._last_ns:
            self._next_ns = None  # a new run (the emulator's time went back)
        self._last_ns = t
        if self._next_ns is not None and t < self._next_ns:
            return
        self._next_ns = (t // self.period_ns + 1) * self.period_ns
        det = m.detection
        try:
            self.publish(
                VisionImage(
                    frame.seq,
                    frame.stamp_ns,
                    t,
                    m.valid,
                    m.reason,
                    (det.u, det.v) if det is not None else (0.0, 0.0),
                    m.f if m.f is not None else (0.0, 0.0),
                    png(frame.pixels),
                    self.source_id,
                )
            )
            self.sent += 1
        except Exception:  # a view never stops the measurements: counted
            self.errors += 1
