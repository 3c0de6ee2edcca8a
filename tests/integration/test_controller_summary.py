"""``hil controller`` run alone prints its summary as ``hil up`` does: ``can`` names the bus it
opened (not ``auto``), and the outages, recorder and rejections blocks are in words, not
Python dicts."""

from __future__ import annotations

import os
import subprocess

import pytest

from hal.bus import isolated_spec
from tests.support import REPO, free_endpoint, hil_command, start_hil, stop_hil

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]


def test_a_lone_controller_names_its_bus_and_words_its_counters(tmp_path) -> None:
    can, ep = isolated_spec("udp_multicast"), free_endpoint()
    group_port = can.partition(":")[2]
    common = ["--zenoh-endpoint", ep, "--key-file", os.environ["HIL_KEY_FILE"]]
    emulator = start_hil(["emulator", "--can", can, *common])
    vision = start_hil(["vision", *common, "--wait", "60"])
    # no --can: transport.can = auto, here python-can's configuration (the isolated bus)
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    env.update(CAN_INTERFACE="udp_multicast", CAN_CHANNEL=group_port, COLUMNS="200")
    try:
        args = ["controller", *common, "--no-rt", "--duration", "1"]
        ctl = subprocess.run(
            [*hil_command(), *args, "--log", str(tmp_path / "run.mcap")],
            capture_output=True,
            text=True,
            timeout=180,
            cwd=REPO,
            env=env,
        )
    finally:
        stop_hil(vision)
        stop_hil(emulator)
    assert ctl.returncode == 0, ctl.stderr
    rows = {
        cells[1].strip(): cells[2].strip()
        for line in ctl.stdout.splitlines()
        if len(cells := line.split("│")) == 4
    }
    assert rows["can"] == can, rows
    assert rows["outages"].startswith("0 (longest"), rows
    for block in ("recorder", "rejections"):
        assert "{" not in rows[block], rows
