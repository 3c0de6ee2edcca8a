"""``cia402.bitrate`` reaches the bus: the cia402 profile's openers (``hil cia402 check``, the
emulated drives) give it to python-can, which sets adapters that take a rate to it, and on
SocketCAN the error for a missing interface names it in the line that brings one up."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.support import REPO, run_hil
from tests.support.vcan import requires_vcan

BITRATE = 250_000
CONFIG = f'[hardware]\nprofile = "cia402"\n[cia402]\nbitrate = {BITRATE}\n'

ADAPTER = """
import sys
import can
import can.util

class RecordingAdapter(can.BusABC):
    '''An adapter that takes a bit rate (as PCAN's or Kvaser's) and is not plugged in.'''

    def __init__(self, channel=None, **kwargs):
        rate = kwargs.get("bitrate")
        raise can.CanInitializationError(f"adapter not plugged in (bitrate={rate})")

    def send(self, msg, timeout=None):
        raise can.CanOperationError("never opened")

can.interfaces.BACKENDS["hiltestadapter"] = ("__main__", "RecordingAdapter")
can.VALID_INTERFACES = can.util.VALID_INTERFACES = can.VALID_INTERFACES | {"hiltestadapter"}
from rt_controller.cli import main
sys.exit(main(sys.argv[1:]))
"""
"""``hil ARGS`` with one more python-can interface, ``hiltestadapter``."""


@pytest.mark.parametrize(
    "command",
    [["cia402", "check"], ["emulator", "--profile", "cia402", "--no-vision-link"]],
    ids=["cia402-check", "emulator"],
)
def test_the_cia402_openers_give_the_configured_bitrate_to_python_can(tmp_path, command):
    config = tmp_path / "rig.toml"
    config.write_text(CONFIG, encoding="utf-8")
    argv = [*command, "--config", str(config), "--can", "hiltestadapter:1"]
    out = subprocess.run(
        [sys.executable, "-c", ADAPTER, *argv],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert out.returncode == 2, out.stderr
    assert f"adapter not plugged in (bitrate={BITRATE})" in out.stderr
    assert "Traceback" not in out.stderr


@pytest.mark.vcan
@requires_vcan
def test_a_missing_socketcan_interface_is_brought_up_at_the_configured_bitrate(tmp_path):
    config = tmp_path / "rig.toml"
    config.write_text(CONFIG, encoding="utf-8")
    argv = ["cia402", "check", "--config", str(config), "--can", "socketcan:hilcan9"]
    out = run_hil(argv, timeout_s=120)
    assert out.returncode == 2, out.stderr
    line = f"sudo ip link set hilcan9 up type can bitrate {BITRATE} dbitrate 2000000 fd on"
    assert line in out.stderr
