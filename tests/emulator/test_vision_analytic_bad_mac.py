"""The analytic vision process (``camera.model = "analytic"``) given another rig key than the
emulator's: its camera poses are ``bad_mac`` and said as the image path says its frames
(``tests/vision/test_vision_bad_mac.py``): once on stderr, naming where the key comes from, and
counted apart in the end line, not among the malformed poses."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from hal.config import RigConfig
from hal.secoc import load_key_file
from hal.vision_codec import encode_pose
from hal.zenoh_session import KEY_CAMERA_POSE, free_loopback_port, open_session
from rt_controller.cli import main
from tests.support.poses import PERIOD, pose_msg

OTHER = b"o" * 32


def test_analytic_hil_vision_with_another_key_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Poses signed with another key: one warning, their count in the end line as bad_mac;
    a payload that is no pose at all stays a rejected (malformed) pose; the rig's own pass."""
    config = tmp_path / "analytic.toml"
    config.write_text('[camera]\nmodel = "analytic"\n')
    assert main(["keygen", str(tmp_path / "rig.key")]) == 0
    own = load_key_file(tmp_path / "rig.key")
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    done, cfg = threading.Event(), RigConfig()

    def emulator() -> None:  # poses signed with another key, a malformed one, then its own
        with open_session(listen=False, endpoint=endpoint) as s:
            pub, seq = s.publisher(KEY_CAMERA_POSE), 1
            while not done.wait(0.02):
                pose = pose_msg(cfg, seq, seq * PERIOD, lockstep=False)
                pub.put(encode_pose(pose, OTHER if seq % 3 else own) if seq % 5 else b"HP\x03")
                seq += 1

    th = threading.Thread(target=emulator)
    th.start()
    try:
        argv = ["vision", "--config", str(config), "--zenoh-role", "hub", "--duration", "3"]
        argv += ["--zenoh-endpoint", endpoint, "--key-file", str(tmp_path / "rig.key")]
        assert main(argv) == 0
    finally:
        done.set()
        th.join(20)
    out, err = capsys.readouterr()
    assert err.count("camera poses are signed with another rig key") == 1
    assert "--key-file" in err and "HIL_KEY_FILE" in err
    end = out.strip().splitlines()[-1]
    poses = int(end.split(" poses, ")[0].rsplit(" ", 1)[1])
    bad_mac = int(end.split(" dropped as bad_mac (another rig key)")[0].rsplit(" ", 1)[1])
    rejected = int(end.split(" poses rejected")[0].rsplit(" ", 1)[1])
    assert poses > 0 and bad_mac > poses and 0 < rejected < bad_mac
