"""The one line a lab engineer gets when a real CAN adapter cannot be opened (via the CLI)."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import can
import pytest

from hal.bus import open_bus
from hal.errors import HalTransportError

ROOT = Path(__file__).resolve().parents[2]
HIL = [sys.executable, "-m", "rt_controller.cli"]


def _has_af_can() -> bool:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (AttributeError, OSError):
        return False
    return True


def _emulator_error(spec: str, tmp_path: Path) -> str:
    key = tmp_path / "rig.key"
    subprocess.run([*HIL, "keygen", str(key)], check=True, capture_output=True, cwd=ROOT)
    cmd = [*HIL, "emulator", "--can", spec, "--key-file", str(key)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode != 0
    assert "Traceback" not in done.stderr
    lines = [line for line in done.stderr.splitlines() if "error:" in line]
    assert len(lines) == 1, done.stderr
    return lines[0]


@pytest.mark.skipif(_has_af_can(), reason="this kernel has SocketCAN")
def test_a_real_socketcan_adapter_on_a_kernel_without_socketcan_is_not_sent_to_udp(
    tmp_path: Path,
) -> None:
    """udp_multicast is host-local: it cannot reach a real DSP on can0, so the line for a real
    adapter says how to get SocketCAN, not to use udp_multicast instead."""
    line = _emulator_error("socketcan:can0", tmp_path)
    assert "modprobe can_raw" in line
    assert "use --can udp_multicast instead" not in line


def test_pcan_without_its_library_names_the_library(tmp_path: Path) -> None:
    pcan = pytest.importorskip("can.interfaces.pcan.basic")
    try:
        pcan.PCANBasic()
    except OSError:
        pass
    else:  # pragma: no cover - PCAN-Basic installed here
        pytest.skip("PCAN-Basic is installed")
    line = _emulator_error("pcan:PCAN_USBBUS1", tmp_path)
    assert "vendor library" in line and "PCAN-Basic" in line
    assert ".;" not in line


def test_a_real_adapter_that_is_down_is_told_its_bit_rates(tmp_path: Path, monkeypatch) -> None:
    """`ip link set up can0` alone fails on a CAN adapter whose bit rates were never set: the line
    for a real adapter that is down gives the whole bring-up line (vcan: `set up` is enough)."""
    import errno

    import can

    import hal.bus
    from hal.bus import open_bus
    from hal.errors import HalTransportError

    for name in ("can0", "vcan5"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "mtu").write_text("72\n")

    def down(**_kw):
        raise OSError(errno.ENETDOWN, "Network is down")

    monkeypatch.setattr(hal.bus, "SYS_CLASS_NET", tmp_path)
    monkeypatch.setattr(can, "Bus", down)
    with pytest.raises(HalTransportError) as info:
        open_bus("socketcan:can0")
    assert "sudo ip link set can0 up type can bitrate 1000000 dbitrate 2000000 fd on" in str(
        info.value
    )
    with pytest.raises(HalTransportError, match=r"sudo ip link set up vcan5$"):
        open_bus("socketcan:vcan5")


class _Adapter(can.BusABC):
    """A vendor adapter as python-can opens it, in the protocol python-can's options gave."""

    def __init__(self, channel: str, protocol: can.CanProtocol, **kwargs) -> None:
        super().__init__(channel)
        self._can_protocol = protocol
        self.kwargs, self.shut = kwargs, False

    def send(self, msg, timeout=None) -> None:
        pass

    def _recv_internal(self, timeout):
        return None, False

    def shutdown(self) -> None:
        self.shut = True
        super().shutdown()


def _opened_as(monkeypatch, protocol: can.CanProtocol) -> list[_Adapter]:
    opened: list[_Adapter] = []

    def bus(interface: str, channel: str, **kwargs):
        opened.append(_Adapter(channel, protocol, **kwargs))
        return opened[-1]

    monkeypatch.setattr(can, "Bus", bus)
    return opened


def test_an_adapter_opened_in_classic_can_is_refused_for_the_dsp_s_fd_frames(monkeypatch):
    """pcan/kvaser open in classic CAN unless python-can's configuration sets fd: the DSP's
    16-byte frames could never be sent, so the open says where FD goes (and shuts the bus)."""
    opened = _opened_as(monkeypatch, can.CanProtocol.CAN_20)
    with pytest.raises(HalTransportError, match="opened in classic CAN") as info:
        open_bus("pcan:PCAN_USBBUS1")
    assert "CAN_CONFIG" in str(info.value) and "\n" not in str(info.value)
    assert opened[0].shut


def test_an_fd_adapter_or_a_classic_bus_for_canopen_opens(monkeypatch):
    _opened_as(monkeypatch, can.CanProtocol.CAN_FD)
    open_bus("kvaser:0").shutdown()
    opened = _opened_as(monkeypatch, can.CanProtocol.CAN_20)
    open_bus("pcan:PCAN_USBBUS1", fd=False).shutdown()  # the cia402 profile: classic frames
    assert opened[0].kwargs["fd"] is False
