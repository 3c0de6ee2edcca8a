"""``cia402.bitrate`` reaches the bus: the cia402 profile's openers (``hil cia402 check``, the
emulated drives) give it to python-can, which sets adapters that take a rate to it, and on
SocketCAN the error for a missing interface names it in the line that brings one up."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import can
import pytest

from hal.bus import open_bus
from hal.errors import HalTransportError
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
    assert f"sudo ip link set hilcan9 up type can bitrate {BITRATE}" in out.stderr
    assert "fd on" not in out.stderr  # CANopen's frames are classic


@pytest.fixture
def classic_can():
    """A SocketCAN interface of MTU 16 (a classic adapter), made for the test (root, vcan)."""
    name = "hilc16"
    ip = shutil.which("ip")
    if ip is None or os.geteuid() != 0:
        pytest.skip("needs root and iproute2 to make a vcan interface")
    subprocess.run([ip, "link", "add", "dev", name, "type", "vcan"], check=True)
    try:
        subprocess.run([ip, "link", "set", name, "mtu", "16"], check=True)
        subprocess.run([ip, "link", "set", "up", name], check=True)
        yield name
    finally:
        subprocess.run([ip, "link", "del", name], check=False)


@pytest.mark.vcan
@requires_vcan
def test_the_cia402_profile_opens_a_classic_can_interface(classic_can):
    """CANopen drives sit on classic adapters: the cia402 openers pass ``fd=False``, which
    opens an interface of MTU 16 that the DSP profile (CAN FD frames) refuses."""
    with pytest.raises(HalTransportError, match="MTU 16"):
        open_bus(f"socketcan:{classic_can}")
    frame = can.Message(arbitration_id=0x601, data=bytes(8), is_extended_id=False)
    with open_bus(f"socketcan:{classic_can}", fd=False) as bus:
        bus.send(frame)
