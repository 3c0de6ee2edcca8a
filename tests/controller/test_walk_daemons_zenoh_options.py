"""The daemons and the live tools (``hil emulator``, ``controller``, ``vision``, ``monitor``,
``param``) given both ``--zenoh-endpoint`` and ``--zenoh-config`` refuse the pair (exit 2, one
line): the config file sets its own endpoints, and the endpoint given was silently ignored."""

from __future__ import annotations

from pathlib import Path

import pytest

from hal.bus import isolated_spec
from tests.support import free_endpoint, run_hil

SCOUTING = "scouting: { multicast: { enabled: false }, gossip: { enabled: false } }"


@pytest.mark.parametrize("command", ["emulator", "controller", "vision", "monitor", "param"])
def test_endpoint_and_config_file_together_are_refused(tmp_path: Path, command: str) -> None:
    key = tmp_path / "rig.key"
    assert run_hil(["keygen", str(key)], timeout_s=60).returncode == 0
    zcfg = tmp_path / "client.json5"
    zcfg.write_text(
        f'{{ mode: "client", connect: {{ endpoints: ["{free_endpoint()}"] }}, {SCOUTING} }}\n'
    )
    args = [command, "--key-file", str(key)]
    args += ["get", "gains.kp"] if command == "param" else ["--duration", "0.1"]
    args += ["--zenoh-endpoint", free_endpoint(), "--zenoh-config", str(zcfg)]
    if command in ("emulator", "controller"):
        args += ["--can", isolated_spec("udp_multicast")]
    if command == "controller":
        args += ["--log", str(tmp_path / "run.mcap")]
    if command == "vision":
        args += ["--wait", "0"]
    done = run_hil(args, timeout_s=180)
    assert done.returncode == 2, (done.returncode, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0] == (
        f"hil {command}: error: --zenoh-endpoint and --zenoh-config: give one "
        "(a zenoh config file sets its own endpoints)"
    ), lines
    assert not (tmp_path / "run.mcap").exists()
