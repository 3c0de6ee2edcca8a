"""What the camera saw, in the log: a ``hil/vision/image`` payload becomes the frame
(``foxglove.CompressedImage``) and its detection (``foxglove.ImageAnnotations``) at its capture
time; a payload that is no vision image is counted, never raised."""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np
from mcap.reader import make_reader

from hal.config import RigConfig
from hal.secoc import rig_key
from hal.vision_image import VisionImage, encode_vision_image
from rt_controller.runtime.recorder import IMAGE, CycleRecorder
from vision.sources import decode_compressed_image


def test_image_records_become_frames_and_detections(tmp_path):
    pixels = np.zeros((48, 64), np.uint8)
    pixels[10:20, 30:40] = 200
    ok, png = cv2.imencode(".png", pixels)
    assert ok
    good = VisionImage(5, 10**9, 2 * 10**9, True, None, (35.5, 15.5), (-3.0, 4.0), png.tobytes())
    none = good._replace(frame=6, valid=False, reason="out_of_view", uv=(0.0, 0.0))
    path = tmp_path / "run.mcap"
    rec = CycleRecorder(path, RigConfig())
    assert rec.write(IMAGE, 0, encode_vision_image(good))
    assert rec.write(IMAGE, 0, encode_vision_image(none))
    assert not rec.write(IMAGE, 0, b"HV\x01 not an image")
    assert rec.images_written == 2 and rec.image_errors == 1
    rec.close()
    with path.open("rb") as fh:
        msgs = [(c.topic, m) for _, c, m in make_reader(fh).iter_messages()]
    images = [m for t, m in msgs if t == "/camera/image"]
    detections = [m for t, m in msgs if t == "/camera/detection"]
    assert len(images) == len(detections) == 2
    assert np.array_equal(decode_compressed_image(images[0].data), pixels)  # lossless
    assert b"detected f = (-3.00, 4.00) px" in detections[0].data
    assert b"no target: out_of_view" in detections[1].data


def test_an_image_the_recorder_process_cannot_log_is_in_the_summary_and_a_problem(tmp_path):
    from rt_controller.runtime.counters import run_problems
    from rt_controller.runtime.recorder_process import RecorderProcess

    pixels = np.zeros((48, 64), np.uint8)
    ok, png = cv2.imencode(".png", pixels)
    assert ok
    good = VisionImage(5, 10**9, 2 * 10**9, True, None, (35.5, 15.5), (-3.0, 4.0), png.tobytes())
    with RecorderProcess(tmp_path / "run.mcap", RigConfig()) as rec:
        assert rec.write(IMAGE, 0, encode_vision_image(good))
        assert rec.write(IMAGE, 0, b"HV\x01 not an image")  # sent: the child finds it bad
        assert rec.as_dict()["images_written"] == 2  # in the run: sent to be written
    counts = rec.as_dict()
    assert (counts["images_written"], counts["image_errors"]) == (1, 1)
    problems = run_problems({"recorder": counts})
    assert problems == ["1 camera image(s) could not be written to the log"]


class _Rings:
    """``subscribe_ring`` of a zenoh session: camera image payloads, once; nothing else."""

    def __init__(self, images: list[bytes]) -> None:
        self.images = images

    def subscribe_ring(self, key: str, capacity: int) -> Any:
        from hal.zenoh_session import KEY_VISION_IMAGE

        payloads = self.images if key == KEY_VISION_IMAGE else []

        class Ring:
            def drain(self) -> list[bytes]:
                out = list(payloads)
                payloads.clear()
                return out

            def close(self) -> None:
                pass

        return Ring()


def test_a_monitor_with_another_key_than_the_rig_s_says_why_it_shows_no_image(caplog):
    """``hil monitor`` shows a camera image only if the rig key authenticates it; given
    another key it would show none and say nothing. It warns once and counts them."""
    from hal.zenoh_session import free_loopback_port
    from rt_controller.monitor.bridge import MonitorBridge

    _ok, png = cv2.imencode(".png", np.zeros((48, 64), np.uint8))
    msg = VisionImage(5, 10**9, 2 * 10**9, True, None, (35.5, 15.5), (-3.0, 4.0), png.tobytes())
    cfg = RigConfig()
    theirs = [encode_vision_image(msg, key=bytes(32)) for _ in range(3)]
    ours = encode_vision_image(msg, key=rig_key(cfg))
    bridge = MonitorBridge(cfg, _Rings([*theirs, ours]), port=free_loopback_port()).start()
    try:
        deadline = time.monotonic() + 30.0  # a hang guard, not a timing claim
        while bridge.counts["images"] + bridge.counts["images_refused"] < 4:
            assert time.monotonic() < deadline, bridge.counts
            time.sleep(0.01)
    finally:
        bridge.close()
    assert (bridge.counts["images"], bridge.counts["images_refused"]) == (1, 3)
    warnings = [r.getMessage() for r in caplog.records if "camera images refused" in r.getMessage()]
    assert len(warnings) == 1 and "--key-file" in warnings[0], warnings
