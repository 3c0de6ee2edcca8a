"""The cia402 master's fault paths against plain canopen LocalNodes (the shipped object
dictionary, no emulation): a drive that does not show CST in 0x6061, a drive without CST, a
wrong type in the EDS, EMCYs counted, a lost heartbeat counted once."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterator

import can
import canopen
import pytest
from canopen.objectdictionary import INTEGER32
from canopen.profiles.p402 import BaseNode402

from hal.cia402_master import boot
from hal.cia402_master.watch import FaultLog, NodeWatch
from hal.cia402_od import EMCY_HEARTBEAT, SUPPORTED_MODES, TARGET_TORQUE, build_od
from hal.errors import HalDriveError


class FakeNow:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def network(channel: str) -> canopen.Network:
    net = canopen.Network(can.Bus(interface="virtual", channel=channel))
    net.NOTIFIER_CYCLE = 0.05  # a quick shutdown
    return net.connect()


@pytest.fixture
def pair() -> Iterator[tuple[canopen.LocalNode, canopen.RemoteNode, canopen.Network]]:
    """A drive (LocalNode 5) and the master's view of it, each on its own network of one
    in-process virtual bus."""
    channel = f"cia402-{uuid.uuid4().hex}"
    drive_od, master_od = build_od(5), build_od(5)
    drive_net = network(channel)
    master_net = network(channel)
    drive = drive_net.create_node(5, drive_od)
    remote = master_net.add_node(BaseNode402(5, master_od))
    try:
        yield drive, remote, master_net
    finally:
        master_net.disconnect()
        drive_net.disconnect()


def test_a_mode_that_0x6061_does_not_show_is_a_clear_error(pair):
    """canopen's op_mode setter would only log this; the master refuses to go on."""
    _drive, remote, _net = pair
    with pytest.raises(HalDriveError, match=r"node 5: 0x6061 reads 0 .* 0x6060 = 10"):
        boot.enter_cst(remote, timeout_s=0.05)


def test_a_mode_that_0x6061_shows_passes(pair):
    drive, remote, _net = pair

    def mirror(index, subindex, od, data):
        if index == 0x6060:
            drive.data_store.setdefault(0x6061, {})[0] = bytes(data)

    drive.add_write_callback(mirror)
    boot.enter_cst(remote, timeout_s=0.5)
    assert remote.sdo[0x6061].raw == boot.CST_MODE


def test_a_drive_without_cst_is_refused_before_any_mode_write(pair):
    drive, remote, _net = pair
    drive.sdo[SUPPORTED_MODES].raw = 0x0008  # profiled torque only
    with pytest.raises(HalDriveError, match="does not advertise cyclic synchronous torque"):
        boot.enter_cst(remote)
    assert remote.sdo[0x6060].raw == 0


def test_an_eds_with_a_32_bit_target_torque_is_refused():
    od = build_od(5)
    od[TARGET_TORQUE].data_type = INTEGER32
    with pytest.raises(HalDriveError, match="0x6071"):
        boot.check_types(canopen.RemoteNode(5, od))


def _watch(remote: canopen.RemoteNode, now: FakeNow) -> tuple[NodeWatch, FaultLog]:
    faults = FaultLog()
    return NodeWatch(remote, faults, threading.Condition(), now, lambda: 0), faults


def test_emcys_are_faults_counted_by_code_and_error_reset_is_not(pair):
    drive, remote, _net = pair
    _, faults = _watch(remote, FakeNow())
    got = threading.Semaphore(0)
    remote.emcy.add_callback(lambda err: got.release())
    for code in (EMCY_HEARTBEAT, 0x8700, EMCY_HEARTBEAT, 0x0000):
        drive.emcy.send(code, 0x11)
    for _ in range(4):
        assert got.acquire(timeout=5)
    assert faults.counts == {"emcy_8130": 2, "emcy_8700": 1}
    assert faults.resets == 1
    assert [e.node for e in faults.events] == [5, 5, 5]


def test_a_lost_heartbeat_is_one_fault_until_it_comes_back(pair):
    drive, remote, _net = pair
    now = FakeNow()
    watch, faults = _watch(remote, now)
    watch.heartbeat_limit_ns = 60_000_000
    beat = threading.Semaphore(0)
    remote.nmt.add_heartbeat_callback(lambda state: beat.release())
    drive.nmt.state = "PRE-OPERATIONAL"
    drive.nmt.start_heartbeat(10)
    assert beat.acquire(timeout=5)
    drive.nmt.stop_heartbeat()
    heard = watch.heartbeat_ns
    now.ns = heard + 60_000_000
    assert not watch.check_heartbeat(now.ns)
    now.ns = heard + 60_000_001
    assert watch.check_heartbeat(now.ns)
    assert watch.check_heartbeat(now.ns + 10**9)  # still lost, counted once
    assert faults.counts == {"heartbeat_lost": 1}
    drive.nmt.start_heartbeat(10)
    assert beat.acquire(timeout=5)
    assert not watch.check_heartbeat(watch.heartbeat_ns)
    drive.nmt.stop_heartbeat()
