"""The vision pipeline on frames drawn with OpenCV (tests/support/synthetic_frames.py): f
against the drawn eq. (6) features over a grid, the lens round trip, and every kind of frame
without a measurement rejected and counted, never raised."""

from __future__ import annotations

import numpy as np
import pytest

from tests.support.synthetic_frames import frame
from vision.intrinsics import Intrinsics
from vision.pipeline import Pipeline

PAPER = Intrinsics(640, 480, 1230.0, 1230.0, 320.0, 240.0)
LENS = Intrinsics(640, 480, 1230.0, 1230.0, 322.5, 238.0, (-0.25, 0.12, 0.001, -0.0005, 0.0))
GRID = [(fx, fy) for fx in np.linspace(-270.3, 270.7, 7) for fy in np.linspace(-190.1, 190.9, 5)]


@pytest.mark.parametrize("k", [PAPER, LENS], ids=["ideal", "distorted"])
def test_f_matches_the_drawn_features_over_a_grid(k: Intrinsics):
    p = Pipeline(k)
    errors = []
    for f in GRID:
        m = p.process(frame(k, f))
        assert m.valid, (f, m.reason)
        errors.append(np.subtract(m.f, f))
    rms = float(np.sqrt(np.mean(np.square(errors))))
    # measured: 0.0012 px ideal, 0.006 px through the lens
    assert rms < 0.02, rms
    assert p.counts.measured == len(GRID)


def test_noise_keeps_the_error_sub_pixel():
    p = Pipeline(PAPER)
    errors = [
        np.subtract(p.process(frame(PAPER, f, noise=3.0, seed=i)).f, f) for i, f in enumerate(GRID)
    ]
    assert float(np.sqrt(np.mean(np.square(errors)))) < 0.1


@pytest.mark.parametrize(
    "f", [(-120.0, -160.0), (0.0, 0.0), (250.0, 180.0), (-300.0, -220.0), (290.0, -200.0)]
)
def test_lens_round_trip(f):
    assert np.allclose(LENS.features(LENS.pixel(f)), f, atol=1e-6)


def test_out_of_view_is_rejected_and_counted():
    p = Pipeline(PAPER)
    m = p.process(frame(PAPER, (-318.0, 10.0)))  # the disc crosses the left border
    assert not m.valid and m.reason == "out_of_view"
    m = p.process(frame(PAPER, (-400.0, 10.0)))  # entirely outside
    assert not m.valid and m.reason == "not_found"
    assert p.counts.as_dict()["rejected"]["out_of_view"] == 1
    assert p.counts.as_dict()["rejected"]["not_found"] == 1


def test_a_smeared_target_is_blurred_not_a_wrong_measurement():
    p = Pipeline(PAPER)
    m = p.process(frame(PAPER, (10.0, 20.0), blur_px=40.0))
    assert not m.valid and m.reason == "blurred"
    assert p.counts.rejected["blurred"] == 1


@pytest.mark.parametrize(
    ("pixels", "reason"),
    [
        (np.zeros((240, 320), np.uint8), "wrong_size"),
        (np.zeros((480, 640), np.float32), "malformed"),
        (np.zeros((480, 640, 3), np.uint8), "malformed"),
        (b"not an image", "malformed"),
        (np.full((480, 640), 128, np.uint8), "not_found"),
    ],
    ids=["mis-sized", "float", "colour", "bytes", "blank"],
)
def test_bad_frames_are_rejected_and_counted(pixels, reason):
    p = Pipeline(PAPER)
    m = p.process(pixels)
    assert (m.valid, m.reason) == (False, reason)
    assert p.counts.as_dict()["rejected"][reason] == 1
    assert p.counts.frames == 1 and p.counts.measured == 0
