"""``hil vision --source``: a source that cannot give frames is one line and status 2 — a
missing or unreadable file, a directory, a missing device before the zenoh hub is waited for;
a file OpenCV reads no frame from instead of a run of 0 frames."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import pytest

from hal.errors import HalConfigError
from tests.support import free_endpoint, run_hil
from vision.sources import check_source

NO_HUB_WAIT = ["--zenoh-role", "client", "--wait", "3"]
"""No hub listens there: a source checked only after the wait says "no hub", not its fault."""


def vision(source: str, *extra: str) -> tuple[int, str]:
    done = run_hil(["vision", "--source", source, "--zenoh-endpoint", free_endpoint(), *extra], 120)
    return done.returncode, done.stderr


def test_a_file_without_a_frame_is_an_error_not_an_empty_run(tmp_path: Path):
    fake = tmp_path / "fake.png"
    fake.write_text("a text file, not an image\n")
    status, err = vision(f"file:{fake}", "--zenoh-role", "hub", "--duration", "2")
    assert status == 2, err
    assert f"hil vision: error: --source file:{fake}: OpenCV could not read a frame" in err


@pytest.mark.parametrize(
    ("target", "said"),
    [
        ("file:{tmp}/nope.mp4", "no such file"),
        ("file:{tmp}", "is a directory, not a video or image file"),
        ("v4l2:{tmp}/video9", "no such device"),
        ("v4l2:{tmp}/plain", "not a video device"),
    ],
)
def test_a_missing_source_is_told_before_the_hub_is_waited_for(tmp_path, target, said):
    (tmp_path / "plain").write_bytes(b"")
    source = target.format(tmp=tmp_path)
    status, err = vision(source, *NO_HUB_WAIT)
    assert status == 2 and f"hil vision: error: --source {source}: {said}" in err, err
    assert "no hub" not in err


@pytest.mark.skipif(
    cv2.videoio_registry.hasBackend(cv2.CAP_GSTREAMER), reason="this OpenCV has GStreamer"
)
def test_a_pipeline_without_gstreamer_is_told_before_the_hub_is_waited_for():
    status, err = vision("gst:videotestsrc ! appsink", *NO_HUB_WAIT)
    assert status == 2 and "built without GStreamer" in err and "no hub" not in err, err


def test_an_unreadable_file_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """As a lab's user, not root (root reads every file, so the OS's answer is stood in for)."""
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"\0" * 16)
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: Path(p) != clip and real(p, mode))
    with pytest.raises(HalConfigError, match=r"--source file:.*clip.mp4: not readable"):
        check_source(f"file:{clip}")
