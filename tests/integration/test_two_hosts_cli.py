"""docs/tutorials/two-hosts.md, walked on loopback: options that a ``--zenoh-config`` file
makes meaningless must be refused in one line rather than ignored, and a TLS file the json5
names that is not there must be named, not reported as an unreachable hub. All endpoints are
``127.0.0.1`` on a free port with scouting off; nothing listens for long.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hal.bus import isolated_spec
from hal.secoc import load_key_file, write_key_file
from hal.vision_codec import FeatureMsg, encode_features
from hal.zenoh_session import KEY_FEATURES, free_loopback_port, open_session
from tests.support import run_hil

pytestmark = pytest.mark.integration

SCOUTING = "scouting: { multicast: { enabled: false }, gossip: { enabled: false } }"


def hil(*args: str) -> subprocess.CompletedProcess:
    return run_hil(list(args), timeout_s=120.0)


def client_config(tmp_path: Path, tls: str = "") -> Path:
    """A client json5 (the page's ``client.json5``) connecting to a port nobody listens on."""
    proto = "tls" if tls else "tcp"
    path = tmp_path / "client.json5"
    path.write_text(
        f'{{ mode: "client", connect: {{ endpoints: ["{proto}/127.0.0.1:{free_loopback_port()}"] '
        f"}}, {SCOUTING}, {tls} }}\n"
    )
    return path


def vision_on_a_client_file(tmp_path: Path, *extra: str, tls: str = "") -> tuple[str, int]:
    """``hil vision --zenoh-config`` a client file (``tls``: its TLS section) with ``extra``
    options, for 1 s on a fresh rig key: its stderr (no traceback in it) and exit status."""
    key = str(write_key_file(tmp_path / "rig.key"))
    config = str(client_config(tmp_path, tls))
    done = hil("vision", "--zenoh-config", config, *extra, "--key-file", key, "--duration", "1")
    return one_line_error(done), done.returncode


def one_line_error(done: subprocess.CompletedProcess) -> str:
    err = done.stderr
    assert "Traceback" not in err, err
    return err


def test_zenoh_role_with_a_zenoh_config_is_not_silently_ignored(tmp_path: Path) -> None:
    """The file sets the mode and the listen endpoints: ``--zenoh-role hub`` cannot make a
    client file listen, and was ignored without a word (the run went on as a client)."""
    err, status = vision_on_a_client_file(tmp_path, "--zenoh-role", "hub")
    assert status == 2, err
    assert "--zenoh-role" in err, err


def test_wait_with_a_zenoh_config_is_not_silently_ignored(tmp_path: Path) -> None:
    """``--wait 5`` with a client file and no hub yet: either honoured (the error says it
    waited 5 s) or refused naming ``--wait``; it gave up at once with zenoh's own words."""
    err, status = vision_on_a_client_file(tmp_path, "--wait", "5")
    assert status != 0, err
    assert "--wait" in err or "after 5 s" in err, err


def test_missing_tls_file_of_a_client_config_is_named(tmp_path: Path) -> None:
    """The page's client.json5 run from a folder without ca.pem/client.key/client.pem (the
    paths are relative to the working directory): the error named no file, only
    "Unable to connect to any of [...]", the same words as a hub that is down."""
    tls = (
        'transport: { link: { tls: { root_ca_certificate: "ca.pem", enable_mtls: true, '
        'connect_private_key: "client.key", connect_certificate: "client.pem" } } }'
    )
    err, status = vision_on_a_client_file(tmp_path, tls=tls)
    assert status != 0, err
    assert "ca.pem" in err, err


def test_hil_up_refuses_a_zenoh_config_file(tmp_path: Path) -> None:
    """``hil up`` runs the three processes on one host over loopback; a rig config with
    ``transport.zenoh_config`` handed the one file to all three, so the second to listen died
    with "Address already in use" (exit 2 from the emulator, after processes had started)."""
    key = str(write_key_file(tmp_path / "rig.key"))
    hub = tmp_path / "hub.json5"
    hub.write_text(
        f'{{ mode: "router", listen: {{ endpoints: ["tcp/127.0.0.1:{free_loopback_port()}"] }}, '
        f"{SCOUTING} }}\n"
    )
    rig = tmp_path / "rig.toml"
    rig.write_text(f'[transport]\nzenoh_config = "{hub}"\n')
    done = hil(
        "up",
        "--config",
        str(rig),
        "--key-file",
        key,
        "--can",
        isolated_spec("udp_multicast"),
        "--duration",
        "2",
    )
    err = one_line_error(done)
    assert done.returncode == 2, err
    assert "transport.zenoh_config" in err, err


def test_future_feature_stamps_are_not_blamed_on_ntp(tmp_path: Path) -> None:
    """A camera on another host (``hil vision --source v4l2:...`` on the camera PC) stamps its
    features with that host's CLOCK_MONOTONIC, which PTP/NTP never align across hosts, and the
    controller refuses stamps more than controller.max_clock_skew_s (5 ms) ahead. Its start-up
    error said "is the sender's clock within 1 s of this host's? (PTP/NTP)": the wrong window
    and a remedy that cannot work. Here a publisher on loopback plays that camera (stamps one
    hour ahead, signed with the rig key) next to a real emulator and controller."""
    key_path = write_key_file(tmp_path / "rig.key")
    key = load_key_file(key_path)
    can = isolated_spec("udp_multicast")
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    emu = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "rt_controller.cli",
            "emulator",
            "--can",
            can,
            "--key-file",
            str(key_path),
            "--no-vision-link",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        stdin=subprocess.DEVNULL,
    )
    stop = threading.Event()
    try:
        with open_session(listen=True, endpoint=endpoint) as hub:
            pub = hub.publisher(KEY_FEATURES)

            def camera_of_another_host() -> None:
                frame = 0
                while not stop.wait(0.02):
                    frame += 1
                    ahead_ns = time.monotonic_ns() + 3600 * 10**9
                    pub.put(encode_features(FeatureMsg(frame, ahead_ns, 0, 0, (1.0, 2.0)), key))

            camera = threading.Thread(target=camera_of_another_host, daemon=True)
            camera.start()
            try:
                done = hil(
                    "controller",
                    "--can",
                    can,
                    "--zenoh-endpoint",
                    endpoint,
                    "--key-file",
                    str(key_path),
                    "--duration",
                    "2",
                    "--log",
                    str(tmp_path / "run.mcap"),
                )
            finally:
                stop.set()
                camera.join()
    finally:
        emu.terminate()
        try:
            emu.wait(20)
        except subprocess.TimeoutExpired:
            emu.kill()
            emu.wait()
    err = one_line_error(done)
    assert done.returncode != 0, err
    assert "future_stamp" in err, err  # the case at hand: features refused as from the future
    assert "within 1 s" not in err, err
    assert "monotonic" in err.lower(), err
