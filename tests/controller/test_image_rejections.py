"""A camera image that the controller refuses for the log (not authentic, malformed) is counted
in the run's diagnostics and said in its summary: a warning for a few, a reason the run is not
clean for a stream of them (as for the features themselves)."""

from __future__ import annotations

import threading
from typing import Any

from hal.config import RigConfig
from hal.secoc import rig_key
from hal.vision_image import VisionImage, encode_vision_image
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import KEY_VISION_IMAGE
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


def test_refused_images_are_counted_and_said_in_the_summary() -> None:
    cfg = RigConfig()
    assert cfg.camera.image_log_fps > 0  # the default logs images
    key = rig_key(cfg)
    rec, session = ImageRecorder(), Session()
    ctx = RunContext(cfg, FakeClock(10**9), threading.Event(), RunCounters(), rec)
    decoder = FeatureDecoder.from_config(cfg.controller, key=key)
    link = FeatureLink(ctx, session, decoder, by_callback=True, record_raw=False)
    link.attach()
    on_image = session.callbacks[KEY_VISION_IMAGE]

    on_image(_image(key))
    on_image(_image(b"k" * len(key)))  # another rig's key: bad MAC
    on_image(b"HV garbage")
    assert len(rec.images) == 1
    counts = link.counts()
    assert counts["images_rejected"] == 2 and counts["accepted"] == 0

    summary = {"rejections": {"features": counts}}
    assert run_problems(summary) == []
    assert "2 camera image(s) refused for the log (not authentic or malformed)" in run_warnings(
        summary
    )
    for _ in range(AUTH_FAULT_MIN - 2):
        on_image(b"HV garbage")
    summary = {"rejections": {"features": link.counts()}}
    assert run_problems(summary) == [
        f"{AUTH_FAULT_MIN} camera image(s) refused for the log (not authentic or malformed)"
    ]
    assert not any("camera image" in w for w in run_warnings(summary))
    link.detach()
