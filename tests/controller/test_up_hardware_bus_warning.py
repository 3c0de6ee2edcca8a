"""``hil up`` and ``hil experiment`` always start the emulated DSP: given a bus that may hold
hardware (a vendor adapter, a SocketCAN interface that is not ``vcan``), they warn that a real
DSP there would be a second DSP; the host-local buses get no warning."""

from __future__ import annotations

import pytest

from hal.bus import resolve_spec
from rt_controller.cli import main
from rt_controller.rig.options import emulator_bus_warning


@pytest.mark.parametrize("spec", ["socketcan:can0", "pcan:PCAN_USBBUS1", "kvaser:0"])
def test_a_bus_with_hardware_is_warned_of(spec: str) -> None:
    warning = emulator_bus_warning(resolve_spec(spec))
    assert warning is not None and "two DSPs" in warning and spec.split(":")[0] in warning


@pytest.mark.parametrize("spec", ["socketcan:vcan0", "udp_multicast", "virtual:x"])
def test_a_host_local_bus_is_not(spec: str) -> None:
    assert emulator_bus_warning(resolve_spec(spec)) is None


def test_hil_up_says_it_before_anything_starts(capsys) -> None:
    # a run of no tick is refused after the warning: nothing starts
    assert main(["up", "--can", "socketcan:can0", "--duration", "0.001"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hil up: warning: socketcan:can0 may be a bus with hardware"), err
