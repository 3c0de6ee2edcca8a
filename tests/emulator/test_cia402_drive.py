"""The emulated CiA 402 drives on a virtual bus, seen by a plain canopen master: boot, SDO,
PDO mapping and its rules, RPDOs latched at SYNC, TPDOs on SYNC."""

from __future__ import annotations

import math
import queue

import can
import pytest
from canopen.sdo import SdoAbortedError

from hal import cia402_od as cia
from hal.config import RigConfig
from plant_emulator.cia402.power_state import PowerState
from plant_emulator.cia402.rig import sync_arrival
from tests.support.cia402 import (
    REPLY_TIMEOUT_S,
    Bench,
    drives_on_virtual_bus,
    round_trip,
    sync_and_wait,
)

SHUTDOWN, SWITCH_ON, ENABLE = 0x06, 0x07, 0x0F


def operational(bench: Bench, node_id: int):
    """A master node of the EDS, its PDOs read, NMT started, mode CST."""
    node = bench.remote(node_id)
    node.tpdo.read()
    node.rpdo.read()
    node.sdo[cia.MODES_OF_OPERATION].raw = cia.CST_MODE
    node.nmt.state = "OPERATIONAL"
    return node


def send_rpdo(node, controlword: int, torque_permille: int) -> None:
    node.rpdo[1]["Controlword"].raw = controlword
    node.rpdo[1]["Target torque"].raw = torque_permille
    node.rpdo[1].transmit()


def test_boot_up_on_start_and_after_an_addressed_reset_communication():
    with drives_on_virtual_bus() as bench:
        node = bench.remote(2)
        node.sdo[cia.HEARTBEAT_PRODUCER].raw = 0  # the drive still answers SDO
        node.nmt.send_command(0x82)  # reset communication, node 2 only
        node.nmt.wait_for_bootup(REPLY_TIMEOUT_S)
        assert node.sdo[cia.MODES_DISPLAY].raw == cia.NO_MODE
        assert bench.rig.drives[1].nmt.state == "PRE-OPERATIONAL"


def test_a_reset_communication_restores_the_pdo_defaults():
    with drives_on_virtual_bus() as bench:
        node = bench.remote(1)
        node.tpdo.read()
        node.tpdo[1].enabled = False
        node.tpdo[1].save()
        assert node.sdo[0x1800][1].raw & cia.PDO_DISABLED
        node.nmt.send_command(0x82)
        node.nmt.wait_for_bootup(REPLY_TIMEOUT_S)
        assert not node.sdo[0x1800][1].raw & cia.PDO_DISABLED


def test_sdo_reads_units_and_state_from_the_drive():
    with drives_on_virtual_bus() as bench:
        node = bench.remote(1)
        assert node.sdo[cia.SUPPORTED_MODES].raw & cia.CST_SUPPORTED_BIT
        assert node.sdo[cia.RATED_TORQUE].raw == 10_000
        assert node.sdo[cia.MAX_TORQUE].raw == 15_000  # 150 Nm of 10 Nm
        assert bench.remote(2).sdo[cia.RATED_TORQUE].raw == 1_000
        assert node.sdo[cia.STATUSWORD].raw & 0x4F == 0x40  # SWITCH ON DISABLED
        ipr = cia.increments_per_rad(node.sdo[0x608F][1].raw)
        assert node.sdo[cia.POSITION_ACTUAL].raw == round(math.pi / 6 * ipr)
        period = cia.interpolation_seconds(node.sdo[0x60C2][1].raw, node.sdo[0x60C2][2].raw)
        assert period == pytest.approx(0.02)


def test_only_no_mode_and_cst_are_accepted():
    with drives_on_virtual_bus() as bench:
        node = bench.remote(1)
        with pytest.raises(SdoAbortedError) as err:
            node.sdo[cia.MODES_OF_OPERATION].raw = 4  # profile torque
        assert err.value.code == 0x06090030
        node.sdo[cia.MODES_OF_OPERATION].raw = cia.CST_MODE
        assert node.sdo[cia.MODES_DISPLAY].raw == cia.CST_MODE


def test_a_remap_while_the_pdo_is_enabled_is_refused_with_an_sdo_abort():
    with drives_on_virtual_bus() as bench:
        node = bench.remote(1)
        entry = cia.pdo_entry(cia.MODES_OF_OPERATION, 0, 8)
        for index, sub, value in ((0x1600, 1, entry), (0x1600, 0, 1), (0x1A01, 2, entry)):
            with pytest.raises(SdoAbortedError) as err:
                node.sdo[index][sub].raw = value
            assert err.value.code == 0x08000022
        with pytest.raises(SdoAbortedError) as err:
            node.sdo[0x1400][1].raw = 0x300 + 1  # another COB-ID while enabled
        assert err.value.code == 0x06090030
        node.rpdo.read()
        assert [v.index for v in node.rpdo[1]] == [cia.CONTROLWORD, cia.TARGET_TORQUE]


def test_the_cia301_remap_procedure_is_taken_and_bad_maps_are_refused():
    with drives_on_virtual_bus() as bench:
        node = bench.remote(1)
        node.tpdo.read()
        tpdo3 = node.tpdo[3]
        tpdo3.clear()
        tpdo3.add_variable(cia.MODES_DISPLAY)
        tpdo3.add_variable(cia.ERROR_CODE)
        tpdo3.enabled = True
        tpdo3.trans_type = 1
        tpdo3.save()  # disable, sub0 = 0, entries, sub0 = n, enable
        node.tpdo.read()
        assert [v.index for v in node.tpdo[3]] == [cia.MODES_DISPLAY, cia.ERROR_CODE]
        node.sdo[0x1802][1].raw = node.tpdo[3].cob_id | cia.PDO_DISABLED
        node.sdo[0x1A02][0].raw = 0
        with pytest.raises(SdoAbortedError) as err:  # an entry while sub0 != 0
            node.sdo[0x1A02][1].raw = cia.pdo_entry(cia.STATUSWORD, 0, 16)
            node.sdo[0x1A02][0].raw = 1
            node.sdo[0x1A02][2].raw = cia.pdo_entry(cia.STATUSWORD, 0, 16)
        assert err.value.code == 0x08000022
        node.sdo[0x1A02][0].raw = 0
        node.sdo[0x1A02][1].raw = cia.pdo_entry(cia.RATED_TORQUE, 0, 32)  # not mappable
        with pytest.raises(SdoAbortedError) as err:
            node.sdo[0x1A02][0].raw = 1
        assert err.value.code == 0x06040041
        for sub in range(1, 4):
            node.sdo[0x1A02][sub].raw = cia.pdo_entry(cia.POSITION_ACTUAL, 0, 32)
        with pytest.raises(SdoAbortedError) as err:
            node.sdo[0x1A02][0].raw = 3  # 96 bits
        assert err.value.code == 0x06040042
        node.rpdo.read()
        node.sdo[0x1401][1].raw = 0x301 | cia.PDO_DISABLED
        node.sdo[0x1601][1].raw = cia.pdo_entry(cia.STATUSWORD, 0, 16)  # read-only in an RPDO
        with pytest.raises(SdoAbortedError) as err:
            node.sdo[0x1601][0].raw = 1
        assert err.value.code == 0x06040041


def test_an_rpdo_between_syncs_has_no_effect_until_the_sync():
    with drives_on_virtual_bus() as bench:
        node, other = operational(bench, 1), operational(bench, 2)
        for word in (SHUTDOWN, SWITCH_ON, ENABLE):
            send_rpdo(node, word, 0)
            send_rpdo(other, word, 0)
            sync_and_wait(bench, node.tpdo[1], node.tpdo[2], other.tpdo[1])
        assert node.tpdo[1]["Statusword"].raw & 0x6F == 0x27
        drive = bench.rig.drives[0]
        send_rpdo(node, ENABLE, 1234)
        # The SDO answer comes after the RPDO was handled (one channel, in order) ...
        assert node.sdo[cia.TORQUE_ACTUAL].raw == 0
        assert node.sdo[cia.TARGET_TORQUE].raw == 0  # ... and it is not in the dictionary yet
        assert drive.torque_nm() == 0.0
        sync_and_wait(bench, node.tpdo[1], node.tpdo[2])
        assert node.tpdo[2]["Torque actual value"].raw == 1234
        assert node.sdo[cia.TARGET_TORQUE].raw == 1234
        assert drive.torque_nm() == pytest.approx(12.34)
        sync_and_wait(bench, node.tpdo[1], node.tpdo[2])
        assert node.tpdo[2]["Velocity actual value"].raw > 0  # the torque acted after that SYNC


def test_the_newest_rpdo_before_a_sync_wins():
    with drives_on_virtual_bus() as bench:
        node = operational(bench, 2)
        for word in (SHUTDOWN, ENABLE):
            send_rpdo(node, word, 0)
            sync_and_wait(bench, node.tpdo[1])
        for torque in (100, -250, 700):
            send_rpdo(node, ENABLE, torque)
        sync_and_wait(bench, node.tpdo[2])
        assert node.tpdo[2]["Torque actual value"].raw == 700


def test_target_torque_is_limited_by_max_torque():
    with drives_on_virtual_bus() as bench:
        node = operational(bench, 1)
        node.sdo[cia.MAX_TORQUE].raw = 500
        for word in (SHUTDOWN, ENABLE):
            send_rpdo(node, word, -3000)
            sync_and_wait(bench, node.tpdo[2])
        assert node.tpdo[2]["Torque actual value"].raw == -500


def test_no_pdo_outside_operational_and_a_short_rpdo_is_counted():
    with drives_on_virtual_bus() as bench:
        node = bench.remote(1)
        node.tpdo.read()
        node.rpdo.read()
        received: queue.Queue[can.Message] = queue.Queue()
        bench.master.subscribe(node.tpdo[1].cob_id, lambda *a: received.put(a))
        bench.master.sync.transmit()
        round_trip(node)  # the SYNC was handled
        assert received.empty()
        assert bench.rig.syncs == 1  # counted all the same
        node.nmt.state = "OPERATIONAL"
        bench.master.send_message(node.rpdo[1].cob_id, b"\x06\x00")  # 2 of 4 bytes
        node.emcy.reset()
        sync_and_wait(bench, node.tpdo[1])
        assert [e.code for e in node.emcy.log] == [0x8210]  # sent before the TPDO
        assert bench.rig.drives[0].pdos.rejected_rpdos == 1
        assert bench.rig.drives[0].power.state is PowerState.SWITCH_ON_DISABLED


def test_enable_with_another_interpolation_period_is_refused():
    with drives_on_virtual_bus(RigConfig()) as bench:
        node = operational(bench, 1)
        node.sdo[0x60C2][1].raw = 10  # 10 ms, the world steps 20 ms
        for word in (SHUTDOWN, SWITCH_ON, ENABLE):
            send_rpdo(node, word, 0)
            sync_and_wait(bench, node.tpdo[1])
        assert node.tpdo[1]["Statusword"].raw & 0x4F == 0x08  # FAULT
        assert node.sdo[cia.ERROR_CODE].raw == cia.EMCY_PARAMETER


def test_the_world_holds_until_every_drive_is_enabled_then_every_sync_steps_it():
    with drives_on_virtual_bus() as bench:
        nodes = [operational(bench, node_id) for node_id in (1, 2)]
        for word in (SHUTDOWN, SWITCH_ON, ENABLE):  # arming SYNCs: the scenario stays at t = 0
            for node in nodes:
                send_rpdo(node, word, 0)
            sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
            assert bench.rig.world.t == 0.0
        assert bench.rig.syncs == 3 and not bench.rig.running
        sync_and_wait(bench, *(n.tpdo[1] for n in nodes))  # both were enabled at the last one
        assert bench.rig.running
        assert bench.rig.world.t == pytest.approx(0.02)
        node = nodes[0]
        send_rpdo(node, SHUTDOWN, 0)  # one drive leaves OPERATION ENABLED: the clock runs on
        sync_and_wait(bench, node.tpdo[1])
        sync_and_wait(bench, node.tpdo[1])
        assert bench.rig.world.t == pytest.approx(0.06)


def test_each_step_is_stamped_with_its_sync_the_time_its_state_is_valid_for():
    """The world after SYNC k is the arm at that SYNC, where a drive samples its position: the
    step listener (the camera's poses) hears the SYNC's arrival, not the end of the step and
    the TPDOs after it (stamped there, f looked younger than the state it goes with)."""
    with drives_on_virtual_bus() as bench:
        heard: queue.Queue = queue.Queue()
        bench.rig.on_step = lambda syncs, world, stamp_ns: heard.put((syncs, world.t, stamp_ns))
        nodes = [operational(bench, node_id) for node_id in (1, 2)]
        for k, word in enumerate((SHUTDOWN, SWITCH_ON, ENABLE, ENABLE), start=1):
            bench.clock.t = 100.0 + 0.02 * k
            for node in nodes:
                send_rpdo(node, word, 0)
            sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
            syncs, t, stamp_ns = heard.get(timeout=REPLY_TIMEOUT_S)
            # the clock at the SYNC less its wait in the bus's queue (under one period)
            assert syncs == k and 0 <= round(bench.clock.t * 1e9) - stamp_ns < 20_000_000
        assert t == pytest.approx(0.02)


def test_a_sync_is_dated_by_its_arrival_when_its_wait_is_plausible():
    assert sync_arrival(100.0, 0.0015, 0.02) == pytest.approx(99.9985)
    assert sync_arrival(100.0, 0.0, 0.02) == 100.0
    # a wall-clock step or a bus without receive stamps: the handling time
    assert sync_arrival(100.0, -0.001, 0.02) == 100.0
    assert sync_arrival(100.0, 0.02, 0.02) == 100.0
    assert sync_arrival(100.0, 1.7e9, 0.02) == 100.0


def test_an_rpdo_value_the_drive_refuses_is_counted_and_the_sync_goes_on():
    with drives_on_virtual_bus() as bench:
        node = operational(bench, 1)
        rpdo2 = node.rpdo[2]
        rpdo2.clear()
        rpdo2.add_variable(cia.MODES_OF_OPERATION)
        rpdo2.enabled = True
        rpdo2.trans_type = 1
        rpdo2.save()
        rpdo2["Modes of operation"].raw = 4  # profile torque: not supported
        rpdo2.transmit()
        sync_and_wait(bench, node.tpdo[1], node.tpdo[2])  # the TPDOs still go out
        assert node.sdo[cia.MODES_DISPLAY].raw == cia.CST_MODE
        assert bench.rig.drives[0].pdos.rejected_rpdos == 1


def test_a_scenario_reset_starts_a_new_run_as_a_fresh_emulator():
    with drives_on_virtual_bus() as bench:
        nodes = [operational(bench, node_id) for node_id in (1, 2)]
        for word, torque in ((SHUTDOWN, 0), (ENABLE, 500), (ENABLE, 500), (ENABLE, 500)):
            for node in nodes:
                send_rpdo(node, word, torque)
            sync_and_wait(bench, *(n.tpdo[1] for n in nodes))
        bench.rig.drives[1].fault(cia.EMCY_SYNC)
        assert bench.rig.world.t > 0 and bench.rig.world.q[0] != pytest.approx(math.pi / 6)
        heard = []
        bench.rig.on_reset = heard.append
        assert bench.rig.request_reset(seed=7)
        assert heard == [7] and bench.rig.world.seed == 7
        assert bench.rig.world.t == 0.0 and bench.rig.syncs == 0 and not bench.rig.running
        for node, drive in zip(nodes, bench.rig.drives, strict=True):
            assert drive.power.state is PowerState.SWITCH_ON_DISABLED
            assert node.sdo[cia.ERROR_CODE].raw == 0
            assert node.sdo[cia.TORQUE_ACTUAL].raw == 0
        ipr = cia.increments_per_rad(1 << 20)
        assert nodes[0].sdo[cia.POSITION_ACTUAL].raw == round(math.pi / 6 * ipr)
