"""0x60C2 (interpolation time period) has one encoder: the emulated drives boot with the value
the cia402 master writes, and a control rate it cannot write exactly (60 Hz) is a one-line
configuration error of the emulator and of any cia402 configuration, before anything opens."""

from __future__ import annotations

import subprocess

import pytest

from hal.bus import isolated_spec
from hal.cia402_master.units import interpolation_period
from hal.config import load_config
from hal.errors import HalConfigError
from tests.support import run_hil
from tests.support.cia402 import drives_on_virtual_bus

RATE_60 = "[rates]\ncontrol_hz = 60\nphysics_hz = 960\nstate_hz = 960\n"
"""A valid dsp configuration whose period, 16.67 ms, has no exact 0x60C2 form."""


@pytest.mark.parametrize("rate_hz", [50.0, 100.0, 250.0, 1000.0])
def test_the_drives_boot_with_the_period_the_master_writes(rate_hz):
    cfg = load_config().with_overrides({"rates.control_hz": rate_hz})
    written = interpolation_period(1.0 / rate_hz)
    with drives_on_virtual_bus(cfg) as bench:
        for drive in bench.rig.drives:
            booted = (drive.sdo[0x60C2][1].raw, drive.sdo[0x60C2][2].raw)
            assert booted == written


def test_a_cia402_configuration_refuses_a_rate_0x60c2_cannot_carry(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(RATE_60, encoding="utf-8")
    assert load_config(path).rates.control_hz == 60.0  # the dsp profile takes it
    path.write_text(RATE_60 + '[hardware]\nprofile = "cia402"\n', encoding="utf-8")
    with pytest.raises(HalConfigError, match=r"rates\.control_hz: 60 Hz .*0x60C2"):
        load_config(path)


def test_the_cia402_emulator_refuses_a_rate_0x60c2_cannot_carry_in_one_line(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(RATE_60, encoding="utf-8")
    argv = ["emulator", "--profile", "cia402", "--config", str(path), "--no-vision-link"]
    try:
        out = run_hil([*argv, "--can", isolated_spec("udp_multicast")], timeout_s=120)
    except subprocess.TimeoutExpired:
        pytest.fail("the emulator served drives at 60 Hz instead of refusing the rate")
    assert out.returncode == 2, out.stderr
    assert out.stderr.startswith("hil emulator: error: ")
    assert "rates.control_hz: 60 Hz" in out.stderr and "0x60C2" in out.stderr
    assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert "serving" not in out.stderr
