"""``hil vision --source`` off the happy path, as a lab plugging in a real camera misuses it: a
file that is no video, a clip of another size than the configured camera, a log that is no
MCAP file, ``--frames`` with a live source, a device named by its index."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import cv2
import pytest

from hal.errors import HalConfigError
from rt_controller.cli import main
from tests.support import free_endpoint, run_hil
from tests.support.synthetic_frames import frame, write_image_log
from vision.intrinsics import Intrinsics
from vision.sources import check_source, open_source

K = Intrinsics(640, 480, 1230.0, 1230.0, 319.5, 239.5)
"""The default [camera]: 640 x 480."""


def _clip(path: Path, size: tuple[int, int], n: int = 4, *, colour: bool = False) -> Path:
    """An mp4 of ``n`` frames of the target, scaled to ``size`` (w, h)."""
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (w, h), colour)
    assert writer.isOpened()
    for i in range(n):
        img = cv2.resize(frame(K, (-20.0 + i, 10.0)), (w, h))
        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if colour else img)
    writer.release()
    return path


def _image_log(path: Path, size: tuple[int, int], n: int = 3) -> Path:
    images = [cv2.resize(frame(K, (-20.0 + i, 10.0)), size) for i in range(n)]
    return write_image_log(path, images)


def _live(tmp_path: Path, source: str, *extra: str) -> list[str]:
    """``hil vision`` in this process on a live ``source``; vision.rt_priority 0: a capture
    source measures on the calling thread, which would stay SCHED_FIFO for later tests."""
    if not (tmp_path / "rig.key").exists():
        assert main(["keygen", str(tmp_path / "rig.key")]) == 0
    cfg = tmp_path / "rig.toml"
    cfg.write_text("[vision]\nrt_priority = 0\n")
    key = str(tmp_path / "rig.key")
    argv = ["vision", "--source", source, "--key-file", key, "--config", str(cfg)]
    return [*argv, "--zenoh-role", "hub", "--zenoh-endpoint", free_endpoint(), *extra]


def test_frames_of_another_size_name_both_sizes_and_time_no_detection(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    """A 320 x 240 clip for a 640 x 480 camera: every frame is rejected wrong_size, the end line
    names both sizes, and no detection ran, so there is no detection time (was ``p99 1 us``)."""
    log = _image_log(tmp_path / "small.mcap", (320, 240))
    assert main(["vision", "--source", f"log:{log}"]) == 0
    out, err = capsys.readouterr()
    assert "wrong_size 3" in out
    assert "frames are 320x240, camera.width_px x height_px 640x480" in out + err
    assert "detection p99" not in out
    assert main(["vision", "--source", f"log:{log}", "--json"]) == 0
    stats = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert stats["pipeline"]["rejected"]["wrong_size"] == 3
    assert stats["detect_us_p50"] is None and stats["detect_us_p99"] is None


def test_a_live_clip_of_another_size_is_told_on_stderr_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    clip = _clip(tmp_path / "small.mp4", (320, 240), colour=True)
    assert main(_live(tmp_path, f"file:{clip}")) == 0
    out, err = capsys.readouterr()
    said = [line for line in err.splitlines() if "320x240" in line]
    assert len(said) == 1 and "wrong_size" in said[0], err
    assert "4 frames" in out and "wrong_size 4" in out


def test_grey_and_colour_clips_measure_alike(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    for colour in (False, True):
        clip = _clip(tmp_path / f"c{colour}.mp4", (640, 480), colour=colour)
        assert main(_live(tmp_path, f"file:{clip}", "--json")) == 0
        stats = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert (stats["frames"], stats["valid"]) == (4, 4)


def _refused(tmp_path: Path, source: str) -> list[str]:
    """The stderr lines of a ``hil vision --source SOURCE`` process that exits 2 (bad usage),
    less its start-up line."""
    key = tmp_path / "rig.key"
    assert run_hil(["keygen", str(key)], 60).returncode == 0
    done = run_hil(
        [
            *("vision", "--source", source, "--key-file", str(key)),
            *("--zenoh-role", "hub", "--zenoh-endpoint", free_endpoint()),
        ],
        120,
    )
    assert done.returncode == 2, done.stderr
    return [line for line in done.stderr.splitlines() if "image pipeline on" not in line]


@pytest.mark.parametrize("content", ["text", "empty", "cut"])
def test_a_file_that_is_no_video_is_one_line_saying_so(tmp_path: Path, content: str):
    """FFmpeg's own complaint ("moov atom not found") is not printed beside ours, and a file
    is not called a busy device."""
    clip = tmp_path / "clip.mp4"
    if content == "cut":  # written whole, then cut: its index (at the end) is gone
        data = _clip(tmp_path / "whole.mp4", (640, 480)).read_bytes()
        clip.write_bytes(data[: len(data) // 2])
    else:
        clip.write_text("not a video\n" if content == "text" else "")
    lines = _refused(tmp_path, f"file:{clip}")
    assert lines == [
        f"hil vision: error: --source file:{clip}: not a video OpenCV can open (or this "
        "OpenCV has no decoder for it)"
    ], lines


@pytest.mark.parametrize(
    ("content", "said"),
    [
        (b"", "an empty file"),
        (b"not an mcap log\n", "does not begin with the MCAP magic"),
        (b"\x89MC", "does not begin with the MCAP magic"),
    ],
)
def test_a_log_that_is_no_mcap_file_says_what_it_is(tmp_path: Path, content: bytes, said: str):
    path = tmp_path / "run.mcap"
    path.write_bytes(content)
    with pytest.raises(HalConfigError, match=f"not an MCAP log: {said}$"):
        open_source(f"log:{path}").run(lambda f: None, lambda r: None, threading.Event())


def test_frames_with_a_live_source_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    clip = _clip(tmp_path / "clip.mp4", (640, 480))
    argv = _live(tmp_path, f"file:{clip}", "--frames")
    capsys.readouterr()  # keygen's line
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--frames: only with --source log:" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("model", ["image", "analytic"])
def test_frames_without_a_log_source_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], model: str
):
    cfg = tmp_path / "rig.toml"
    cfg.write_text(f'[camera]\nmodel = "{model}"\n')
    assert main(["vision", "--config", str(cfg), "--frames"]) == 2
    assert "--frames: only with --source log:" in capsys.readouterr().err


def test_a_device_named_by_its_index_is_pointed_at_its_path():
    with pytest.raises(HalConfigError, match=r"v4l2:0: no such device \(give its path"):
        check_source("v4l2:0")


def test_a_device_that_gives_no_video_is_one_line(tmp_path: Path):
    """/dev/null is a character device this user may open, as a USB camera's metadata node
    (its second /dev/videoN) is: OpenCV's own warning is not printed beside ours."""
    lines = _refused(tmp_path, "v4l2:/dev/null")
    assert len(lines) == 1 and "v4l2:/dev/null: OpenCV cannot open it" in lines[0], lines
    assert "metadata" in lines[0]


def test_a_home_relative_path_is_found(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """``--source log:~/run.mcap``: the shell leaves a ``~`` after ``log:`` as it is."""
    monkeypatch.setenv("HOME", str(tmp_path))
    _image_log(tmp_path / "run.mcap", (640, 480))
    seen: list[int] = []
    open_source("log:~/run.mcap").run(lambda f: seen.append(f.seq), seen.append, threading.Event())
    assert seen == [0, 1, 2]
    check_source("file:~/run.mcap")  # found (what it holds is the capture's business)


def test_a_capture_source_leaves_the_callers_scheduling_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    """vision.rt_priority (60 by default) makes the thread that measures a camera's frames
    SCHED_FIFO: that is the capture's own thread, not the caller's (it stayed SCHED_FIFO,
    and every thread it started after, for the rest of an in-process caller's life)."""
    import os

    clip = _clip(tmp_path / "clip.mp4", (640, 480))
    key = tmp_path / "rig.key"
    assert main(["keygen", str(key)]) == 0
    argv = ["vision", "--source", f"file:{clip}", "--key-file", str(key), "--json"]
    before = os.sched_getscheduler(0)
    assert main([*argv, "--zenoh-role", "hub", "--zenoh-endpoint", free_endpoint()]) == 0
    stats = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert stats["valid"] == 4
    assert os.sched_getscheduler(0) == before


def test_a_log_of_an_analytic_camera_run_is_refused(tmp_path: Path):
    """Such a run logs the monitor's blank image plane on /camera/image (about 1 Hz): it was
    re-run as camera frames, "0 measured (not_found N)", exit 0."""
    from foxglove.messages import CompressedImage, Timestamp
    from mcap.writer import Writer

    path = tmp_path / "analytic.mcap"
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start()
        w.add_metadata("hil.config", {"json": json.dumps({"camera": {"model": "analytic"}})})
        sid = w.register_schema(
            "foxglove.CompressedImage", "protobuf", CompressedImage.get_schema().data
        )
        ch = w.register_channel("/camera/image", "protobuf", sid)
        blank = cv2.imencode(".png", frame(K, (0.0, 0.0)) * 0 + 24)[1].tobytes()
        msg = CompressedImage(timestamp=Timestamp(sec=0), frame_id="camera", data=blank)
        w.add_message(ch, 0, msg.encode(), 0)
        w.finish()
    seen: list[object] = []
    with pytest.raises(HalConfigError, match=r"a run of the analytic camera .* no camera frames"):
        open_source(f"log:{path}").run(seen.append, seen.append, threading.Event())
    assert seen == []
