"""The frame grabber: each frame through the pipeline into one features message.

A frame gives ``FeatureMsg(frame=seq, stamp_ns=capture stamp, sim_time_ns, pose_seq=period,
f, valid, lockstep)``: in lockstep the camera sends exactly one frame per control period, so
every period is answered; a frame without a measurement is answered with ``valid = 0`` (its
reason counted), and the controller's hold logic applies. A lockstep frame sent again (the
DSP re-announced the period) is answered again with the same message, without a second
detection.

Region of interest: once a frame's features have left, the grabber asks the camera for the region
of its next frame that the pipeline will read (:meth:`vision.pipeline.Pipeline.roi`; the whole
frame when it has no tracking window: at the start, after a frame without the target), on the
source's ``request_roi`` (a source that cannot read out a region ignores it). A region that does
not hold the target is not answered: the grabber asks for the same frame whole and measures
that, so the features are those of whole frames, whatever the camera sent. In lockstep the
request is a function of the frames before it, the same on every run.

Image log: a frame whose image the log will get (:meth:`vision.image_log.ImageLog.claim`) says
so in its features (``image``), so the controller counts an image that never reaches the log
exactly; the frame goes to the log's queue after its features left.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from hal.camera_frame import CameraFrame, RoiRequest
from hal.dropout import Dropout, in_dropout
from hal.durations import Durations
from hal.fifo import fifo_thread
from hal.vision_codec import FeatureMsg
from vision.image_log import ImageLog
from vision.pipeline import Measurement, Pipeline

Publish = Callable[[FeatureMsg], None]
RequestRoi = Callable[[RoiRequest], None]


Observer = Callable[[CameraFrame, Measurement, FeatureMsg], None]


@dataclass
class GrabberStats:
    """What the grabber did (``hil vision --json``)."""

    source: str = ""
    frames: int = 0
    """Frames processed (re-sent lockstep frames not included)."""
    published: int = 0
    valid: int = 0
    invalid: int = 0
    reanswers: int = 0
    """Lockstep frames sent again, answered again unchanged."""
    roi_frames: int = 0
    """Frames that came as a region of interest and were measured in it."""
    roi_misses: int = 0
    """Regions of interest without the target whole in their window: the frame asked again
    whole."""
    roi_request_errors: int = 0
    publish_errors: int = 0
    callback_errors: int = 0
    """Frames lost to an exception in the source's zenoh callback (the session's
    ``callback_errors``: a bug if not zero)."""
    dropouts: list[str] = field(default_factory=list)
    """Fault injection: the windows ``START:DURATION`` (s of simulation time) without features."""
    dropout_answers: int = 0
    """Lockstep frames in a dropout, answered with valid = 0 (also counted in ``invalid``)."""
    dropout_frames: int = 0
    """Realtime frames in a dropout, not answered."""
    pipeline: dict[str, Any] = field(default_factory=dict)
    """Frames, measurements and rejections by reason."""
    wrong_size_px: list[int] | None = None
    """[width, height] of the first frame of another size than the camera's (``wrong_size``:
    a real camera or clip of another resolution than ``[camera]``'s); None: there was none."""
    frame_rx: dict[str, int] = field(default_factory=dict)
    """The frame decoder's counters (emulated source)."""
    scheduling: str = ""
    """How realtime frames were measured: ``SCHED_FIFO`` (``vision.rt_priority``), the reason it
    was refused, or empty (normal scheduling, or no realtime frame)."""
    image_log: dict[str, int] = field(default_factory=dict)
    """The decimated image stream's counters (:meth:`vision.image_log.ImageLog.as_dict`)."""
    detect_us_p50: float | None = None
    """Timings in us; None (null in JSON) where no frame gave one."""
    detect_us_p99: float | None = None
    latency_us_p50: float | None = None
    """Capture stamp to publish (emulated source and real cameras: same clock)."""
    latency_us_p99: float | None = None
    pipeline_us_p50: float | None = None
    """Emulated source: a frame's payload received to its features published (decode, MAC,
    detect, undistort, publish)."""
    pipeline_us_p99: float | None = None
    arrival_us_p50: float | None = None
    """Emulated source, lockstep: the camera pose offered to the frame's arrival (the camera's
    render and encode, zenoh)."""
    arrival_us_p99: float | None = None

    def as_dict(self) -> dict[str, Any]:
        """Every field by name, in order (``hil vision --json``)."""
        return dataclasses.asdict(self)


class Grabber:
    """Pipeline and publisher; :meth:`on_frame` is safe to call from any one thread at a time
    (a lock serialises zenoh's callback threads)."""

    def __init__(
        self,
        pipeline: Pipeline,
        publish: Publish,
        *,
        source_id: int,
        observer: Observer | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        dropouts: Sequence[Dropout] = (),
        rt_priority: int = 0,
        request_roi: RequestRoi | None = None,
        image_log: ImageLog | None = None,
    ) -> None:
        self.pipeline = pipeline
        self.image_log = image_log
        """Where the frames whose image is logged go (None: no image log)."""
        self.request_roi = request_roi
        """Where the region of interest of the next frame is asked for (None: nowhere)."""
        self.rt_priority = rt_priority
        """Realtime frames are measured on SCHED_FIFO threads of this priority (0: normal)."""
        self._fifo_threads: set[int] = set()
        self.publish = publish
        self.source_id = source_id
        self.observer = observer
        self.clock = clock
        self.dropouts = tuple(dropouts)
        self.stats = GrabberStats(dropouts=[str(d) for d in self.dropouts])
        self._lock = threading.Lock()
        self._last: tuple[tuple[int, int, int], FeatureMsg] | None = None
        self._detect_ns = Durations()
        self._latency_ns = Durations()
        self._closed = False

    def on_reject(self, reason: str) -> None:
        """A payload that was no frame (nothing to answer: it names no period)."""
        with self._lock:
            self.pipeline.reject(reason)

    def close(self) -> None:
        """Publish nothing more: waits for a frame in progress (a zenoh callback may still run
        after its subscriber was undeclared), so the publisher can be undeclared after this."""
        with self._lock:
            self._closed = True

    def on_frame(self, frame: CameraFrame) -> FeatureMsg | None:
        """Measure ``frame`` and publish its features message (returned; None once closed)."""
        with self._lock:
            if self._closed:
                return None
            ident = (frame.source, frame.seq, frame.period)
            if frame.lockstep and self._last is not None and self._last[0] == ident:
                msg = self._last[1]
                self.stats.reanswers += 1
                self._send(msg)
                return msg
            if self.rt_priority and not frame.lockstep:
                self._realtime_thread()
            delivered_ns = frame.sim_time_ns + frame.exposure_ns // 2  # the exposure's end
            if in_dropout(self.dropouts, delivered_ns):
                return self._dropout(frame, ident)
            if frame.is_roi:
                region = self.pipeline.process_region(frame.pixels, frame.x0, frame.y0)
                if region is None:  # only the whole frame can tell: ask for it again whole
                    self.stats.roi_misses += 1
                    self._ask(RoiRequest(frame.source, frame.seq, None))
                    return None
                self.stats.roi_frames += 1
                m = region
            else:
                m = self.pipeline.process(frame.pixels)
            f = m.f if m.f is not None else (0.0, 0.0)
            log = self.image_log
            image = log is not None and log.claim(frame)
            msg = FeatureMsg(
                frame.seq,
                frame.stamp_ns,
                frame.sim_time_ns,
                frame.period,
                f,
                m.valid,
                frame.lockstep,
                self.source_id,
                image,
            )
            self.stats.frames += 1
            if m.valid:
                self.stats.valid += 1
            else:
                self.stats.invalid += 1
            self._last = (ident, msg)
            self._send(msg)
            self._ask(RoiRequest(frame.source, frame.seq + 1, self.pipeline.roi()))
            if m.detect_ns:  # 0: no detection ran (a frame of another size, malformed)
                self._detect_ns.add(m.detect_ns)
            if not frame.lockstep:
                self._latency_ns.add(self.clock() - frame.stamp_ns)
            if log is not None and image:
                log.put(frame, m)
            if self.observer is not None:
                self.observer(frame, m, msg)
            return msg

    def _realtime_thread(self) -> None:
        """SCHED_FIFO for the thread that measures realtime frames, asked once per thread (the
        source's: zenoh's callback thread, the capture loop); a refusal is kept in
        ``scheduling``."""
        thread = threading.get_ident()
        if thread not in self._fifo_threads:
            self._fifo_threads.add(thread)
            self.stats.scheduling = fifo_thread(self.rt_priority) or "SCHED_FIFO"

    def _dropout(self, frame: CameraFrame, ident: tuple[int, int, int]) -> FeatureMsg | None:
        """A frame inside a dropout window: lockstep answers it with valid = 0 (one answer per
        period), realtime publishes nothing, so the controller's features go stale."""
        if not frame.lockstep:
            self.stats.dropout_frames += 1
            return None
        msg = FeatureMsg(
            frame.seq,
            frame.stamp_ns,
            frame.sim_time_ns,
            frame.period,
            (0.0, 0.0),
            False,
            True,
            self.source_id,
        )
        self.stats.dropout_answers += 1
        self.stats.invalid += 1
        self._last = (ident, msg)
        self._send(msg)
        self._ask(RoiRequest(frame.source, frame.seq + 1, self.pipeline.roi()))
        return msg

    def _ask(self, req: RoiRequest) -> None:
        """Ask the source for a region of interest (right after the features leave, off their
        path: in lockstep the next period's pose follows the features' hop to the controller,
        its tick and the torque over CAN); a failed request is counted (the camera then sends
        the whole frame)."""
        if self.request_roi is None:
            return
        try:
            self.request_roi(req)
        except Exception:
            self.stats.roi_request_errors += 1

    def _send(self, msg: FeatureMsg) -> None:
        try:
            self.publish(msg)
            self.stats.published += 1
        except Exception:  # a failed put is counted; the next frame may pass
            self.stats.publish_errors += 1

    def snapshot(self) -> GrabberStats:
        """A copy of the counters with the timing percentiles filled in."""
        with self._lock:
            s = dataclasses.replace(self.stats)
            s.pipeline = self.pipeline.counts.as_dict()
            if self.pipeline.wrong_size is not None:
                s.wrong_size_px = list(self.pipeline.wrong_size)
            if self._detect_ns:
                s.detect_us_p50, s.detect_us_p99 = self._detect_ns.percentiles_us()
            if self._latency_ns:
                s.latency_us_p50, s.latency_us_p99 = self._latency_ns.percentiles_us()
            return s
