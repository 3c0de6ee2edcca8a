"""What the camera saw, in the log: a ``hil/vision/image`` payload becomes the frame
(``foxglove.CompressedImage``) and its detection (``foxglove.ImageAnnotations``) at its capture
time; a payload that is no vision image is counted, never raised."""

from __future__ import annotations

import cv2
import numpy as np
from mcap.reader import make_reader

from hal.config import RigConfig
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
