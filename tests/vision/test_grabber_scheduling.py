"""The frame grabber asks for SCHED_FIFO (``vision.rt_priority``) once for each thread that
measures realtime frames, never for lockstep ones; a refusal is reported, never raised."""

from __future__ import annotations

import os
import threading

import numpy as np

from hal.camera_frame import CameraFrame
from vision.grabber import Grabber
from vision.intrinsics import Intrinsics
from vision.pipeline import Pipeline

K = Intrinsics(640, 480, 1230.0, 1230.0, 319.5, 239.5)


def measured_on_a_thread(g: Grabber, lockstep: bool) -> int:
    """Measure one blank frame on a thread of its own; that thread's policy afterwards."""
    policy = []

    def body() -> None:
        g.on_frame(CameraFrame(1, 1, 1, 0, 1, np.full((480, 640), 200, np.uint8), lockstep))
        policy.append(os.sched_getscheduler(0))

    t = threading.Thread(target=body)
    t.start()
    t.join(10)
    return policy[0]


def test_realtime_frames_are_measured_on_a_fifo_thread_or_say_why_not():
    g = Grabber(Pipeline(K), lambda msg: None, source_id=1, rt_priority=10)
    assert measured_on_a_thread(g, lockstep=True) == os.SCHED_OTHER
    assert g.snapshot().scheduling == ""
    policy = measured_on_a_thread(g, lockstep=False)
    why = g.snapshot().scheduling
    if why == "SCHED_FIFO":
        assert policy == os.SCHED_FIFO
    else:  # no CAP_SYS_NICE here: the reason, and the frame was measured all the same
        assert why.startswith("SCHED_FIFO 10 refused") and policy == os.SCHED_OTHER
    assert g.snapshot().frames == 2


def test_no_priority_leaves_scheduling_alone():
    g = Grabber(Pipeline(K), lambda msg: None, source_id=1)
    assert measured_on_a_thread(g, lockstep=False) == os.SCHED_OTHER
    assert g.snapshot().scheduling == ""
