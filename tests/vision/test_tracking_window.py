"""The pipeline's tracking window: a measurement found in the window is the whole frame's (to the
threshold's effect on a textured plane), and a target the window misses (a jump, a frame
without it) is found in the whole frame."""

from __future__ import annotations

import numpy as np

from tests.support.synthetic_frames import frame
from vision.intrinsics import Intrinsics
from vision.pipeline import Pipeline

PAPER = Intrinsics(640, 480, 1230.0, 1230.0, 320.0, 240.0)
PATH = [(-120.0 + 3.7 * i, -160.0 + 2.9 * i + 0.4 * i * i) for i in range(12)]


def test_a_tracked_target_measures_as_in_the_whole_frame():
    tracked, whole = Pipeline(PAPER), Pipeline(PAPER, track=False)
    for i, f in enumerate(PATH):
        img = frame(PAPER, f, noise=2.0, seed=i)
        a, b = tracked.process(img), whole.process(img)
        assert a.valid and b.valid
        # the window's median grey sets the threshold, so the disc's edge pixels taken can
        # differ on a textured plane: measured up to 0.0011 px (identical on a plain one)
        np.testing.assert_allclose(a.f, b.f, rtol=0, atol=0.005)
    assert tracked.counts.tracked == len(PATH) - 1  # the first frame has no window yet
    assert whole.counts.tracked == 0


def test_a_jump_out_of_the_window_is_found_in_the_whole_frame():
    p = Pipeline(PAPER)
    for f in [(0.0, 0.0), (1.5, 1.0), (250.0, 180.0), (251.0, 181.0)]:
        m = p.process(frame(PAPER, f))
        assert m.valid, (f, m.reason)
        np.testing.assert_allclose(m.f, f, atol=0.05)
    assert p.counts.tracked == 2  # (1.5, 1) and (251, 181); the jump searched the whole frame


def test_a_frame_without_the_target_then_the_target_again():
    p = Pipeline(PAPER)
    assert p.process(frame(PAPER, (10.0, 10.0))).valid
    lost = p.process(frame(PAPER, (-318.0, 10.0)))  # across the left border
    assert (lost.valid, lost.reason) == (False, "out_of_view")
    back = p.process(frame(PAPER, (-100.0, 50.0)))
    assert back.valid
    np.testing.assert_allclose(back.f, (-100.0, 50.0), atol=0.05)
    assert p.counts.as_dict()["rejected"]["out_of_view"] == 1
