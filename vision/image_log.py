"""The decimated image stream: every ``1 / image_log_fps`` of capture time, a frame as PNG with
what the detector made of it, on ``hil/vision/image`` (:mod:`hal.vision_image`) for the log
and live views. Slots are in the frames' simulation time, so a lockstep run logs the same
frames every time. Only whole frames are logged: the emulated camera sends the first frame of
each slot whole (the others may be a region of interest, :mod:`hal.camera_frame`), by the same
rule on the same simulation times (:class:`hal.vision_image.ImageSlots`).

The PNG is made on a thread of its own, never on the grabber's: a frame's features leave
before its PNG is made, and the next frame does not wait for it. A realtime frame that finds
:data:`BACKLOG` frames still waiting is not logged (counted ``dropped``); a lockstep frame
waits for room, and its image is published with ``lockstep`` set (``hil vision`` then blocks
on a congested link instead of dropping it), so a lockstep run's log holds the same frames
every time.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable

import cv2
import numpy as np

from hal.camera_frame import CameraFrame
from hal.fifo import raise_nice, short_gil_switch
from hal.vision_image import ImageSlots, VisionImage
from vision.pipeline import Measurement

PNG_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION,
    1,
    cv2.IMWRITE_PNG_FILTER,
    cv2.IMWRITE_PNG_FILTER_NONE,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
]
"""No row filter, Huffman coding only: a noisy sensor frame has no repeats for LZ77 to find
and its filtered rows compress no better, so this is less than half the CPU of zlib's level 1
for a smaller file (docs/benchmarks.md, "Design choices, measured")."""
BACKLOG = 4
"""Frames waiting for their PNG at most (realtime; lockstep frames wait for room)."""
LOCKSTEP_NICE = 10
"""Lockstep: how much the PNG thread lowers its own priority (nice) once it has a lockstep
frame, so the period's chain of processes gets the cores first (see :meth:`ImageLog._run`)."""


def png(pixels: np.ndarray) -> bytes:
    """``pixels`` (8-bit grey) as PNG with :data:`PNG_PARAMS`."""
    ok, buf = cv2.imencode(".png", pixels, PNG_PARAMS)
    if not ok:  # pragma: no cover - OpenCV encodes any 8-bit grey image
        raise ValueError("cv2.imencode failed")
    return buf.tobytes()


class ImageLog:
    """Hands every ``1 / fps``-th frame the grabber claims (:meth:`claim`, :meth:`put`), as
    PNG, to ``publish(image, lockstep)`` from its own thread (started on the first frame;
    :meth:`close` logs what is queued and stops it)."""

    def __init__(
        self,
        fps: float,
        publish: Callable[[VisionImage, bool], None],
        source_id: int,
        *,
        backlog: int = BACKLOG,
    ):
        self.slots = ImageSlots(fps)
        self.period_ns = self.slots.period_ns
        self.publish = publish
        self.source_id = source_id
        self.sent = self.errors = self.dropped = self.regions = 0
        self._queue: queue.Queue[tuple[CameraFrame, Measurement] | None] = queue.Queue(backlog)
        self._thread: threading.Thread | None = None
        self._closed = False

    def claim(self, frame: CameraFrame) -> bool:
        """Whether ``frame``'s image will follow: a whole frame that opens its slot, with room
        for it (a realtime frame that finds :data:`BACKLOG` frames waiting is not logged,
        counted ``dropped``). The grabber asks before the frame's features leave, so they can
        say so (:attr:`hal.vision_codec.FeatureMsg.image`), and then hands a claimed frame to
        :meth:`put`."""
        if self.period_ns <= 0 or self._closed:
            return False
        if frame.is_roi:  # the log and the live views show whole frames only (the camera
            self.regions += 1  # sends the first frame of each slot whole)
            return False
        if not self.slots.take(frame.sim_time_ns):
            return False
        if not frame.lockstep and self._queue.full():
            self.dropped += 1
            return False
        return True

    def put(self, frame: CameraFrame, m: Measurement) -> None:
        """Queue a claimed frame for its PNG (a lockstep frame waits for room; a realtime one
        has the room its claim found: only the grabber's thread puts)."""
        if self._thread is None:
            short_gil_switch()  # the PNG thread's Python holds the GIL the grabber wants
            self._thread = threading.Thread(target=self._run, name="hil-image-log", daemon=True)
            self._thread.start()
        self._queue.put((frame, m))

    def as_dict(self) -> dict[str, int]:
        """Frames logged, not logged for a full backlog, failed to encode or publish, and
        regions of interest passed over (not whole frames)."""
        return {
            "sent": self.sent,
            "dropped": self.dropped,
            "errors": self.errors,
            "regions": self.regions,
        }

    def close(self, timeout_s: float = 5.0) -> None:
        """Log the frames still queued, then stop the thread. Idempotent."""
        self._closed = True
        if self._thread is None:
            return
        self._queue.put(None)
        self._thread.join(timeout_s)
        self._thread = None

    def _run(self) -> None:
        """Lockstep: once it has a lockstep frame, the thread runs at :data:`LOCKSTEP_NICE`. A
        period's chain (render, detect, tick, DSP) runs in four processes on a host that may
        have only two cores; the PNG (2 ms a frame) is off that chain, so it takes a smaller
        share of the cores, but a share: when it falls :data:`BACKLOG` frames behind the
        grabber waits for it, and on a host busy with other work an idle-class thread
        (SCHED_IDLE) got so little that periods outlasted the DSP's reply timeout and the run
        left its deterministic schedule. Realtime frames keep the default priority: there a
        starved thread would drop frames (``dropped``)."""
        niced = False
        while (item := self._queue.get()) is not None:
            if not niced and item[0].lockstep:
                niced = True
                raise_nice(threading.get_native_id(), LOCKSTEP_NICE)
            self._send(*item)

    def _send(self, frame: CameraFrame, m: Measurement) -> None:
        det = m.detection
        try:
            self.publish(
                VisionImage(
                    frame.seq,
                    frame.stamp_ns,
                    frame.sim_time_ns,
                    m.valid,
                    m.reason,
                    (det.u, det.v) if det is not None else (0.0, 0.0),
                    m.f if m.f is not None else (0.0, 0.0),
                    png(frame.pixels),
                    self.source_id,
                ),
                frame.lockstep,
            )
            self.sent += 1
        except Exception:  # a view never stops the measurements: counted
            self.errors += 1
