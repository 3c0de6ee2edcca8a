"""The cia402 master off the happy path, against the emulated drives on python-can's
in-process virtual bus: a run stopped after the boot but before arming, and a second master
already driving the bus (another ``hil controller``, a PLC, the dsp profile's emulator)."""

from __future__ import annotations

import can
import canopen
import pytest

from hal.cia402_master.master import HEARTBEAT_MS, Cia402Master
from hal.cia402_master.watch import heartbeat_dictionary
from hal.config import RigConfig
from hal.config.cia402 import CONTROLLER_NODE_ID
from hal.errors import HalDriveError
from rt_controller.cli import main
from tests.support.cia402 import FakeNow, drives_on_virtual_bus, round_trip

CFG = RigConfig()


@pytest.fixture
def bench():
    with drives_on_virtual_bus(CFG) as bench:
        yield bench


def new_master(bench) -> Cia402Master:
    bus = can.Bus(interface="virtual", channel=bench.master.bus.channel_id)
    return Cia402Master.from_config(CFG, bus, now_ns=FakeNow())


def test_closing_a_booted_master_that_never_armed_leaves_the_drives_pre_operational(bench):
    """A run stopped (Ctrl-C) after the boot and before its first arming step never
    deactivates; its end must still take the drives out of NMT operational, as a check's."""
    master = new_master(bench)
    try:
        master.boot()
        round_trip(bench.remote(CFG.cia402.node_id_1))  # the NMT start was handled
        assert [d.nmt.state for d in bench.rig.drives] == ["OPERATIONAL"] * 2
    finally:
        master.close()
    round_trip(bench.remote(CFG.cia402.node_id_1))
    assert [d.nmt.state for d in bench.rig.drives] == ["PRE-OPERATIONAL"] * 2
    assert [d.power.state.name for d in bench.rig.drives] == ["SWITCH_ON_DISABLED"] * 2
    for drive in bench.rig.drives:  # nobody's heartbeat consumed: nothing faults them later
        assert drive.sdo[0x1016][1].raw == 0


def _other_master_sync(network: canopen.Network) -> None:
    network.sync.start(0.02)


def _other_master_heartbeat(network: canopen.Network) -> None:
    other = canopen.LocalNode(CONTROLLER_NODE_ID, heartbeat_dictionary())
    network.add_node(other)
    other.nmt.state = "OPERATIONAL"
    other.nmt.start_heartbeat(HEARTBEAT_MS)


@pytest.mark.parametrize(
    ("start_other", "seen"),
    [(_other_master_sync, "SYNC"), (_other_master_heartbeat, "heartbeat of node 127")],
)
def test_a_second_master_on_the_bus_is_refused_before_any_drive_is_reset(
    bench, capsys, start_other, seen
):
    """`hil cia402 check` (or a second `hil controller`) on a bus another master drives
    would reset and remap the drives under the running one: refuse it in one line, and
    send the drives nothing."""
    start_other(bench.master)
    try:
        channel = bench.master.bus.channel_id
        assert main(["cia402", "check", "--can", f"virtual:{channel}"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert "another CANopen master" in err and seen in err, err
        for drive in bench.rig.drives:  # never configured: its heartbeat producer still off
            assert drive.sdo[0x1017].raw == 0
        assert [d.nmt.state for d in bench.rig.drives] == ["PRE-OPERATIONAL"] * 2
        master = new_master(bench)
        try:
            with pytest.raises(HalDriveError, match="another CANopen master"):
                master.boot()
        finally:
            master.close()
    finally:
        bench.master.sync.stop()


@pytest.mark.parametrize(("index", "sub", "name"), [(0x6076, 0, "0x6076"), (0x608F, 1, "0x608F")])
def test_a_drive_with_a_zero_unit_is_named_in_the_one_line_error(bench, capsys, index, sub, name):
    """An unconfigured drive (rated torque or encoder resolution 0: the vendor tool never
    stored them) is refused naming the node and the object, not an anonymous unit name."""
    drive = bench.drive(CFG.cia402.node_id_2)
    drive.data_store.setdefault(index, {})[sub] = bytes(4)  # its store, past the EDS range
    channel = bench.master.bus.channel_id
    assert main(["cia402", "check", "--can", f"virtual:{channel}"]) == 2
    waiting, err = capsys.readouterr().err.splitlines()  # what it waited for, then the error
    assert waiting.startswith("hil cia402 check: NMT reset communication sent, waiting"), waiting
    assert f"node {CFG.cia402.node_id_2}" in err and name in err, err
    assert [d.nmt.state for d in bench.rig.drives] == ["PRE-OPERATIONAL"] * 2
