"""The decimated image stream's slots (hal.vision_image.ImageSlots): one rule for the image log,
which takes those frames, and the emulated camera, which sends them whole."""

from __future__ import annotations

from hal.vision_image import ImageSlots


def test_image_slots_take_the_first_frame_of_each_slot_and_restart_with_a_new_run():
    slots = ImageSlots(10.0)  # 100 ms slots
    times = [-2, 18, 38, 98, 118, 138, 250, 20, 40, 120]  # ms; 20 after 250: a new run
    taken = []
    for t in times:
        due = slots.due(t * 1_000_000)
        took = slots.take(t * 1_000_000)
        assert due == took
        taken.append(took)
    assert [t for t, k in zip(times, taken, strict=True) if k] == [-2, 18, 118, 250, 20, 120]
    slots.reset()
    assert slots.take(130_000_000)
    assert not ImageSlots(0.0).take(0) and not ImageSlots(0.0).due(0)
