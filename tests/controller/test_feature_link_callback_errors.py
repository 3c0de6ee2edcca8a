"""An exception in one of the controller's feature-link callbacks (swallowed by the zenoh
session, counted in its ``callback_errors``) is in the run's feature counters and makes the run
not clean: a lost message or image is never silent."""

from __future__ import annotations

import threading
import time
from typing import Any

from hal.config import RigConfig
from hal.secoc import rig_key
from hal.vision_image import VisionImage, encode_vision_image
from hal.vision_receivers import FeatureDecoder
from hal.zenoh_session import KEY_VISION_IMAGE, open_session
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters, run_problems
from rt_controller.runtime.feature_link import FeatureLink
from tests.support.fake_clock import FakeClock


class FailingRecorder:
    """A log that fails on every write (a bug in the recorder's path)."""

    def write(self, kind: int, t_ns: int, obj: Any, final: bool = False) -> bool:
        raise RuntimeError("the recorder failed")


def _counts_when(link: FeatureLink, done: Any, timeout_s: float = 10.0) -> dict[str, int]:
    end = time.monotonic() + timeout_s
    while not done(link.as_dict()) and time.monotonic() < end:
        time.sleep(0.01)
    return link.as_dict()


def test_a_failed_callback_is_counted_and_makes_the_run_not_clean(endpoint: str) -> None:
    cfg = RigConfig()
    key = rig_key(cfg)
    with open_session(listen=True, endpoint=endpoint) as session:
        before = session.subscribe(KEY_VISION_IMAGE, lambda _: 1 / 0)  # not the run's error
        pub = session.publisher(KEY_VISION_IMAGE)
        image = VisionImage(5, 10**9, 2 * 10**9, True, None, (35.5, 15.5), (-3.0, 4.0), b"png")
        pub.put(encode_vision_image(image, key=key))
        deadline = time.monotonic() + 10
        while session.callback_errors < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert session.callback_errors == 1
        before.undeclare()
        ctx = RunContext(cfg, FakeClock(10**9), threading.Event(), RunCounters(), FailingRecorder())
        decoder = FeatureDecoder.from_config(cfg.controller, key=key)
        link = FeatureLink(ctx, session, decoder, by_callback=True, record_raw=False)
        link.attach()
        try:
            assert link.as_dict()["callback_errors"] == 0  # the session's count before the run
            pub.put(encode_vision_image(image, key=key))
            counts = _counts_when(link, lambda c: c["callback_errors"] >= 1)
        finally:
            link.detach()
    assert counts["callback_errors"] == 1
    problems = run_problems({"rejections": {"features": counts}})
    assert any(p.startswith("1 feature-link callback error(s)") for p in problems), problems
