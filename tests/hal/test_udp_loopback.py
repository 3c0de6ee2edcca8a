"""The host-local UDP multicast bus (hal.udp_loopback): what it refuses, warns about and counts.

Oracles are independent of the code under test: python-can's own ``Message`` check for frame
validity, the kernel (a second bind, a real capped receive buffer) for reservations and buffers,
and exact accounting (every frame sent is either received or counted as dropped).
Nothing here asserts on wall-clock time; receive timeouts only bound a wait.
"""

from __future__ import annotations

import errno
import importlib.util
import io
import ipaddress
import random
import socket
import subprocess
import sys
import tarfile
import time
import warnings
from pathlib import Path

import can
import pytest

from hal import udp_loopback
from hal.bus import isolated_spec, open_bus, parse_spec
from hal.errors import HalCodecError, HalError, HalTransportError
from hal.udp_loopback import (
    CAN_FD_LENGTHS,
    GroupUnreachableError,
    InvalidFrameError,
    LoopbackMulticastBus,
    ReceiveBufferWarning,
)

ROOT = Path(__file__).resolve().parents[2]
RECV_TIMEOUT_S = 5.0
IPV6_GROUP = "ff11:7079:7468:6f6e:6465:6d6f:6d63:6173"  # python-can's host-local test group


def _pair(spec: str) -> tuple[str, int]:
    parsed = parse_spec(spec)
    return str(parsed.channel), int(parsed.kwargs["port"])


# --------------------------------------------------------------------------- refusal at open


class DeafSocket(socket.socket):
    """A socket whose ``sendto`` the kernel seems to take but never delivers (a host that routes
    the group and does not loop it back): the bus's loop probe cannot come back."""

    def sendto(self, data: bytes, *args: object) -> int:
        return len(data)


def test_a_group_whose_datagrams_do_not_come_back_is_refused_in_one_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    spec = isolated_spec("udp_multicast")
    monkeypatch.setattr(udp_loopback.socket, "socket", DeafSocket)
    monkeypatch.setattr(udp_loopback, "LOOP_PROBE_TIMEOUT_S", 0.05)
    with pytest.raises(GroupUnreachableError) as info:
        open_bus(spec)
    text = str(info.value)
    assert "\n" not in text
    assert "did not come back" in text and _pair(spec)[0] in text
    # One exception that both worlds catch: HAL callers and python-can callers (can.Bus).
    assert isinstance(info.value, HalTransportError | can.CanInitializationError)
    assert isinstance(info.value, HalError) and isinstance(info.value, can.CanInitializationError)


def test_ipv6_group_either_works_end_to_end_or_is_refused_at_open() -> None:
    """Never "opens, then every send fails" (issue 17): refused in one line, or it carries."""
    port = _pair(isolated_spec("udp_multicast"))[1]
    spec = f"udp_multicast:[{IPV6_GROUP}]:{port}"
    try:
        rx = open_bus(spec)
    except GroupUnreachableError as exc:
        text = str(exc)
        assert "\n" not in text and IPV6_GROUP in text and "IPv4 group" in text
        return
    with rx, open_bus(spec) as tx:
        tx.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
        got = rx.recv(timeout=RECV_TIMEOUT_S)
        assert got is not None and got.arbitration_id == 0x123 and bytes(got.data) == b"\x01\x02"


def test_refused_bus_leaves_no_socket_open(monkeypatch: pytest.MonkeyPatch) -> None:
    group, port = _pair(isolated_spec("udp_multicast"))  # its port reservation stays open
    opened: list[socket.socket] = []

    class Tracking(DeafSocket):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            opened.append(self)

    monkeypatch.setattr(udp_loopback.socket, "socket", Tracking)
    monkeypatch.setattr(udp_loopback, "LOOP_PROBE_TIMEOUT_S", 0.05)
    with pytest.raises(GroupUnreachableError):
        LoopbackMulticastBus(group, port=port)
    assert opened and all(sock.fileno() == -1 for sock in opened)


# ------------------------------------------------------------------------- send() validation

INVALID = [
    pytest.param(dict(arbitration_id=0x800, is_extended_id=False), id="11-bit id 0x800"),
    pytest.param(dict(arbitration_id=0x20000000, is_extended_id=True), id="29-bit id 2^29"),
    pytest.param(dict(arbitration_id=-1, is_extended_id=False), id="negative id"),
    pytest.param(dict(arbitration_id=1, data=bytes(9), dlc=9), id="9 bytes classic"),
    pytest.param(dict(arbitration_id=1, data=bytes(65), dlc=65, is_fd=True), id="65 bytes FD"),
    pytest.param(dict(arbitration_id=1, data=bytes(9), dlc=9, is_fd=True), id="9 bytes FD"),
    pytest.param(dict(arbitration_id=1, data=bytes(33), dlc=33, is_fd=True), id="33 bytes FD"),
    pytest.param(dict(arbitration_id=1, data=bytes(3), dlc=5), id="dlc != len"),
    pytest.param(dict(arbitration_id=1, is_remote_frame=True, is_fd=True), id="remote FD"),
    pytest.param(dict(arbitration_id=1, is_remote_frame=True, dlc=9), id="remote dlc 9"),
    pytest.param(dict(arbitration_id=1, is_error_frame=True, is_remote_frame=True), id="rtr+err"),
    pytest.param(dict(arbitration_id=1, data=b"\x01", bitrate_switch=True), id="brs classic"),
]


@pytest.mark.parametrize("fields", INVALID)
def test_send_refuses_an_invalid_frame_and_sends_nothing(fields: dict) -> None:
    msg = can.Message(check=False, **fields)
    spec = isolated_spec("udp_multicast")
    with open_bus(spec) as tx, open_bus(spec) as rx:
        with pytest.raises(InvalidFrameError) as info:
            tx.send(msg)
        assert isinstance(info.value, ValueError)  # python-can's Message check raises this
        assert isinstance(info.value, can.CanOperationError)  # what python-can's send() raises
        assert isinstance(info.value, HalCodecError)
        assert "\n" not in str(info.value)
        marker = can.Message(arbitration_id=0x7FF, data=b"\xaa", is_extended_id=False)
        tx.send(marker)
        got = rx.recv(timeout=RECV_TIMEOUT_S)
        assert got is not None and got.arbitration_id == 0x7FF  # nothing arrived before it
        assert rx.malformed_datagrams == 0


def test_fd_frame_refused_on_a_classic_bus() -> None:
    group, port = _pair(isolated_spec("udp_multicast"))
    with LoopbackMulticastBus(group, port=port, fd=False) as bus, pytest.raises(InvalidFrameError):
        bus.send(can.Message(arbitration_id=1, data=bytes(12), is_fd=True))


def _random_message(rng: random.Random) -> can.Message:
    extended = rng.random() < 0.5
    fd = rng.random() < 0.5
    remote = rng.random() < 0.15
    limit = 0x20000000 if extended else 0x800
    arb = rng.choice([rng.randrange(limit), limit, limit - 1, rng.randrange(limit, 2 * limit)])
    length = rng.choice([0, 3, 8, 9, 12, 13, 48, 64, 65])
    data = bytes(rng.randrange(256) for _ in range(0 if remote else length))
    dlc = length if rng.random() < 0.9 else length + 1
    return can.Message(
        arbitration_id=arb,
        is_extended_id=extended,
        is_fd=fd,
        is_remote_frame=remote,
        bitrate_switch=rng.random() < 0.2,
        data=data,
        dlc=dlc,
        check=False,
    )


def _python_can_accepts(msg: can.Message) -> bool:
    """The oracle: python-can's own Message check (what every receiver applies), plus the CAN FD
    length table (ISO 11898-1: a CAN FD frame carries 0..8, 12, 16, 20, 24, 32, 48 or 64 bytes)."""
    try:
        can.Message(
            arbitration_id=msg.arbitration_id,
            is_extended_id=msg.is_extended_id,
            is_fd=msg.is_fd,
            is_remote_frame=msg.is_remote_frame,
            bitrate_switch=msg.bitrate_switch,
            data=msg.data,
            dlc=msg.dlc,
            check=True,
        )
    except ValueError:
        return False
    return not (msg.is_fd and len(msg.data) not in CAN_FD_LENGTHS)


def test_send_accepts_exactly_the_frames_a_receiver_accepts() -> None:
    rng = random.Random(17)
    spec = isolated_spec("udp_multicast")
    sent = refused = 0
    with open_bus(spec) as tx, open_bus(spec) as rx:
        for _ in range(400):
            msg = _random_message(rng)
            if _python_can_accepts(msg):
                tx.send(msg)
                got = rx.recv(timeout=RECV_TIMEOUT_S)
                assert got is not None
                assert got.equals(msg, timestamp_delta=None, check_channel=False)
                sent += 1
            else:
                with pytest.raises(InvalidFrameError):
                    tx.send(msg)
                refused += 1
        assert rx.recv(timeout=0) is None  # nothing refused was sent after all
        assert rx.malformed_datagrams == 0 and rx.kernel_drops == 0
    assert sent > 50 and refused > 50  # both sides of the oracle were exercised


def test_frames_carry_the_kernels_arrival_stamp_not_the_time_they_are_read() -> None:
    """Like SocketCAN: the stamp is taken when the datagram is queued (during send on
    loopback), so a frame read later still says when it arrived. Linux switches its receive
    stamping on a moment after the first socket asks for it (a deferred static key) and stamps
    at read time until then, so the frames are sent until one carries a queue-time stamp."""
    spec = isolated_spec("udp_multicast")
    stamped_at_arrival = False
    with open_bus(spec) as tx, open_bus(spec) as rx:
        for _ in range(50):
            before = time.time()
            tx.send(can.Message(arbitration_id=0x123, data=b"\x01"))
            after = time.time()
            time.sleep(0.02)
            read = time.time()
            got = rx.recv(timeout=RECV_TIMEOUT_S)
            assert got is not None
            assert before - 1e-6 <= got.timestamp  # never earlier than the send
            if got.timestamp <= after + 1e-6 < read:
                stamped_at_arrival = True
                break
    assert stamped_at_arrival


# ----------------------------------------------------------------- receive buffer and drops


def _rmem_max() -> int:
    return int(Path("/proc/sys/net/core/rmem_max").read_text())


@pytest.mark.skipif(not Path("/proc/sys/net/core/rmem_max").exists(), reason="Linux only")
def test_a_capped_receive_buffer_is_a_warning() -> None:
    group, port = _pair(isolated_spec("udp_multicast"))
    asked = 2 * _rmem_max() + 4096  # the kernel caps SO_RCVBUF at rmem_max, even for root
    with pytest.warns(ReceiveBufferWarning, match="rmem_max") as record:
        bus = LoopbackMulticastBus(group, port=port, rcvbuf=asked)
    with bus:
        assert bus.rcvbuf_granted == _rmem_max() < asked
        assert str(asked) in str(record[0].message) and str(bus.rcvbuf_granted) in str(
            record[0].message
        )


def test_a_granted_receive_buffer_is_not_a_warning() -> None:
    group, port = _pair(isolated_spec("udp_multicast"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", ReceiveBufferWarning)
        with LoopbackMulticastBus(group, port=port, rcvbuf=4096) as bus:
            assert bus.rcvbuf_granted >= 4096


def test_kernel_drops_account_for_every_frame_sent() -> None:
    """Flood a receiver whose buffer holds a few frames: received + kernel_drops == sent."""
    group, port = _pair(isolated_spec("udp_multicast"))
    flood = 500
    with (
        LoopbackMulticastBus(group, port=port, rcvbuf=4096) as rx,
        LoopbackMulticastBus(group, port=port, rcvbuf=4096) as tx,
    ):
        for i in range(flood):
            tx.send(can.Message(arbitration_id=0x100, data=i.to_bytes(2, "little")))
        received = 0
        markers = 0
        # A marker (id 0x7FF) sent after the flood carries the drop count of everything before
        # it. It may be dropped too (buffer still full), so keep sending numbered markers until
        # the latest one sent is received: then every frame sent precedes a received one.
        while True:
            markers += 1
            tx.send(can.Message(arbitration_id=0x7FF, data=markers.to_bytes(2, "little")))
            latest_seen = False
            while (msg := rx.recv(timeout=RECV_TIMEOUT_S)) is not None:
                received += 1
                if msg.arbitration_id == 0x7FF and int.from_bytes(msg.data, "little") == markers:
                    latest_seen = True
                    break
            if latest_seen:
                break
        assert rx.kernel_drops > 0  # the buffer really overflowed
        assert received + rx.kernel_drops == flood + markers
        assert rx.malformed_datagrams == 0


# ---------------------------------------------------------------------- race-free free port


def test_isolated_port_is_held_so_no_one_else_can_be_given_it() -> None:
    group, port = _pair(isolated_spec("udp_multicast"))
    assert ipaddress.ip_address(group).is_multicast
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        with pytest.raises(OSError) as info:
            other.bind(("127.0.0.1", port))  # what another process's port choice would do
        assert info.value.errno == errno.EADDRINUSE


def test_isolated_specs_of_two_processes_never_coincide() -> None:
    mine = {_pair(isolated_spec("udp_multicast")) for _ in range(50)}
    assert len(mine) == 50
    code = (
        "from hal.bus import isolated_spec\n"
        "for _ in range(50): print(isolated_spec('udp_multicast'))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    ).stdout.split()
    theirs = {_pair(spec) for spec in out}
    assert len(theirs) == 50
    assert not mine & theirs
    assert {port for _, port in mine}.isdisjoint(port for _, port in theirs)


def test_isolated_spec_skips_a_pair_a_bus_was_opened_on_by_hand() -> None:
    group, port = _pair(isolated_spec("udp_multicast"))
    taken = str(ipaddress.IPv4Address(group) + 1)  # the pair the next call would pick
    with LoopbackMulticastBus(taken, port=port):
        following = _pair(isolated_spec("udp_multicast"))
    assert following != (taken, port)
    assert following[1] == port and following[0] != group


# ------------------------------------------------------------ the peer-suite script's parts


def _load_script():
    path = ROOT / "scripts" / "can_peer_suite.py"
    spec = importlib.util.spec_from_file_location("can_peer_suite", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_peer_suite_extracts_the_suite_and_its_helpers_byte_for_byte(tmp_path: Path) -> None:
    script = _load_script()
    files = {
        "pkg-1/test/__init__.py": b"",
        "pkg-1/test/back2back_test.py": b"from .config import X\nfrom . import helper\n",
        "pkg-1/test/config.py": b"X = 1\n",
        "pkg-1/test/helper.py": b"Y = 2\n",
        "pkg-1/test/unrelated_test.py": b"raise SystemExit\n",
    }
    sdist = tmp_path / "pkg-1.tar.gz"
    with tarfile.open(sdist, "w:gz") as tar:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    out = tmp_path / "work"
    names = script.extract_suite(sdist, out)
    assert names == ["__init__.py", "back2back_test.py", "config.py", "helper.py"]
    for name in names:
        assert (out / "test" / name).read_bytes() == files[f"pkg-1/test/{name}"]
    assert not (out / "test" / "unrelated_test.py").exists()


def test_peer_suite_counts_outcomes_per_group(tmp_path: Path) -> None:
    script = _load_script()
    junit = tmp_path / "junit.xml"
    junit.write_text(
        "<testsuites><testsuite>"
        '<testcase classname="test_hal_peer.TestHalIPv4" name="a"/>'
        '<testcase classname="test_hal_peer.TestHalIPv4ThreadSafe" name="b"><failure/></testcase>'
        '<testcase classname="test_hal_peer.TestHalIPv4" name="c"><skipped message="x"/>'
        "</testcase>"
        '<testcase classname="test_hal_peer.TestHalIPv6" name="a">'
        '<skipped message="refused at open: no route"/></testcase>'
        "</testsuite></testsuites>"
    )
    counts = script.summarise(junit)
    assert counts["IPv4"] == {"passed": 1, "failed": 1, "skipped": 1}
    assert counts["IPv6"] == {"skipped": 1, "refused": 1}
    assert list(counts["IPv6 reason"]) == ["no route"]
