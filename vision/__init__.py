"""The vision process of a rig that sees pixels: frame sources, the OpenCV target detector, the
calibrated camera's intrinsics, and the process that publishes the paper's features f (eq. 6)
on ``hil/vision/features``.

It is product code: it would run unchanged on a real rig behind a frame grabber. It knows
nothing of the emulator, the arm's pose or the target's true position, only frames
(``tests/controller/test_layering.py`` checks this).
"""
