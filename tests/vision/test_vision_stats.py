"""``hil vision --json``: a timing no frame gave is null, not a measured 0 us."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from hal.zenoh_session import free_loopback_port
from rt_controller.cli import main
from tests.support.synthetic_frames import frame
from vision.grabber import Grabber
from vision.intrinsics import Intrinsics
from vision.pipeline import Pipeline

K = Intrinsics(640, 480, 1230.0, 1230.0, 320.0, 240.0)


def test_a_grabber_without_frames_has_no_timings() -> None:
    stats = Grabber(Pipeline(K), lambda msg: None, source_id=1).snapshot()
    timings = [stats.detect_us_p50, stats.detect_us_p99, stats.latency_us_p50]
    assert timings == [None, None, None]


def test_a_file_source_has_no_emulated_camera_timings(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The pipeline and arrival times belong to the emulated camera's payloads; a clip has
    none, and its JSON says null where it said 0.0."""
    clip = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480))
    for i in range(3):
        writer.write(cv2.cvtColor(frame(K, (-120.0 + i, -160.0)), cv2.COLOR_GRAY2BGR))
    writer.release()
    assert main(["keygen", str(tmp_path / "rig.key")]) == 0
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    argv = ["vision", "--source", f"file:{clip}", "--json", "--zenoh-role", "hub"]
    argv += ["--zenoh-endpoint", endpoint, "--key-file", str(tmp_path / "rig.key")]
    assert main(argv) == 0
    stats = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert stats["frames"] == 3
    assert stats["pipeline_us_p50"] is None and stats["arrival_us_p99"] is None
    assert np.isfinite(stats["detect_us_p99"]) and stats["detect_us_p99"] > 0
