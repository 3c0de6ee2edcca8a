"""The cia402 master against the emulated drives (plant_emulator.cia402, canopen LocalNodes)
on python-can's in-process virtual bus: boot and mapping as an independent SDO client reads
them back, the walk to operation enabled, torque in per mille, the EMCY of a SYNC loss
counted, and the deactivate sequence."""

from __future__ import annotations

import json
import math

import can
import pytest

from hal.cia402_master.master import CONSUMER_PERIODS, HEARTBEAT_MS, Cia402Master
from hal.config import RigConfig
from tests.support.cia402 import FakeNow, drives_on_virtual_bus

CFG = RigConfig()
IDS = (CFG.cia402.node_id_1, CFG.cia402.node_id_2)
PERIOD_S = 1.0 / CFG.rates.control_hz
WAIT_S = 5.0
"""How long a test waits for the drives' TPDOs (generous: shared CPUs)."""


@pytest.fixture
def bench():
    with drives_on_virtual_bus(CFG) as bench:
        yield bench


@pytest.fixture
def master(bench):
    bus = can.Bus(interface="virtual", channel=bench.master.bus.channel_id)
    m = Cia402Master.from_config(CFG, bus, now_ns=FakeNow())
    try:
        yield m
    finally:
        m.close()


def one_sync(m: Cia402Master, torques=None) -> None:
    m.send(torques)
    k = m.sync()
    assert m.wait_tpdos(k, WAIT_S), f"no TPDOs after SYNC {k}"


def enable(m: Cia402Master) -> int:
    """The arming walk, one SYNC per transition (the drives watch the controller's heartbeat
    from its start, as in the profile); the SYNCs it took."""
    m.watch_controller()
    for n in range(1, 12):
        if m.steer("OPERATION ENABLED"):
            return n
        one_sync(m)
    raise AssertionError(f"not enabled: {m.diagnostics()['drives']}")


def test_boot_configures_and_maps_every_drive(bench, master):
    master.boot()
    for node_id in IDS:  # the controller's heartbeat is consumed from arming on
        assert bench.drive(node_id).sdo[0x1016][1].raw == 0
    master.watch_controller()
    for node_id in IDS:
        node = bench.drive(node_id)  # what the master wrote, read without the bus
        assert node.sdo[0x1017].raw == HEARTBEAT_MS
        assert node.sdo[0x1016][1].raw == (0x7F << 16) | CONSUMER_PERIODS * HEARTBEAT_MS
        assert (node.sdo[0x60C2][1].raw, node.sdo[0x60C2][2].raw) == (20, -3)
        assert node.sdo[0x6061].raw == 10
        node.tpdo.read()
        node.rpdo.read()
        got = {
            name: {
                n: (p.trans_type, [(v.index, v.length) for v in p.map])
                for n, p in maps.map.items()
                if p.enabled
            }
            for name, maps in (("rpdo", node.rpdo), ("tpdo", node.tpdo))
        }
        assert got == {
            "rpdo": {1: (1, [(0x6040, 16), (0x6071, 16)])},
            "tpdo": {1: (1, [(0x6041, 16), (0x6064, 32)]), 2: (1, [(0x606C, 32), (0x6077, 16)])},
        }
    assert [d.nmt.state for d in bench.rig.drives] == ["OPERATIONAL", "OPERATIONAL"]
    # 0x6072 from robot.tau_max over the rated torque 0x6076 read from the drive
    for j, units in enumerate(master.units):
        assert units.rated_torque_mnm == round(CFG.cia402.rated_torque[j] * 1000)
        assert master.limits[j] == math.floor(
            CFG.robot.tau_max[j] / CFG.cia402.rated_torque[j] * 1000
        )
        assert bench.drive(IDS[j]).sdo[0x6072].raw == master.limits[j]


def test_the_walk_enables_and_torque_reaches_the_joints(bench, master):
    master.boot()
    assert master.mode(master.now_ns()) == "no_status"
    one_sync(master)
    assert enable(master) <= 5  # shutdown, switch on, enable operation
    assert master.mode(master.now_ns()) == "enabled"
    one_sync(master, (1.25, -0.5))  # latched at this SYNC: acts on the next period
    assert bench.rig.torques() == pytest.approx((1.25, -0.5))
    js = master.joint_state()
    assert js.states == ("OPERATION ENABLED", "OPERATION ENABLED")
    assert js.tau == pytest.approx((1.25, -0.5))
    q0 = CFG.scenario.q0
    inc = [1 / u.increments_per_rad for u in master.units]
    assert js.q == pytest.approx(q0, abs=max(inc))  # nothing moved yet: the torque acts next
    one_sync(master, (1.25, -0.5))
    js2 = master.joint_state()
    assert js2.sync == js.sync + 1
    assert js2.dq[0] > 0 and js2.dq[1] < 0  # torque at work


def test_a_sync_loss_is_an_emcy_fault_counted(bench, master):
    master.boot()
    one_sync(master)
    enable(master)
    t = bench.clock.t
    bench.rig.poll(t + 3 * PERIOD_S)  # no SYNC for 3 periods
    for _ in range(3):  # the EMCYs arrive on canopen's receive thread
        one_sync(master)
        if sum(master.faults.counts.values()) >= 2:
            break
    assert master.faults.counts["emcy_8700"] == 2
    assert master.mode(master.now_ns()) == "fault"
    assert master.joint_state().states == ("FAULT", "FAULT")
    assert bench.rig.torques() == (0.0, 0.0)


def test_deactivate_quick_stops_disables_and_leaves_operational(bench, master):
    master.boot()
    one_sync(master)
    enable(master)
    one_sync(master, (2.0, 0.2))
    steps = master.deactivate(WAIT_S)
    assert steps == [
        ("quick stop", ("QUICK STOP ACTIVE", "QUICK STOP ACTIVE")),
        ("disable operation", ("SWITCH ON DISABLED", "SWITCH ON DISABLED")),
        ("pre-operational", ("PRE-OPERATIONAL", "PRE-OPERATIONAL")),
    ]
    assert bench.rig.torques() == (0.0, 0.0)
    # the drives no longer consume the controller's heartbeat: its end faults nobody
    for node_id in IDS:
        assert bench.drive(node_id).sdo[0x1016][1].raw == 0
    bench.rig.poll(bench.clock.t + 10.0)
    assert [d.power.state.name for d in bench.rig.drives] == ["SWITCH_ON_DISABLED"] * 2


def test_hil_cia402_check_boots_maps_and_leaves_the_drives_disabled(bench, capsys):
    from rt_controller.cli import main

    channel = bench.master.bus.channel_id
    assert main(["cia402", "check", "--can", f"virtual:{channel}", "--json"]) == 0
    drives = json.loads(capsys.readouterr().out)["drives"]
    assert [d["node"] for d in drives] == list(IDS)
    for j, d in enumerate(drives):
        assert d["state"] == "switch on disabled"
        assert d["mode_display"] == 10
        assert d["pdo"] == {
            "rpdo": {"1": ["0x6040", "0x6071"]},
            "tpdo": {"1": ["0x6041", "0x6064"], "2": ["0x606C", "0x6077"]},
        }
        assert d["torque_limit_nm"] == pytest.approx(CFG.robot.tau_max[j], rel=1e-3)
        assert d["interpolation_period_s"] == pytest.approx(PERIOD_S)
    assert [dr.nmt.state for dr in bench.rig.drives] == ["PRE-OPERATIONAL"] * 2
    assert bench.rig.syncs == 0


def test_hil_cia402_check_without_drives_says_so_in_one_line(capsys):
    """... and, on python-can's in-process virtual bus, says at the start that a drive in
    another process cannot answer there."""
    from rt_controller.cli import main

    assert main(["cia402", "check", "--can", "virtual:cia402-nobody"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "hil cia402 check: NMT reset communication sent, waiting up to 20 s for the boot-up of "
        "node 1 (EDS the shipped hal/cia402_drive.eds) and node 2 (EDS the shipped "
        "hal/cia402_drive.eds) (on python-can's virtual bus only drives in this process can "
        "answer, none in another: use udp_multicast (this host) or socketcan:CHANNEL)",
        "hil cia402 check: error: nodes 1, 2 sent no boot-up within 20 s of NMT reset "
        "communication: are they powered, on this bus at its bit rate, with node ids 1, 2?",
    ]


def test_an_incomplete_tpdo_set_gives_the_last_complete_one(bench, master):
    """While the TPDOs of the newest SYNC are still arriving (here: one drive never answers)
    the joint state is the previous complete set, not none."""
    master.boot()
    one_sync(master)
    enable(master)
    before = master.joint_state()
    bench.remote(IDS[1]).nmt.state = "PRE-OPERATIONAL"  # node 2 sends no more PDOs
    k = master.sync()
    assert not master.wait_tpdos(k, 0.5)
    assert master.joint_state() == before
    assert before.sync == k - 1
