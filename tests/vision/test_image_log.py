"""The decimated image stream (vision.image_log): PNGs made off the grabber's thread, lockstep
frames never dropped, realtime frames dropped and counted when the backlog is full, and a
frame's claim (made before its features leave) exactly the frames logged."""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest

from hal.camera_frame import CameraFrame
from vision.image_log import LOCKSTEP_NICE, ImageLog, png
from vision.pipeline import Measurement

NO_F = Measurement(None, "not_found", None, 0)


def frame(seq: int, lockstep: bool) -> CameraFrame:
    pixels = np.random.default_rng(seq).integers(0, 256, (48, 64), dtype=np.uint8)
    t = seq * 20_000_000  # 50 Hz
    return CameraFrame(seq, t, t, 0, seq, pixels, lockstep)


def offer(log: ImageLog, f: CameraFrame) -> bool:
    """As the grabber does: claim the frame before its features leave, then queue it."""
    claimed = log.claim(f)
    if claimed:
        log.put(f, NO_F)
    return claimed


def test_png_is_lossless():
    img = frame(1, True).pixels
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(png(img), np.uint8), 0), img)


@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (480, 640)])
@pytest.mark.parametrize("content", ["noise", "flat", "strided"])
def test_png_is_an_8_bit_grey_png_of_the_same_pixels(shape, content):
    rng = np.random.default_rng(7)
    if content == "noise":
        img = rng.integers(0, 256, shape, dtype=np.uint8)
    elif content == "flat":
        img = np.full(shape, 204, np.uint8)
    else:  # a view that is not contiguous, as a frame cut from a larger one
        img = rng.integers(0, 256, (shape[0], 2 * shape[1]), dtype=np.uint8)[:, ::2]
    data = png(img)
    assert data.startswith(b"\x89PNG\r\n\x1a\n")
    out = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert out.dtype == np.uint8 and out.shape == shape
    np.testing.assert_array_equal(out, img)


def test_lockstep_frames_wait_for_room_and_are_all_logged_in_order():
    gate, got, how = threading.Event(), [], set()

    def publish(image, lockstep: bool) -> None:
        gate.wait(5.0)
        got.append(image.frame)
        how.add(lockstep)

    log = ImageLog(10.0, publish, 1, backlog=2)
    frames = [frame(i, True) for i in range(40)]  # 0.8 s at 50 Hz: every 5th frame is logged
    feeder = threading.Thread(target=lambda: [offer(log, f) for f in frames])
    feeder.start()
    feeder.join(0.5)
    assert feeder.is_alive()  # blocked on the full backlog, not dropping
    gate.set()
    feeder.join(5.0)
    log.close()
    assert got == list(range(0, 40, 5))
    assert how == {True}  # published to be waited for, never dropped on the way
    assert log.as_dict() == {"sent": 8, "dropped": 0, "errors": 0, "regions": 0}


def test_realtime_frames_beyond_the_backlog_are_dropped_and_counted():
    gate, got, how = threading.Event(), [], set()

    def publish(image, lockstep: bool) -> None:
        gate.wait(5.0)
        got.append(image.frame)
        how.add(lockstep)

    log = ImageLog(10.0, publish, 1, backlog=2)
    claimed = [i for i in range(40) if offer(log, frame(i, False))]  # never blocks
    gate.set()
    log.close()
    c = log.as_dict()
    assert c["sent"] + c["dropped"] == 8 and c["dropped"] >= 5  # one in the encoder, two queued
    assert got == claimed  # a frame refused at its claim, before its features left, only
    assert how == {False}


def test_regions_of_interest_are_never_logged_the_slot_takes_the_next_whole_frame():
    got = []
    log = ImageLog(10.0, lambda image, lockstep: got.append(image), 1)
    for f in (frame(i, True) for i in range(12)):
        if f.seq in (0, 5, 6):  # regions of the sensor's frame, as the camera may send
            f = CameraFrame(
                f.seq, f.stamp_ns, f.sim_time_ns, 0, f.seq, f.pixels[:10, :20], True, 0,
                "mono8", 4, 4, (64, 48),
            )  # fmt: skip
        offer(log, f)
    log.close()
    assert [img.frame for img in got] == [1, 7, 10]
    shapes = {cv2.imdecode(np.frombuffer(img.png, np.uint8), 0).shape for img in got}
    assert shapes == {(48, 64)}
    assert log.as_dict()["regions"] == 3


@pytest.mark.parametrize("lockstep", [True, False])
def test_lockstep_pngs_are_made_at_a_lower_priority_realtime_ones_at_the_default(lockstep):
    """Lockstep: the PNG thread is off the period's chain and runs niced (LOCKSTEP_NICE), at
    the default policy, so it keeps a share of a busy host (an idle-class thread starved
    there, and the chain waited for it); realtime frames keep the default priority (a
    starved thread would drop them). The grabber's thread is never touched."""
    import os

    def priority() -> tuple[int, int]:
        return os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    seen: list[tuple[int, int]] = []
    log = ImageLog(10.0, lambda image, lockstep: seen.append(priority()), 1)
    before = priority()
    for i in range(10):  # 0.2 s at 50 Hz: frames 0 and 5 are logged
        f = frame(i, lockstep)
        offer(log, f)
    log.close()
    assert priority() == before and before[0] == os.SCHED_OTHER
    niced = min(before[1] + LOCKSTEP_NICE, 19) if lockstep else before[1]
    assert seen == [(os.SCHED_OTHER, niced)] * 2


def test_the_png_thread_shortens_the_gil_switch_interval():
    """The PNG thread's Python competes with the grabber for the GIL: once it runs, the
    process hands the GIL over after GIL_SWITCH_S, not Python's 5 ms."""
    import sys

    from hal.fifo import GIL_SWITCH_S

    before = sys.getswitchinterval()
    sys.setswitchinterval(0.005)
    try:
        log = ImageLog(10.0, lambda image, lockstep: None, 1)
        f = frame(0, True)
        offer(log, f)
        log.close()
        assert sys.getswitchinterval() == GIL_SWITCH_S
    finally:
        sys.setswitchinterval(before)
