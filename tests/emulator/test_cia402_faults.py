"""Fault reactions of the emulated CiA 402 drives: SYNC loss and the controller's heartbeat lost
put every drive in FAULT with torque off and an EMCY on the bus within 3 SYNC periods, and a
drive leaves FAULT only by a fault reset. The monitors run on a manual clock the test advances."""

from __future__ import annotations

from hal import cia402_od as cia
from hal.config import RigConfig
from plant_emulator.cia402.power_state import PowerState
from tests.support.cia402 import Bench, drives_on_virtual_bus, round_trip, sync_and_wait

SHUTDOWN, ENABLE, FAULT_RESET = 0x06, 0x0F, 0x80
PERIOD_S = 0.02
MASTER_ID = 0x7F


def both_enabled_with_torque(bench: Bench) -> list:
    nodes = []
    for node_id in (1, 2):
        node = bench.remote(node_id)
        node.tpdo.read()
        node.rpdo.read()
        node.sdo[cia.MODES_OF_OPERATION].raw = cia.CST_MODE
        node.nmt.state = "OPERATIONAL"
        nodes.append(node)
    for word in (SHUTDOWN, ENABLE):
        for node in nodes:
            node.rpdo[1]["Controlword"].raw = word
            node.rpdo[1]["Target torque"].raw = 400
            node.rpdo[1].transmit()
        bench.clock.t += PERIOD_S
        sync_and_wait(bench, *(n.tpdo[2] for n in nodes))
    for node, drive in zip(nodes, bench.rig.drives, strict=True):
        assert drive.power.state is PowerState.OPERATION_ENABLED
        assert drive.torque_nm() > 0
        node.emcy.reset()
    return nodes


def assert_faulted(bench: Bench, nodes: list, code: int) -> None:
    for node, drive in zip(nodes, bench.rig.drives, strict=True):
        assert drive.power.state is PowerState.FAULT
        assert drive.torque_nm() == 0.0
        assert node.sdo[cia.TORQUE_ACTUAL].raw == 0
        assert node.sdo[cia.STATUSWORD].raw & 0x4F == 0x08
        assert node.sdo[cia.ERROR_CODE].raw == code
        # the EMCY went out before the SDO answers above (one channel, in order)
        assert [e.code for e in node.emcy.log] == [code]


def test_sync_loss_faults_every_drive_within_3_periods():
    with drives_on_virtual_bus() as bench:
        nodes = both_enabled_with_torque(bench)
        last_sync = bench.clock.t
        bench.rig.poll(last_sync + 2.4 * PERIOD_S)  # one SYNC late: still fine
        assert all(d.power.state is PowerState.OPERATION_ENABLED for d in bench.rig.drives)
        bench.rig.poll(last_sync + 2.6 * PERIOD_S)
        assert_faulted(bench, nodes, cia.EMCY_SYNC)


def test_heartbeat_loss_faults_every_drive_with_emcy_8130():
    with drives_on_virtual_bus() as bench:
        nodes = both_enabled_with_torque(bench)
        for node in nodes:
            node.sdo[cia.HEARTBEAT_CONSUMER][1].raw = MASTER_ID << 16 | 60  # 3 periods
        bench.master.send_message(0x700 + MASTER_ID, b"\x05")  # the controller's heartbeat
        for node in nodes:
            round_trip(node)  # the heartbeat was handled
        beat = bench.clock.t
        for k in range(1, 3):  # SYNCs go on, so only the heartbeat can trip
            bench.clock.t = beat + k * PERIOD_S
            sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
            bench.rig.poll()
        assert all(d.power.state is PowerState.OPERATION_ENABLED for d in bench.rig.drives)
        bench.clock.t = beat + 3 * PERIOD_S + 0.001
        sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
        bench.rig.poll()
        assert_faulted(bench, nodes, cia.EMCY_HEARTBEAT)


def test_in_lockstep_the_heartbeat_limit_is_the_sync_limit():
    """In lockstep the world waits for the controller: a heartbeat late by more than 0x1016's
    time on a loaded host is not a lost controller. The drive allows the lockstep SYNC limit
    (``cia402.lockstep_sync_timeout_s``), as it does for SYNC; beyond it the drive faults."""
    cfg = RigConfig()
    limit = cfg.cia402.lockstep_sync_timeout_s
    with drives_on_virtual_bus(cfg, lockstep=True) as bench:
        nodes = both_enabled_with_torque(bench)
        for node in nodes:
            node.sdo[cia.HEARTBEAT_CONSUMER][1].raw = MASTER_ID << 16 | 500  # as the master
        bench.master.send_message(0x700 + MASTER_ID, b"\x05")
        for node in nodes:
            round_trip(node)
        beat = bench.clock.t
        bench.clock.t = beat + 0.9 * limit  # SYNC comes on time: only the heartbeat is late
        sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
        bench.rig.poll()
        assert all(d.power.state is PowerState.OPERATION_ENABLED for d in bench.rig.drives)
        bench.clock.t = beat + limit + 0.001
        sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
        bench.rig.poll()
        assert_faulted(bench, nodes, cia.EMCY_HEARTBEAT)


def test_a_drive_stays_in_fault_until_a_fault_reset():
    with drives_on_virtual_bus() as bench:
        nodes = both_enabled_with_torque(bench)
        bench.rig.poll(bench.clock.t + 3 * PERIOD_S)
        node, drive = nodes[0], bench.rig.drives[0]
        for word in (SHUTDOWN, ENABLE):  # SYNC is back and the master asks again: no
            node.rpdo[1]["Controlword"].raw = word
            node.rpdo[1].transmit()
            bench.clock.t += PERIOD_S
            sync_and_wait(bench, node.tpdo[1])
            bench.rig.poll()
        assert drive.power.state is PowerState.FAULT
        assert node.tpdo[2]["Torque actual value"].raw == 0
        node.rpdo[1]["Controlword"].raw = FAULT_RESET
        node.rpdo[1].transmit()
        sync_and_wait(bench, node.tpdo[1])
        assert drive.power.state is PowerState.SWITCH_ON_DISABLED
        assert [e.code for e in node.emcy.log] == [cia.EMCY_SYNC, 0]  # then the error reset
        assert node.sdo[cia.ERROR_CODE].raw == 0


def test_no_sync_monitoring_outside_operational():
    with drives_on_virtual_bus() as bench:
        nodes = both_enabled_with_torque(bench)
        for node in nodes:
            node.nmt.state = "PRE-OPERATIONAL"
            round_trip(node)
        bench.rig.poll(bench.clock.t + 100 * PERIOD_S)
        assert all(d.power.state is PowerState.OPERATION_ENABLED for d in bench.rig.drives)
        assert all(not n.emcy.log for n in nodes)


def test_lockstep_widens_the_sync_loss_limit_to_its_timeout():
    with drives_on_virtual_bus(lockstep=True) as bench:
        nodes = both_enabled_with_torque(bench)
        last_sync = bench.clock.t
        bench.rig.poll(last_sync + 10 * PERIOD_S)  # a slow lockstep tick: no fault
        assert all(d.power.state is PowerState.OPERATION_ENABLED for d in bench.rig.drives)
        bench.rig.poll(last_sync + RigConfig().cia402.lockstep_sync_timeout_s + 0.001)
        assert_faulted(bench, nodes, cia.EMCY_SYNC)


def test_a_joint_beyond_its_position_limit_faults_its_own_drive():
    cfg = RigConfig().with_overrides({"dsp.q_max": (0.53, 2.6)})  # q0 = pi/6 = 0.5236
    with drives_on_virtual_bus(cfg) as bench:
        nodes = both_enabled_with_torque(bench)  # +4 Nm and +0.4 Nm
        for _ in range(20):
            bench.clock.t += PERIOD_S
            sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
            if bench.rig.drives[0].power.faulted:
                break
        drive1, drive2 = bench.rig.drives
        assert drive1.power.state is PowerState.FAULT and drive1.torque_nm() == 0.0
        assert bench.rig.world.q[0] > 0.53
        assert [e.code for e in nodes[0].emcy.log] == [cia.EMCY_POSITION_LIMIT]
        assert drive2.power.state is PowerState.OPERATION_ENABLED  # its joint is within limits
        assert nodes[1].tpdo[1]["Statusword"].raw & 0x6F == 0x27


def test_a_joint_faster_than_its_limit_faults_its_drive():
    cfg = RigConfig().with_overrides({"dsp.dq_max": (10.0, 0.05)})
    with drives_on_virtual_bus(cfg) as bench:
        nodes = both_enabled_with_torque(bench)
        for _ in range(20):
            bench.clock.t += PERIOD_S
            sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
            if bench.rig.drives[1].power.faulted:
                break
        assert bench.rig.drives[1].power.state is PowerState.FAULT
        assert [e.code for e in nodes[1].emcy.log] == [cia.EMCY_VELOCITY_LIMIT]
