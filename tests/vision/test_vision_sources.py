"""Frame sources behind one interface: a video file through cv2.VideoCapture (written here with
cv2.VideoWriter), a log's recorded frames, the emulated camera's zenoh payloads (good, corrupted,
mis-sized), and the grabber's answer to each frame."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from hal.camera_frame import CameraFrame, encode_frame
from hal.errors import HalConfigError
from hal.vision_codec import FeatureMsg
from tests.support.synthetic_frames import frame, write_image_log
from vision.grabber import Grabber
from vision.intrinsics import Intrinsics
from vision.pipeline import Pipeline
from vision.sources import EmulatedSource, check_source, open_source, parse_source

K = Intrinsics(640, 480, 1230.0, 1230.0, 320.0, 240.0)
PATH_F = [(-120.0 + 10 * i, -160.0 + 8 * i) for i in range(8)]
KEY = b"k" * 32


def grabber(sent: list[FeatureMsg]) -> Grabber:
    return Grabber(Pipeline(K), sent.append, source_id=7)


def test_video_file_through_videocapture(tmp_path: Path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480))
    assert writer.isOpened()
    for f in PATH_F:
        writer.write(cv2.cvtColor(frame(K, f, radius_px=14.0), cv2.COLOR_GRAY2BGR))
    writer.release()
    sent: list[FeatureMsg] = []
    g = grabber(sent)
    open_source(f"file:{path}").run(g.on_frame, g.on_reject, threading.Event())
    assert len(sent) == len(PATH_F)
    assert [m.frame for m in sent] == list(range(len(PATH_F)))
    assert all(m.valid and not m.lockstep for m in sent)
    err = np.array([np.subtract(m.f, f) for m, f in zip(sent, PATH_F, strict=True)])
    assert np.abs(err).max() < 0.3  # MJPEG's compression, measured 0.05 px


def test_a_missing_file_is_a_one_line_error(tmp_path: Path):
    with pytest.raises(HalConfigError, match="no such file"):
        open_source(f"file:{tmp_path / 'nope.mp4'}").run(
            lambda fr: None, lambda r: None, threading.Event()
        )


def test_an_image_sequence_through_videocapture(tmp_path: Path):
    (tmp_path / "views").mkdir()
    for i, f in enumerate(PATH_F):
        cv2.imwrite(str(tmp_path / "views" / f"view-{i:03d}.png"), frame(K, f, radius_px=14.0))
    sent: list[FeatureMsg] = []
    g = grabber(sent)
    spec = f"file:{tmp_path / 'views' / 'view-%03d.png'}"
    open_source(spec).run(g.on_frame, g.on_reject, threading.Event())
    assert [m.frame for m in sent] == list(range(len(PATH_F)))
    assert all(m.valid for m in sent)


@pytest.mark.parametrize(
    ("names", "pattern", "said"),
    [
        ([], "view-%03d.png", "no file matches the image sequence"),
        (["view-007.png"], "view-%03d.png", "numbered from 7"),
        (["view-1.png"], "missing/view-%d.png", "no such folder"),
    ],
)
def test_an_image_sequence_that_cannot_play_is_one_line(
    tmp_path: Path, names: list[str], pattern: str, said: str
):
    for name in names:
        cv2.imwrite(str(tmp_path / name), np.zeros((8, 8), np.uint8))
    with pytest.raises(HalConfigError, match=said):
        check_source(f"file:{tmp_path / pattern}")


@pytest.mark.parametrize("spec", ["usb0", "file:", "emulated:x", "log"])
def test_bad_source_specs(spec: str):
    with pytest.raises(HalConfigError, match="--source"):
        parse_source(spec)


def test_log_frames_are_re_run(tmp_path: Path):
    images = [frame(K, f) for f in PATH_F]
    path = write_image_log(tmp_path / "run.mcap", images, tail=b"\x00garbage")
    sent: list[FeatureMsg] = []
    g = grabber(sent)
    open_source(f"log:{path}").run(g.on_frame, g.on_reject, threading.Event())
    assert len(sent) == len(PATH_F)
    err = np.array([np.subtract(m.f, f) for m, f in zip(sent, PATH_F, strict=True)])
    assert np.abs(err).max() < 0.02  # PNG is lossless
    assert g.snapshot().pipeline["rejected"]["malformed"] == 1


class FakeSession:
    """Delivers payloads to the subscriber the way ZenohSession.subscribe does."""

    def __init__(self) -> None:
        self.callback = None
        self.sent: list[bytes] = []

    def subscribe(self, key, cb):
        self.callback = cb
        return self

    def publisher(self, key, **kw):
        return self

    def put(self, payload: bytes) -> None:
        self.sent.append(payload)

    def undeclare(self) -> None:
        pass


def test_emulated_frames_good_corrupted_and_mis_sized():
    session = FakeSession()
    source = EmulatedSource(session, KEY)
    sent: list[FeatureMsg] = []
    g = grabber(sent)
    stop = threading.Event()
    t = threading.Thread(target=source.run, args=(g.on_frame, g.on_reject, stop))
    t.start()
    while session.callback is None:
        pass

    def payload(pixels, seq, period, lockstep=True):
        return encode_frame(
            pixels,
            seq=seq,
            stamp_ns=1000 + seq,
            sim_time_ns=20_000_000 * seq,
            exposure_ns=2_000_000,
            period=period,
            lockstep=lockstep,
            key=KEY,
        )

    good = payload(frame(K, (-120.0, -160.0)), 0, 0)
    session.callback(good)
    session.callback(good)  # the period re-sent: answered again, not detected again
    corrupted = bytearray(payload(frame(K, (-110.0, -150.0)), 1, 1))
    corrupted[5000] ^= 0xFF
    session.callback(bytes(corrupted))
    session.callback(b"HC\x01")
    session.callback(payload(np.zeros((240, 320), np.uint8), 2, 2))
    session.callback(payload(frame(K, (-100.0, -140.0)), 3, 3))
    stop.set()
    t.join()
    assert [(m.frame, m.pose_seq, m.valid) for m in sent] == [
        (0, 0, True),
        (0, 0, True),
        (2, 2, False),
        (3, 3, True),
    ]
    assert sent[0] == sent[1] and sent[0].lockstep and sent[0].source == 7
    assert sent[0].sim_time_ns == 0 and sent[3].sim_time_ns == 60_000_000
    assert np.allclose(sent[3].f, (-100.0, -140.0), atol=0.02)
    s = g.snapshot()
    assert s.reanswers == 1 and s.frames == 3 and s.invalid == 1
    assert s.pipeline["rejected"]["malformed"] == 1  # the 3-byte payload
    assert s.pipeline["rejected"]["bad_mac"] == 1  # the corrupted frame
    assert s.pipeline["rejected"]["wrong_size"] == 1
    rx = source.decoder.as_dict()
    assert rx["bad_mac"] == 1 and rx["bad_size"] == 1 and rx["resent"] == 1


def test_an_invalid_frame_is_answered_invalid():
    sent: list[FeatureMsg] = []
    g = grabber(sent)
    fr = CameraFrame(5, 123, 456, 1, 9, np.full((480, 640), 200, np.uint8), lockstep=True)
    msg = g.on_frame(fr)
    assert msg == FeatureMsg(5, 123, 456, 9, (0.0, 0.0), False, True, 7)
    assert sent == [msg]


def test_a_dropout_answers_lockstep_invalid_and_skips_realtime():
    from vision.grabber import Dropout

    sent: list[FeatureMsg] = []
    g = Grabber(Pipeline(K), sent.append, source_id=7, dropouts=[Dropout.parse("1:0.5")])
    img = frame(K, (-120.0, -160.0))
    for i, sim_ns in enumerate((900_000_000, 1_000_000_000, 1_499_999_999, 1_500_000_000)):
        g.on_frame(CameraFrame(i, i, sim_ns, 1, i, img, lockstep=True))
    assert [m.valid for m in sent] == [True, False, False, True]
    rt = g.on_frame(CameraFrame(9, 9, 1_200_000_000, 1, 9, img, lockstep=False))
    assert rt is None and len(sent) == 4
    s = g.snapshot()
    assert (s.dropout_answers, s.dropout_frames, s.dropouts) == (2, 1, ["1:0.5"])


@pytest.mark.parametrize("bad", ["0.5", "1:-2", "x:1", "-1:1"])
def test_a_bad_dropout_is_one_clear_line(bad):
    from vision.grabber import Dropout

    with pytest.raises(HalConfigError, match="--dropout must be START:DURATION"):
        Dropout.parse(bad)


def test_a_live_file_plays_at_its_frame_rate(tmp_path: Path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (640, 480))
    for f in PATH_F[:5]:
        writer.write(cv2.cvtColor(frame(K, f, radius_px=14.0), cv2.COLOR_GRAY2BGR))
    writer.release()
    stamps: list[int] = []
    open_source(f"file:{path}", live=True).run(
        lambda fr: stamps.append(fr.stamp_ns), lambda r: None, threading.Event()
    )
    # paced at 20 fps: frame k is read no earlier than k / 20 s after the first (a lower bound
    # holds under any scheduling)
    assert len(stamps) == 5 and stamps[-1] - stamps[0] >= 4 * 50_000_000 - 1_000_000


def _image_log(path: Path, n: int = len(PATH_F)) -> Path:
    """A log of ``n`` PNG frames on /camera/image, each in its own chunk."""
    return write_image_log(path, [frame(K, f) for f in PATH_F[:n]], chunk_size=1)


def test_a_log_whose_frames_none_decodes_is_refused(tmp_path: Path):
    """As a file OpenCV cannot read: one line, not an exit 0 over 0 measured frames."""
    from mcap.writer import Writer

    path = tmp_path / "damaged.mcap"
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start()
        ch = w.register_channel("/camera/image", "protobuf", 0)
        for i in range(3):
            w.add_message(ch, i * 10**8, b"\x00garbage", i * 10**8)
        w.finish()
    g = grabber([])
    with pytest.raises(HalConfigError, match="none of its 3 /camera/image frames"):
        open_source(f"log:{path}").run(g.on_frame, g.on_reject, threading.Event())
    assert g.snapshot().pipeline["rejected"]["malformed"] == 3


def test_a_cut_log_gives_the_frames_of_its_complete_chunks(tmp_path: Path):
    path = _image_log(tmp_path / "run.mcap")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 3 // 4])  # the recorder killed: no summary, no footer
    sent: list[FeatureMsg] = []
    g = grabber(sent)
    open_source(f"log:{path}").run(g.on_frame, g.on_reject, threading.Event())
    assert 0 < len(sent) < len(PATH_F)


def test_a_log_without_frames_and_a_directory_are_refused(tmp_path: Path):
    path = _image_log(tmp_path / "none.mcap", n=0)
    g = grabber([])
    with pytest.raises(HalConfigError, match="has no /camera/image frames"):
        open_source(f"log:{path}").run(g.on_frame, g.on_reject, threading.Event())
    with pytest.raises(HalConfigError, match="is a directory"):
        open_source(f"log:{tmp_path}").run(g.on_frame, g.on_reject, threading.Event())


def test_a_cut_log_is_said_to_be_cut(tmp_path: Path):
    from hal.config import RigConfig
    from vision.process import run_offline

    path = _image_log(tmp_path / "run.mcap")
    said: list[str] = []
    run_offline(RigConfig(), f"log:{path}", notice=said.append)
    assert said == []  # a whole log: nothing to say
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 3 // 4])  # the recorder killed: no summary, no footer
    stats = run_offline(RigConfig(), f"log:{path}", notice=said.append)
    assert len(said) == 1 and str(path) in said[0], said
    assert f"ends after {stats.frames} /camera/image frames in a cut" in said[0], said
