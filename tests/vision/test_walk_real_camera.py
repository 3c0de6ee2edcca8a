"""Walking docs/tutorials/real-camera.md as a lab with a real camera would: an image sequence
whose files are not all of one size, ``--frames --json`` on a log, ``hil camera calibrate``
with a rig config that does not exist yet."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from rt_controller.cli import main
from tests.support.synthetic_frames import frame, write_image_log
from vision.grabber import Grabber
from vision.intrinsics import Intrinsics
from vision.pipeline import Pipeline
from vision.sources import open_source

K = Intrinsics(640, 480, 1230.0, 1230.0, 319.5, 239.5)
"""The default [camera]: 640 x 480."""


def test_an_image_sequence_keeps_each_files_size(tmp_path: Path):
    """A file of another size in a numbered sequence is rejected as wrong_size, not scaled to
    the first file's size and measured (FFmpeg's image2 demuxer rescales it silently)."""
    (tmp_path / "seq").mkdir()
    f = (-20.0, 10.0)
    images = [frame(K, f), cv2.resize(frame(K, f), (800, 600)), frame(K, f)]
    for i, img in enumerate(images):
        cv2.imwrite(str(tmp_path / "seq" / f"view-{i:03d}.png"), img)
    sent = []
    g = Grabber(Pipeline(K), sent.append, source_id=1)
    open_source(f"file:{tmp_path / 'seq' / 'view-%03d.png'}").run(
        g.on_frame, g.on_reject, threading.Event()
    )
    stats = g.snapshot()
    assert [m.valid for m in sent] == [True, False, True]
    assert stats.pipeline["rejected"]["wrong_size"] == 1
    assert stats.wrong_size_px == (800, 600) or list(stats.wrong_size_px) == [800, 600]
    assert np.abs(np.subtract(sent[0].f, f)).max() < 0.05


def test_an_image_sequence_plays_past_a_gap(tmp_path: Path):
    """Every file of the sequence is played, in number order: a missing number does not end
    it (FFmpeg stops at the first gap and drops the rest without a word)."""
    (tmp_path / "seq").mkdir()
    for i in (0, 1, 3, 4, 10):
        cv2.imwrite(str(tmp_path / "seq" / f"v{i}.png"), frame(K, (-20.0 + i, 10.0)))
    sent = []
    g = Grabber(Pipeline(K), sent.append, source_id=1)
    open_source(f"file:{tmp_path / 'seq' / 'v%d.png'}").run(
        g.on_frame, g.on_reject, threading.Event()
    )
    assert len(sent) == 5 and all(m.valid for m in sent)
    assert [round(m.f[0]) for m in sent] == [-20, -19, -17, -16, -10]


def test_frames_and_json_keep_stdout_json_lines_of_frames(tmp_path: Path, capsys):
    """``--frames``: stdout is one JSON line per frame; the summary, --json or not, goes to
    stderr (as the option's help says)."""
    log = write_image_log(tmp_path / "run.mcap", [frame(K, (-20.0 + i, 10.0)) for i in range(3)])
    assert main(["vision", "--source", f"log:{log}", "--frames", "--json"]) == 0
    out, err = capsys.readouterr()
    lines = [json.loads(line) for line in out.splitlines()]
    assert [line["seq"] for line in lines] == [0, 1, 2]
    assert json.loads(err.strip().splitlines()[-1])["frames"] == 3


def test_calibrate_with_a_config_that_does_not_exist_says_what_to_do(tmp_path: Path, capsys):
    missing = tmp_path / "rig.toml"
    assert main(["camera", "calibrate", "--images", str(tmp_path), "--config", str(missing)]) == 2
    err = capsys.readouterr().err
    assert "examples/rig.toml" in err and len(err.strip().splitlines()) == 1
    assert not missing.exists()


@pytest.mark.parametrize("frames", [False, True])
def test_frames_without_json_prints_the_summary_line(tmp_path: Path, capsys, frames: bool):
    log = write_image_log(tmp_path / "run.mcap", [frame(K, (-20.0, 10.0))])
    assert main(["vision", "--source", f"log:{log}", *(["--frames"] if frames else [])]) == 0
    out, err = capsys.readouterr()
    summary = err if frames else out
    assert "1 frames from log:" in summary


def test_calibrate_keeps_the_comments_of_the_keys_it_replaces(tmp_path: Path):
    """The [vision] keys' own comments (examples/rig.toml: ``fx = 1230.0  # px``) stay on the
    lines of the calibrated values."""
    from vision.calibration import Calibration, write_vision_section

    rig = tmp_path / "rig.toml"
    rig.write_text(
        "[vision]\ncalibrated = false\nfx = 1230.0               # px\n"
        "k1 = 0.0                  # OpenCV's distortion model (k1, k2, p1, p2, k3)\n"
        "rt_priority = 60          # realtime\n"
    )
    k = np.array([[1229.7, 0.0, 319.4], [0.0, 1229.8, 239.5], [0.0, 0.0, 1.0]])
    dist = np.array([-0.0987, 0.0346, 0.0, 0.0, 0.0])
    write_vision_section(rig, Calibration(640, 480, k, dist, 0.05, 20, 20, 1110))
    lines = rig.read_text().splitlines()
    assert "fx = 1229.7  # px" in lines
    assert "k1 = -0.0987  # OpenCV's distortion model (k1, k2, p1, p2, k3)" in lines
    assert "rt_priority = 60          # realtime" in lines
    assert "calibrated = true" in lines


def _square(img: np.ndarray, x: int, y: int, side: int, angle: float = 0.0) -> np.ndarray:
    """``img`` with a dark square of ``side`` px centred at (x, y), turned by ``angle`` deg."""
    box = cv2.boxPoints(((float(x), float(y)), (float(side), float(side)), angle))
    cv2.fillPoly(img, [np.round(box * 16).astype(np.int32)], 30, cv2.LINE_AA, shift=4)
    return img


@pytest.mark.parametrize("angle", [0.0, 30.0])
def test_a_dark_square_is_not_the_target(angle: float):
    """A real scene holds dark squares (the calibration board's markers, a chip): their
    moments are as round as a disc's, but a square fills only 0.955 of its moment ellipse
    (any parallelogram: the ratio does not change with the view's tilt), a disc 1."""
    plane = np.full((480, 640), 200, np.uint8)
    m = Pipeline(K).process(_square(plane, 300, 200, 24, angle))
    assert not m.valid and m.reason == "not_found"


def test_the_disc_wins_over_a_square_beside_it():
    f = (-20.0, 10.0)
    img = _square(frame(K, f), 500, 400, 22)
    m = Pipeline(K).process(img)
    assert m.valid and np.abs(np.subtract(m.f, f)).max() < 0.05
