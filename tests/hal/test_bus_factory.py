"""The bus factory (:mod:`hal.bus`): CAN specs parsed and resolved (``auto``, python-can's own
configuration), clear errors for a bus that cannot open, and the loopback-only UDP multicast
transport (hop limit 0, isolated channels, garbage datagrams skipped)."""

from __future__ import annotations

import socket
from pathlib import Path

import can
import can.util
import pytest

from hal import bus as hal_bus
from hal.bus import BusSpec, isolated_spec, open_bus, parse_spec, process_spec, resolve_spec
from hal.can_codec import DspCodec
from hal.errors import HalConfigError, HalTransportError
from hal.udp_loopback import DEFAULT_GROUP, LoopbackMulticastBus

RECV_TIMEOUT_S = 5.0


@pytest.fixture
def no_python_can_config(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """No CAN_* variables and no can.conf: returns where a test may write one."""
    for var in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(var, raising=False)
    conf = tmp_path / "can.conf"
    monkeypatch.setattr(can.util, "CONFIG_FILES", [str(conf)])
    monkeypatch.setattr(can, "rc", {})
    return conf


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("socketcan:vcan0", BusSpec("socketcan", "vcan0")),
        ("socketcan", BusSpec("socketcan", "vcan0")),
        ("socketcan:can1", BusSpec("socketcan", "can1")),
        ("virtual", BusSpec("virtual", "hil")),
        ("virtual:mychannel", BusSpec("virtual", "mychannel")),
        ("udp_multicast", BusSpec("udp_multicast", DEFAULT_GROUP)),
        ("udp_multicast:239.74.163.9", BusSpec("udp_multicast", "239.74.163.9")),
        (
            "udp_multicast:239.74.163.2:45000",
            BusSpec("udp_multicast", DEFAULT_GROUP, {"port": 45000}),
        ),
        ("udp_multicast:[ff15::1]:45000", BusSpec("udp_multicast", "ff15::1", {"port": 45000})),
        ("udp_multicast:ff15::1", BusSpec("udp_multicast", "ff15::1")),
    ],
)
def test_parse_spec(text: str, expected: BusSpec) -> None:
    assert parse_spec(text) == expected


@pytest.mark.parametrize(
    "text", ["", "nosuchbus", "udp_multicast:10.0.0.1", "udp_multicast:239.1.1.1:99999", "auto"]
)
def test_bad_specs_name_the_problem(text: str) -> None:
    with pytest.raises(HalConfigError):
        parse_spec(text)


def test_auto_prefers_vcan0_then_udp_multicast(
    no_python_can_config: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    net = tmp_path / "net"
    net.mkdir()
    monkeypatch.setattr(hal_bus, "SYS_CLASS_NET", net)
    assert resolve_spec(None) == BusSpec("udp_multicast", DEFAULT_GROUP, {}, "auto")
    (net / "vcan0").mkdir()
    assert resolve_spec("auto") == BusSpec("socketcan", "vcan0", {}, "auto")


def test_auto_honours_python_can_environment(
    no_python_can_config: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    channel = isolated_spec("virtual").partition(":")[2]
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", channel)
    assert resolve_spec("auto").channel == channel
    with open_bus() as bus:
        assert bus.channel_info.endswith(channel)
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.delenv("CAN_CHANNEL")
    monkeypatch.setenv("CAN_CONFIG", '{"port": 45123}')
    assert str(resolve_spec(None)) == f"udp_multicast:{DEFAULT_GROUP}:45123"


def test_auto_honours_a_can_conf_file(no_python_can_config: Path) -> None:
    no_python_can_config.write_text("[default]\ninterface = virtual\nchannel = from-file\n")
    resolved = resolve_spec(None)
    assert (resolved.interface, resolved.channel, resolved.source) == (
        "virtual",
        "from-file",
        "python-can config",
    )


def test_explicit_spec_wins_over_python_can_config(
    no_python_can_config: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    assert resolve_spec("udp_multicast").interface == "udp_multicast"


def test_a_bus_between_processes_is_never_the_in_process_virtual_bus(
    no_python_can_config: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for spec in ("virtual", "virtual:x", " Virtual:y "):
        with pytest.raises(HalConfigError, match=r"one process only.*udp_multicast"):
            process_spec(spec)
    monkeypatch.setenv("CAN_INTERFACE", "virtual")  # python-can's config naming it: the same
    with pytest.raises(
        HalConfigError, match=r"virtual:hil \(from python-can config\).*one process only"
    ):
        process_spec("auto")
    assert process_spec("udp_multicast") == resolve_spec("udp_multicast")


def test_invalid_python_can_config_is_a_config_error(
    no_python_can_config: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "nosuchbus")
    with pytest.raises(HalConfigError, match="CAN_INTERFACE"):
        open_bus()


def test_missing_socketcan_interface_is_one_clear_line() -> None:
    with pytest.raises(HalTransportError) as info:
        open_bus("socketcan:vcan97")
    text = str(info.value)
    assert "\n" not in text
    assert "udp_multicast" in text
    assert "modprobe vcan" in text or "AF_CAN" in text


def test_udp_multicast_stays_on_loopback_with_hop_limit_0() -> None:
    with open_bus(isolated_spec("udp_multicast")) as bus:
        assert isinstance(bus, LoopbackMulticastBus)
        tx = bus.sender
        assert tx is not None
        assert tx.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0
        out_if = tx.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4)
        assert socket.inet_ntoa(out_if) == "127.0.0.1"
        assert tx.getsockname()[0] == "127.0.0.1"
        assert "hop limit 0" in bus.channel_info


def test_udp_multicast_hop_limit_only_when_passed_explicitly() -> None:
    with open_bus(isolated_spec("udp_multicast"), hop_limit=1) as bus:
        assert bus.sender.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 1


@pytest.mark.parametrize("interface", ["virtual", "udp_multicast"])
def test_isolated_specs_do_not_cross_talk(interface: str) -> None:
    first, second = isolated_spec(interface), isolated_spec(interface)
    assert first != second
    with open_bus(first) as a_tx, open_bus(first) as a_rx, open_bus(second) as b_rx:
        a_tx.send(DspCodec().encode_sync(1))
        assert a_rx.recv(timeout=RECV_TIMEOUT_S) is not None
        assert b_rx.recv(timeout=0.1) is None


def test_udp_multicast_skips_garbage_datagrams() -> None:
    spec = isolated_spec("udp_multicast")
    parsed = parse_spec(spec)
    group, port = parsed.channel, parsed.kwargs["port"]
    with open_bus(spec) as bus, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        raw.sendto(b"\xc1 not msgpack", (group, port))
        with open_bus(spec) as tx:
            tx.send(DspCodec().encode_sync(3))
            got = bus.recv(timeout=RECV_TIMEOUT_S)
        assert got is not None and got.arbitration_id == 0x080
        assert bus.malformed_datagrams == 1


def test_an_adapter_without_its_vendor_library_is_one_line() -> None:
    """python-can's Kvaser interface raises NameError when canlib is not installed: before
    this, a traceback from every command given --can kvaser:0."""
    kvaser = pytest.importorskip("can.interfaces.kvaser.canlib")
    if hasattr(kvaser, "canGetNumberOfChannels"):
        pytest.skip("this host has Kvaser's canlib")
    with pytest.raises(HalTransportError, match=r"^cannot open CAN bus kvaser:0: .*vendor library"):
        open_bus("kvaser:0")


def test_a_name_error_of_our_own_is_not_taken_for_the_adapter(monkeypatch) -> None:
    def broken(**_kw):
        raise NameError("name 'oops' is not defined")

    monkeypatch.setattr(can, "Bus", broken)
    with pytest.raises(NameError, match="oops"):
        open_bus("virtual:x")
