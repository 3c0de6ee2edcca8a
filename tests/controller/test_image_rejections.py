"""A camera image that the controller refuses for the log (not authentic, malformed) is counted
in the run's diagnostics and said in its summary: a warning for a few, a reason the run is not
clean for a stream of them (as for the features themselves)."""

from __future__ import annotations

import threading
import time
from typing import Any

from hal.config import RigConfig
from hal.secoc import rig_key
from hal.vision_image import VisionImage, encode_vision_image
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import KEY_FEATURES, KEY_VISION_IMAGE
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters, run_problems, run_warnings
from rt_controller.runtime.diagnostics import AUTH_FAULT_MIN
from rt_controller.runtime.feature_link import FeatureLink
from tests.support.fake_clock import FakeClock


class Session:
    """Keeps each subscription's callback by key, as zenoh would call it."""

    def __init__(self) -> None:
        self.callbacks: dict[str, Any] = {}

    def subscribe(self, key: str, on_payload: Any) -> Any:
        self.callbacks[key] = on_payload

        class Subscriber:
            def undeclare(self) -> None:
                pass

        return Subscriber()


class ImageRecorder:
    def __init__(self) -> None:
        self.images: list[bytes] = []

    def write(self, kind: int, t_ns: int, obj: Any, final: bool = False) -> bool:
        self.images.append(obj)
        return True


def _image(key: bytes) -> bytes:
    msg = VisionImage(5, 10**9, 2 * 10**9, True, None, (35.5, 15.5), (-3.0, 4.0), b"png")
    return encode_vision_image(msg, key=key)


def _frame_image(key: bytes, k: int) -> bytes:
    """The logged image of frame ``k`` (one every 20 ms of simulation time)."""
    msg = VisionImage(k, 10**9, k * 20_000_000, True, None, (1.0, 2.0), (3.0, 4.0), b"png")
    return encode_vision_image(msg, key=key)


def _features(key: bytes, k: int, image: bool | None = None) -> bytes:
    """The lockstep features of frame ``k`` (every 20 ms of simulation time); ``image``: they
    announce the frame's image (default: every fifth frame, as the 10 fps image log takes)."""
    from hal.vision_codec import FeatureMsg, encode_features

    image = k % 5 == 0 if image is None else image
    msg = FeatureMsg(k, 10**9, k * 20_000_000, k, (-120.0, -160.0), True, True, 7, image)
    return encode_features(msg, key=key)


def _lockstep_link(
    cfg: RigConfig,
) -> tuple[FeatureLink, FeatureDecoder, ImageRecorder, Session]:
    """A lockstep run's feature link, attached, on a session that keeps its callbacks."""
    rec, session = ImageRecorder(), Session()
    ctx = RunContext(cfg, FakeClock(10**9), threading.Event(), RunCounters(), rec)
    decoder = FeatureDecoder.from_config(cfg.controller, key=rig_key(cfg))
    link = FeatureLink(ctx, session, decoder, by_callback=True, record_raw=False)
    link.attach()
    return link, decoder, rec, session


def test_features_arriving_after_the_end_announce_no_image() -> None:
    """The loop has ended and the images it was owed are in: features that arrive now (the
    answer to the last pose) are not the run's and announce no image it must wait for."""
    cfg = RigConfig()
    key = rig_key(cfg)
    link, _, rec, session = _lockstep_link(cfg)
    on_features, on_image = session.callbacks[KEY_FEATURES], session.callbacks[KEY_VISION_IMAGE]
    on_features(_features(key, 0))
    on_image(_frame_image(key, 0))
    assert link.settle_images(0.01)
    on_features(_features(key, 5))  # between the wait for images and the detach
    link.detach()
    assert link.as_dict()["images_missing"] == 0 and len(rec.images) == 1


def test_refused_images_are_counted_and_said_in_the_summary() -> None:
    cfg = RigConfig()
    assert cfg.camera.image_log_fps > 0  # the default logs images
    key = rig_key(cfg)
    link, _, rec, session = _lockstep_link(cfg)
    on_image = session.callbacks[KEY_VISION_IMAGE]

    on_image(_image(key))
    on_image(_image(b"k" * len(key)))  # another rig's key: bad MAC
    on_image(b"HV garbage")
    assert len(rec.images) == 1
    counts = link.as_dict()
    assert counts["images_rejected"] == 2 and counts["accepted"] == 0

    summary = {"rejections": {"features": counts}}
    assert run_problems(summary) == []
    assert "2 camera image(s) refused for the log (not authentic or malformed)" in run_warnings(
        summary
    )
    for _ in range(AUTH_FAULT_MIN - 2):
        on_image(b"HV garbage")
    summary = {"rejections": {"features": link.as_dict()}}
    assert run_problems(summary) == [
        f"{AUTH_FAULT_MIN} camera image(s) refused for the log (not authentic or malformed)"
    ]
    assert not any("camera image" in w for w in run_warnings(summary))
    link.detach()


def test_a_lockstep_run_ends_after_the_images_of_its_last_frames() -> None:
    """The vision process sends a frame's image after its features: the end of a lockstep run
    waits for the images of the frames it received (10 fps of simulation time: the frames at
    0 and 0.1 s of these six), so the log holds them all."""
    cfg = RigConfig()
    assert cfg.camera.model == "image" and cfg.camera.image_log_fps == 10.0
    key = rig_key(cfg)
    link, decoder, rec, session = _lockstep_link(cfg)
    on_features, on_image = session.callbacks[KEY_FEATURES], session.callbacks[KEY_VISION_IMAGE]

    for k in range(6):  # frames every 20 ms of simulation time
        on_features(_features(key, k))
    assert decoder.latest is not None and decoder.latest.frame == 5
    on_image(_frame_image(key, 0))
    assert link.as_dict()["images_missing"] == 1  # the frame of 0.1 s
    assert not link.settle_images(0.01)
    late = threading.Timer(0.05, on_image, args=(_frame_image(key, 5),))
    late.start()
    assert link.settle_images(10.0)
    late.join()
    assert link.as_dict()["images_missing"] == 0 and len(rec.images) == 2
    link.detach()


class _Ring:
    """What ``subscribe_ring`` gives a realtime run: payloads the control thread drains."""

    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def drain(self) -> list[bytes]:
        out, self.payloads = self.payloads, []
        return out

    def close(self) -> None:
        pass


def test_a_realtime_run_counts_the_images_of_its_last_frames_that_did_not_come() -> None:
    """Realtime features are drained by the control thread, not fed by a callback; the images
    of the frames it received are still owed to the log, and the ones that never came are
    counted (``images_missing``) instead of lost unsaid."""
    cfg = RigConfig()
    key = rig_key(cfg)
    rec, ring = ImageRecorder(), _Ring()

    class RingSession(Session):
        def subscribe_ring(self, key: str) -> _Ring:
            return ring

    session = RingSession()
    clock = FakeClock(10**9)
    ctx = RunContext(cfg, clock, threading.Event(), RunCounters(), rec)
    decoder = FeatureDecoder.from_config(cfg.controller, key=key)
    link = FeatureLink(ctx, session, decoder, by_callback=False, record_raw=False)
    link.attach()
    on_image = session.callbacks[KEY_VISION_IMAGE]

    for k in range(6):  # frames every 20 ms of simulation time; logged: those of 0 and 0.1 s
        ring.payloads.append(_features(key, k))
    link.poll(clock.now_ns())
    assert decoder.latest is not None and decoder.latest.frame == 5
    on_image(_frame_image(key, 0))
    assert link.as_dict()["images_missing"] == 1  # the frame of 0.1 s
    assert not link.settle_images(0.01)
    on_image(_frame_image(key, 5))
    assert link.settle_images(0.01)
    assert link.as_dict()["images_missing"] == 0 and len(rec.images) == 2
    link.detach()


def test_the_end_of_a_run_waits_for_images_as_long_as_they_keep_coming() -> None:
    """A vision process far behind still sends the last frames' images one after another: the
    end of the run waits on while each comes within ``quiet_s`` of the one before, however long
    all of them take (here 1.2 s against a ``quiet_s`` of 1 s), and gives up once one does not
    come."""
    cfg = RigConfig()
    key = rig_key(cfg)
    link, _, rec, session = _lockstep_link(cfg)
    on_features, on_image = session.callbacks[KEY_FEATURES], session.callbacks[KEY_VISION_IMAGE]
    for k in range(65):  # logged: the frames of 0, 0.1, ... 1.2 s (every fifth)
        on_features(_features(key, k))
    assert link.as_dict()["images_missing"] == 13
    quiet_s, stop = 1.0, threading.Event()
    spans: list[tuple[float, float]] = []  # each image's (start, end) of delivery, monotonic

    def send() -> None:
        for k in range(0, 60, 5):  # one image every 0.1 s; the frame of 1.2 s never comes
            if stop.wait(0.1):
                return
            start = time.monotonic()
            on_image(_frame_image(key, k))
            spans.append((start, time.monotonic()))

    sender = threading.Thread(target=send)
    sender.start()
    try:
        began = time.monotonic()
        settled = link.settle_images(quiet_s)
        logged_by_then = len(rec.images)  # at least those it saw (logged before they are seen)
    except BaseException:
        stop.set()
        raise
    finally:
        sender.join()
    assert not settled  # the last image never comes
    assert len(spans) == len(rec.images) == 12 and link.as_dict()["images_missing"] == 1
    # How many it had to wait for follows from when they came, not from how fast the host was:
    # it waits quiet_s from (at the earliest) the start of the delivery of the last image it saw,
    # so every image whose delivery ended within quiet_s of the start of the one before (of the
    # call, for the first) was seen. Half of quiet_s is the margin for the clocks' grain.
    chain, before = 0, began
    for start, end in spans:
        if end - before >= quiet_s / 2:
            break
        chain, before = chain + 1, start
    assert logged_by_then >= chain, (chain, spans, began)  # all that came, not only the first
    link.detach()


def test_an_image_overtaken_by_a_newer_one_is_counted_at_once() -> None:
    """The vision process sends its images in order on one publisher: an announced image that a
    newer one overtook never comes (a realtime link dropped it). It is counted missing at once,
    and the end of the run does not wait for it."""
    cfg = RigConfig()
    key = rig_key(cfg)
    link, _, rec, session = _lockstep_link(cfg)
    on_features, on_image = session.callbacks[KEY_FEATURES], session.callbacks[KEY_VISION_IMAGE]
    for k in range(11):  # announced: the images of frames 0, 5 and 10
        on_features(_features(key, k))
    on_image(_frame_image(key, 0))
    on_image(_frame_image(key, 10))  # the image of frame 5 was dropped on the way
    assert link.as_dict()["images_missing"] == 1
    assert link.settle_images(0.01)  # nothing still to come
    assert len(rec.images) == 2
    link.detach()


def test_only_announced_images_are_expected() -> None:
    """Features that do not announce an image (a frame the vision process did not log: a region
    of interest, a dropout, a full backlog, or the first frame of a slot the controller received
    when the vision process logged an earlier one) leave nothing owed to the log."""
    cfg = RigConfig()
    key = rig_key(cfg)
    link, _, rec, session = _lockstep_link(cfg)
    on_features, on_image = session.callbacks[KEY_FEATURES], session.callbacks[KEY_VISION_IMAGE]
    for k in range(1, 5):  # the controller subscribed after frame 0, whose image was logged
        on_features(_features(key, k, image=False))
    on_features(_features(key, 5))
    assert link.as_dict()["images_missing"] == 1
    on_image(_frame_image(key, 5))
    assert link.as_dict()["images_missing"] == 0
    assert link.settle_images(0.01) and len(rec.images) == 1
    link.detach()


def test_an_image_missing_makes_a_lockstep_run_not_clean_and_a_realtime_one_warned() -> None:
    """Lockstep images wait on a congested link, so one missing means the log is incomplete;
    a realtime link drops an image rather than delay the features: a warning."""
    summary = {"rejections": {"features": {"images_missing": 2}}}
    said = "2 camera image(s) announced by their features are not in the log"
    assert run_problems({**summary, "clock": "lockstep"}) == [said]
    assert said not in run_warnings({**summary, "clock": "lockstep"})
    assert run_problems({**summary, "clock": "realtime"}) == []
    assert said in run_warnings({**summary, "clock": "realtime"})


def test_a_late_image_of_the_plan_run_before_stays_out_of_the_next_runs_log() -> None:
    """A plan's runs share the vision process: an image the run before gave up waiting for can
    come once the next run started. The next run's link is given what the run before was owed;
    such an image, its time not yet reached by the new run's features, is counted and kept out
    of the new run's log, and the new run's own images are neither overtaken by it nor
    refused."""
    cfg = RigConfig()
    key = rig_key(cfg)
    first, _, _, before = _lockstep_link(cfg)
    for k in range(11):  # announced: the images of frames 0, 5 and 10 (0, 0.1 and 0.2 s)
        before.callbacks[KEY_FEATURES](_features(key, k))
    for k in (0, 5):
        before.callbacks[KEY_VISION_IMAGE](_frame_image(key, k))
    assert not first.settle_images(0.01)  # the image of frame 10 is late
    first.detach()
    assert first.images_owed() == (200_000_000,)

    rec, session = ImageRecorder(), Session()
    ctx = RunContext(cfg, FakeClock(10**9), threading.Event(), RunCounters(), rec)
    decoder = FeatureDecoder.from_config(cfg.controller, key=key)
    link = FeatureLink(
        ctx, session, decoder, by_callback=True, record_raw=False, owed_before=first.images_owed()
    )
    link.attach()
    on_features, on_image = session.callbacks[KEY_FEATURES], session.callbacks[KEY_VISION_IMAGE]
    for k in range(6):  # the next run's frames 0-5 (its clock starts at 0 again)
        on_features(_features(key, k))
    on_image(_frame_image(key, 10))  # the run before's image of 0.2 s, late
    assert link.as_dict()["images_of_run_before"] == 1
    assert link.as_dict()["images_missing"] == 2  # this run's 0 and 0.1 s, still to come
    for k in (0, 5):
        on_image(_frame_image(key, k))
    assert link.as_dict()["images_missing"] == 0 and link.settle_images(0.01)
    for k in range(6, 11):  # this run reaches 0.2 s: its own image of 0.2 s is logged
        on_features(_features(key, k))
    on_image(_frame_image(key, 10))
    assert len(rec.images) == 3 and link.as_dict()["images_missing"] == 0
    assert link.as_dict()["images_of_run_before"] == 1
    link.detach()
