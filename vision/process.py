"""``hil vision`` on frames: a frame source, the pipeline and the features publisher.

Live sources (the emulated camera, a real one) publish ``hil/vision/features`` on zenoh, as
the analytic vision process does, with a random source id; a recorded log (``log:``) is re-run
offline: nothing is published, every frame's measurement is handed to ``on_result``.
"""

from __future__ import annotations

import secrets
import threading
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from hal.camera_frame import CameraFrame
from hal.config import RigConfig
from hal.dropout import Dropout
from hal.secoc import rig_key
from hal.vision_codec import FeatureMsg, encode_features
from hal.vision_image import encode_vision_image
from hal.zenoh_session import DEFAULT_WAIT_S, KEY_FEATURES, KEY_VISION_IMAGE, open_session
from vision.grabber import Grabber, GrabberStats
from vision.image_log import ImageLog
from vision.intrinsics import intrinsics_from_config
from vision.pipeline import Measurement, Pipeline
from vision.sources import EmulatedSource, open_source, parse_source


def run_offline(
    cfg: RigConfig,
    spec: str,
    on_result: Callable[[CameraFrame, Measurement, FeatureMsg], None] | None = None,
    stop_event: threading.Event | None = None,
    notice: Callable[[str], None] | None = None,
) -> GrabberStats:
    """Run the pipeline over every frame of a log or file, publishing nothing (``notice``:
    told once, at the first frame of another size than the camera's, and at a log's cut end)."""
    grabber = Grabber(
        Pipeline(intrinsics_from_config(cfg), notice=notice),
        lambda msg: None,
        source_id=0,
        observer=on_result,
    )
    source = open_source(spec, notice=notice)
    source.run(grabber.on_frame, grabber.on_reject, stop_event or threading.Event())
    stats = grabber.snapshot()
    stats.source = source.name
    return stats


def run_live(
    cfg: RigConfig,
    spec: str,
    *,
    stop_event: threading.Event,
    duration_s: float = 0.0,
    endpoint: str | None = None,
    config_file: str | None = None,
    listen: bool | None = False,
    wait_s: float = DEFAULT_WAIT_S,
    ready: threading.Event | None = None,
    dropouts: Sequence[Dropout] = (),
    rt_priority: int = 0,
    notice: Callable[[str], None] | None = None,
) -> GrabberStats:
    """Serve ``spec``'s frames as features on zenoh until ``stop_event``, ``duration_s`` (0 =
    forever) or the end of a file; ``dropouts``: windows without features (fault injection);
    ``rt_priority``: realtime frames are measured on SCHED_FIFO threads (``hil vision`` passes
    ``vision.rt_priority``; 0: normal scheduling); ``notice``: told once, at the first frame of
    another size than the camera's."""
    parse_source(spec)  # a bad spec fails before zenoh is opened
    key = rig_key(cfg)
    session = open_session(
        cfg,
        listen=listen,
        endpoint=endpoint,
        config_file=config_file,
        wait_s=wait_s,
        stop_event=stop_event,
    )
    timer: threading.Timer | None = None
    try:
        pub = session.publisher(KEY_FEATURES)
        source_id = secrets.randbits(32)
        image_pubs: dict[bool, Any] = {}
        image_log = None
        if cfg.camera.image_log_fps > 0:
            image_pubs = {  # lockstep: never lost; realtime: never delays the features
                lockstep: session.publisher(
                    KEY_VISION_IMAGE, block=lockstep, priority=zenoh.Priority.DATA_LOW
                )
                for lockstep in (True, False)
            }
            image_log = ImageLog(
                cfg.camera.image_log_fps,
                lambda img, lockstep: image_pubs[lockstep].put(encode_vision_image(img, key)),
                source_id,
            )
        source = open_source(spec, session=session, key=key, live=True)
        grabber = Grabber(
            Pipeline(intrinsics_from_config(cfg), notice=notice),
            lambda msg: pub.put(encode_features(msg, key)),
            source_id=source_id,
            dropouts=dropouts,
            rt_priority=rt_priority,
            request_roi=source.request_roi,
            image_log=image_log,
        )
        if duration_s > 0:
            timer = threading.Timer(duration_s, stop_event.set)
            timer.daemon = True
            timer.start()
        if ready is not None:
            ready.set()
        try:
            source.run(grabber.on_frame, grabber.on_reject, stop_event)
        finally:
            grabber.close()
            pub.undeclare()
            if image_log is not None:
                image_log.close()
            for image_pub in image_pubs.values():
                image_pub.undeclare()
        stats = grabber.snapshot()
        stats.callback_errors = session.callback_errors  # frames lost in zenoh's callbacks
        if image_log is not None:
            stats.image_log = image_log.as_dict()
        stats.source = source.name
        if isinstance(source, EmulatedSource):
            stats.frame_rx = source.decoder.as_dict()
            if source.pipeline_ns:
                stats.pipeline_us_p50, stats.pipeline_us_p99 = source.pipeline_ns.percentiles_us()
            if source.arrival_ns:
                stats.arrival_us_p50, stats.arrival_us_p99 = source.arrival_ns.percentiles_us()
        return stats
    finally:
        if timer is not None:
            timer.cancel()
        session.close()
