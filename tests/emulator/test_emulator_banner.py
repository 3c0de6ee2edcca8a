"""The ``hil emulator`` banner names the zenoh endpoint the other processes must reach, also
when the session comes from a ``--zenoh-config`` file (not the file's name alone)."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest

from hal.bus import isolated_spec
from hal.zenoh_session import free_loopback_port
from tests.support.emulator_proc import emulator, stop_emulator

pytestmark = pytest.mark.integration


def test_banner_names_the_listen_endpoint_of_a_zenoh_config_file(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    hub = tmp_path / "hub.json5"
    scouting = "scouting: { multicast: { enabled: false }, gossip: { enabled: false } }"
    listen = json.dumps({"endpoints": [endpoint]})
    hub.write_text(f'{{ mode: "router", listen: {listen}, {scouting} }}\n')
    spec = isolated_spec("udp_multicast")
    with emulator(spec, "--zenoh-config", str(hub), "--no-camera") as emu:
        banner = next(line for line in emu.err if "serving the arm on" in line)
        stop_emulator(emu, signal.SIGTERM)
    assert f"camera poses on zenoh {endpoint} (listen endpoints of {hub})" in banner, banner
