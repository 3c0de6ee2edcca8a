"""Region-of-interest readout at the frame grabber: it asks for the region its tracking window
reads (the whole frame with no window: at the start, after losing the target), a region gives
the features of the whole frame bit for bit, and a region without the target is asked for again
whole and answered from the whole frame, so the features never depend on what the camera sent."""

from __future__ import annotations

import numpy as np

from hal.camera_frame import CameraFrame, RoiRequest
from hal.vision_codec import FeatureMsg
from tests.support.synthetic_frames import frame
from vision.grabber import Grabber
from vision.intrinsics import Intrinsics
from vision.pipeline import Pipeline

K = Intrinsics(640, 480, 1230.0, 1230.0, 320.0, 240.0)
SOURCE = 0x5151
# a moving target, a jump (out of any window), out of view, back in view
PATH = [(-120.0 + 3.7 * i, -160.0 + 2.9 * i) for i in range(6)] + [
    (150.0, 120.0),
    (152.0, 121.5),
    (-318.0, 10.0),
    (-100.0, 50.0),
    (-98.0, 51.0),
]


def images() -> list[np.ndarray]:
    return [frame(K, f, noise=2.0, seed=i) for i, f in enumerate(PATH)]


def camera_frame(seq: int, img: np.ndarray, window=None) -> CameraFrame:
    x0, y0, x1, y1 = (0, 0, img.shape[1], img.shape[0]) if window is None else window
    return CameraFrame(
        seq, seq, seq, 0, seq, img[y0:y1, x0:x1], True, SOURCE, "mono8", x0, y0, (640, 480)
    )


def run_whole(imgs: list[np.ndarray]) -> list[FeatureMsg]:
    sent: list[FeatureMsg] = []
    g = Grabber(Pipeline(K), sent.append, source_id=1)
    for seq, img in enumerate(imgs):
        g.on_frame(camera_frame(seq, img))
    return sent


def test_regions_give_the_whole_frames_features_and_a_miss_asks_the_frame_again_whole():
    imgs = images()
    sent: list[FeatureMsg] = []
    asked: list[RoiRequest] = []
    g = Grabber(Pipeline(K), sent.append, source_id=1, request_roi=asked.append)
    sent_whole = []  # frames the grabber had to ask for again whole
    for seq, img in enumerate(imgs):
        req = next((r for r in reversed(asked) if r.seq == seq), None)
        window = req.window if req is not None else None
        if g.on_frame(camera_frame(seq, img, window)) is None:
            assert asked[-1] == RoiRequest(SOURCE, seq, None)
            sent_whole.append(seq)
            assert g.on_frame(camera_frame(seq, img)) is not None
    assert sent == run_whole(imgs)  # every field, f bit for bit
    assert sent_whole == [6, 8]  # the jump, the target out of view; 9 was asked whole at once
    s = g.snapshot()
    assert (s.roi_misses, s.roi_frames) == (2, 7)
    assert s.published == len(PATH) and s.pipeline["frames"] == len(PATH)


def test_the_grabber_asks_for_the_whole_frame_without_a_window():
    imgs = images()
    asked: list[RoiRequest] = []
    g = Grabber(Pipeline(K), lambda m: None, source_id=1, request_roi=asked.append)
    g.on_frame(camera_frame(0, imgs[0]))
    first = asked[-1]
    assert first.seq == 1 and first.source == SOURCE and first.window is not None
    x0, y0, x1, y1 = first.window
    assert 0 <= x0 < x1 <= 640 and 0 <= y0 < y1 <= 480
    assert (x1 - x0) * (y1 - y0) < 640 * 480 / 8  # a region, not the frame
    lost = g.on_frame(camera_frame(1, imgs[8]))  # the target out of view
    assert lost is not None and not lost.valid
    assert asked[-1] == RoiRequest(SOURCE, 2, None)  # lost: the whole next frame


def test_a_region_that_does_not_hold_the_window_is_asked_again_whole():
    """A camera that sent another region than asked (clamped, stale) cannot fool the grabber:
    the region is not measured, the frame is asked for whole."""
    imgs = images()
    asked: list[RoiRequest] = []
    sent: list[FeatureMsg] = []
    g = Grabber(Pipeline(K), sent.append, source_id=1, request_roi=asked.append)
    g.on_frame(camera_frame(0, imgs[0]))
    x0, y0, x1, y1 = asked[-1].window
    assert g.on_frame(camera_frame(1, imgs[1], (x0 + 2, y0, x1, y1))) is None
    assert asked[-1] == RoiRequest(SOURCE, 1, None)
    assert g.on_frame(camera_frame(1, imgs[1])) is not None
    assert sent == run_whole(imgs[:2])


def test_sources_that_cannot_read_out_a_region_ignore_the_request():
    from vision.sources import CaptureSource, LogSource

    for source in (CaptureSource("file", "clip.mp4"), LogSource("run.mcap")):
        assert source.request_roi(RoiRequest(1, 1, (0, 0, 10, 10))) is None
