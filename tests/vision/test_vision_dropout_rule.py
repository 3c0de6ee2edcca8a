"""``hil vision --dropout``: one rule for both vision processes (the analytic one and the image
pipeline), a window beyond it one line before anything starts; ``--dropout`` refused with a
log source (re-run offline, nothing to pause); a frame whose callback failed counted in the
image pipeline's stats, not lost unseen."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from hal.config import RigConfig
from hal.zenoh_session import free_loopback_port
from rt_controller.cli import main
from tests.support.live_grabber import live_grabber
from tests.support.synthetic_frames import frame
from vision.intrinsics import intrinsics_from_config
from vision.pipeline import Measurement, Pipeline

K = intrinsics_from_config(RigConfig())


def hil(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    """Exit status and the stderr lines of ``hil ARGV`` in-process."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return code, err.strip().splitlines()


def _clip(path: Path) -> Path:
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (640, 480))
    for _ in range(3):
        out.write(np.zeros((480, 640, 3), np.uint8))
    out.release()
    return path


def _image_log(path: Path) -> Path:
    """An MCAP log with two PNG frames on ``/camera/image``."""
    from foxglove.messages import CompressedImage, Timestamp
    from mcap.writer import Writer

    with path.open("wb") as fh:
        w = Writer(fh)
        w.start()
        schema = CompressedImage.get_schema().data
        sid = w.register_schema("foxglove.CompressedImage", "protobuf", schema)
        ch = w.register_channel("/camera/image", "protobuf", sid)
        for i in range(2):
            png = cv2.imencode(".png", frame(K, (-120.0, -160.0)))[1].tobytes()
            msg = CompressedImage(timestamp=Timestamp(sec=i), frame_id="camera", data=png)
            w.add_message(ch, i * 10**8, msg.encode(), i * 10**8)
        w.finish()
    return path


@pytest.mark.parametrize("window", ["inf:1", "0:inf", "1e300:1", "0:604801", "nan:1"])
@pytest.mark.parametrize("source", ["file", "emulated", "analytic"])
def test_an_unbounded_dropout_is_one_line_in_both_vision_processes(
    window: str, source: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A window must be finite and at most a week (``hal.arguments.MAX_DURATION_S``), the same
    for every source; refused before the hub is waited for or a frame is read."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    argv = ["vision", "--dropout", window, "--zenoh-endpoint", endpoint, "--wait", "0.5"]
    if source == "file":
        argv += ["--source", f"file:{_clip(tmp_path / 'clip.avi')}", "--zenoh-role", "hub"]
    elif source == "emulated":
        argv += ["--source", "emulated"]
    else:  # the analytic vision process
        (tmp_path / "rig.toml").write_text('[camera]\nmodel = "analytic"\n')
        argv += ["--config", str(tmp_path / "rig.toml")]
    code, err = hil(argv, capsys)
    assert code == 2 and err[-1].startswith("hil vision: error: --dropout must be"), err
    assert "604800" in err[-1]


def test_a_dropout_with_a_log_source_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A log is re-run offline (nothing is published, nothing to pause): ``--dropout`` with it
    is refused, as the analytic camera's options are, not silently ignored."""
    log = _image_log(tmp_path / "run.mcap")
    code, err = hil(["vision", "--source", f"log:{log}", "--dropout", "0:1"], capsys)
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("hil vision: error: --dropout") and "log:" in err[0]
    assert hil(["vision", "--source", f"log:{log}"], capsys)[0] == 0  # without it: re-run


def test_a_frame_whose_callback_failed_is_counted_in_the_stats(
    endpoint: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An exception in the frame's zenoh callback (here the pipeline failing on a blank frame)
    is the session's ``callback_errors``, in the grabber's stats (``hil vision --json``)."""
    measure = Pipeline.process

    def failing(self: Pipeline, pixels: np.ndarray) -> Measurement:
        if pixels.min() == pixels.max():
            raise RuntimeError("a bug in the pipeline")
        return measure(self, pixels)

    monkeypatch.setattr(Pipeline, "process", failing)
    out: dict = {}
    with live_grabber(RigConfig(), endpoint, out) as grabber:
        target = frame(K, (-120.0, -160.0), radius_px=20.0)
        grabber.first(target)
        grabber.send(1, np.full_like(target, 200))  # the callback fails: no answer
        grabber.send(2, target)
        assert grabber.answer(2) is not None
    stats = out["stats"]
    assert stats.callback_errors == 1 and stats.frames == 2
