"""Camera frames signed with another rig key: rejected as ``bad_mac`` (the features link's
word), not as ``malformed``; said once on stderr, naming where the key comes from, and counted
in the end line."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from hal.camera_frame import encode_frame
from hal.zenoh_session import KEY_CAMERA_FRAME, free_loopback_port, open_session
from rt_controller.cli import main
from tests.support.synthetic_frames import frame
from vision.grabber import Grabber
from vision.intrinsics import Intrinsics
from vision.pipeline import Pipeline
from vision.sources import EmulatedSource

K = Intrinsics(640, 480, 1230.0, 1230.0, 320.0, 240.0)
KEY, OTHER = b"k" * 32, b"o" * 32


def payload(seq: int, key: bytes) -> bytes:
    pixels = frame(K, (-120.0 + seq, -160.0))
    return encode_frame(
        pixels,
        seq=seq,
        stamp_ns=seq,
        sim_time_ns=20_000_000 * seq,
        exposure_ns=0,
        period=seq,
        lockstep=True,
        key=key,
    )


class FakeSession:
    """Hands the subscriber's callback to the test, as ZenohSession.subscribe calls it."""

    def __init__(self) -> None:
        self.callback = None
        self.subscribed = threading.Event()

    def subscribe(self, key, cb):
        self.callback = cb
        self.subscribed.set()
        return self

    def publisher(self, key, **kw):
        return self

    def put(self, data: bytes) -> None:
        pass

    def undeclare(self) -> None:
        pass


def test_frames_of_another_rig_key_are_bad_mac_and_said_once(capsys: pytest.CaptureFixture[str]):
    session, sent = FakeSession(), []
    source = EmulatedSource(session, KEY)
    g = Grabber(Pipeline(K), sent.append, source_id=1)
    stop = threading.Event()
    t = threading.Thread(target=source.run, args=(g.on_frame, g.on_reject, stop))
    t.start()
    assert session.subscribed.wait(10)
    for seq in range(3):
        session.callback(payload(seq, OTHER))
    session.callback(b"HC\x02")  # no frame at all: still malformed
    session.callback(payload(3, KEY))
    stop.set()
    t.join()
    rejected = g.snapshot().pipeline["rejected"]
    assert (rejected["bad_mac"], rejected["malformed"]) == (3, 1)
    assert source.decoder.as_dict()["bad_mac"] == 3
    err = capsys.readouterr().err
    assert err.count("another rig key") == 1 and "--key-file" in err
    assert [m.frame for m in sent] == [3]  # the rig's own frame still passes


def test_hil_vision_with_another_key_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    """``hil vision --key-file other.key`` against a camera signing with another key: one
    warning on stderr, the count in the end line, ``bad_mac`` in ``--json``-less output."""
    assert main(["keygen", str(tmp_path / "other.key")]) == 0
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    done = threading.Event()

    def camera() -> None:  # the emulator's camera, signing with its own key
        with open_session(listen=False, endpoint=endpoint) as s:
            pub = s.publisher(KEY_CAMERA_FRAME)
            seq = 0
            while not done.wait(0.02):
                pub.put(payload(seq, OTHER))
                seq += 1

    th = threading.Thread(target=camera)
    th.start()
    try:
        argv = ["vision", "--source", "emulated", "--zenoh-role", "hub", "--duration", "3"]
        argv += ["--zenoh-endpoint", endpoint, "--key-file", str(tmp_path / "other.key")]
        assert main(argv) == 0
    finally:
        done.set()
        th.join(20)
    out, err = capsys.readouterr()
    assert err.count("signed with another rig key") == 1
    assert "--key-file" in err and "HIL_KEY_FILE" in err
    end = out.strip().splitlines()[-1]
    assert "malformed" not in end
    n = int(end.split(" dropped as bad_mac")[0].rsplit(" ", 1)[1])
    assert n > 0
