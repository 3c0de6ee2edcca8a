"""rt_controller.logtools.canopen_timing on hand-made frame lists with known time stamps:
SYNC jitter, SYNC-to-TPDO, PDO round trip, torque-to-effect (with a superseded target and one
never reported), the EMCYs and the drives' power states, and the window that leaves out the
SYNCs of boot and deactivation."""

from __future__ import annotations

import struct

import pytest

from rt_controller.logtools.canopen_timing import canopen_timing

PERIOD_NS = 20_000_000
NODES = (1, 2)


def frame(t_ns: int, cob_id: int, data: bytes = b"") -> dict:
    return {"t_ns": t_ns, "arbitration_id": cob_id, "data": data.hex(), "dlc": len(data)}


def tpdos(t_ns: int, torques: dict[int, int], statusword: int = 0x0637) -> list[dict]:
    out = []
    for i, node in enumerate(NODES):
        out.append(frame(t_ns + 100_000 * i, 0x180 + node, struct.pack("<Hi", statusword, 0)))
        out.append(
            frame(t_ns + 100_000 * i + 50_000, 0x280 + node, struct.pack("<ih", 0, torques[node]))
        )
    return out


def run(syncs_ns: list[int], targets: list[dict[int, int]], answer_us: int = 1000):
    """Per period: the RPDOs (targets), 10 µs later the SYNC, TPDOs ``answer_us`` after it
    reporting the target just latched."""
    tx, rx = [], []
    for t, target in zip(syncs_ns, targets, strict=True):
        for node in NODES:
            tx.append(frame(t - 10_000, 0x200 + node, struct.pack("<Hh", 0x0F, target[node])))
        tx.append(frame(t, 0x080))
        rx.extend(tpdos(t + answer_us * 1000 - 150_000, target))
    return rx, tx


def test_sync_jitter_is_the_interval_error_against_the_period():
    syncs = [0, 20_000_000, 40_500_000, 60_000_000, 80_000_000]
    rx, tx = run(syncs, [{1: 0, 2: 0}] * 5)
    out = canopen_timing(rx, tx, period_s=PERIOD_NS / 1e9, nodes=NODES)
    assert out["sync"]["syncs"] == 5
    errors = [0.0, 500.0, 500.0, 0.0]  # µs
    assert out["sync"]["period_error_us"]["max"] == pytest.approx(max(errors))
    assert out["sync"]["period_error_us"]["median"] == pytest.approx(250.0)
    assert out["sync"]["interval_us"]["median"] == pytest.approx(20_000.0)


def test_sync_to_tpdo_waits_for_every_drives_both_tpdos():
    syncs = [i * PERIOD_NS for i in range(4)]
    rx, tx = run(syncs, [{1: 0, 2: 0}] * 4, answer_us=1000)
    out = canopen_timing(rx, tx, period_s=0.02, nodes=NODES)
    # last TPDO (node 2's TPDO2) at sync + 1000 - 150 + 100 + 50 µs
    assert out["sync_to_tpdo_us"]["median"] == pytest.approx(1000.0)
    assert out["pdo_round_trip_us"]["median"] == pytest.approx(1010.0)  # from the RPDO
    assert out["answered"] == 4 and out["incomplete"] == 0
    rx = [f for f in rx if not (f["arbitration_id"] == 0x282 and f["t_ns"] > 3 * PERIOD_NS)]
    out = canopen_timing(rx, tx, period_s=0.02, nodes=NODES)
    assert out["answered"] == 3 and out["incomplete"] == 1


def test_torque_to_effect_from_the_new_target_to_the_torque_actual_reporting_it():
    syncs = [i * PERIOD_NS for i in range(4)]
    targets = [{1: 0, 2: 0}, {1: 100, 2: 0}, {1: 100, 2: -40}, {1: 100, 2: -40}]
    rx, tx = run(syncs, targets)
    out = canopen_timing(rx, tx, period_s=0.02, nodes=NODES)
    assert out["changes"] == 2 and out["superseded"] == 0 and out["never"] == 0
    # node 1: RPDO at sync - 10 µs, its TPDO2 at sync + 1000 - 150 + 50 µs
    assert out["torque_to_effect_us"]["median"] == pytest.approx((910.0 + 1010.0) / 2)
    # a drive that never reports the new value (torque off): counted, not timed
    rx = [f for f in rx if f["arbitration_id"] != 0x282]
    out = canopen_timing(rx, tx, period_s=0.02, nodes=NODES)
    assert out["never"] == 1 and out["changes"] == 1


def test_a_target_replaced_before_it_took_effect_is_superseded():
    tx = [
        frame(-1_000, 0x201, struct.pack("<Hh", 0x0F, 0)),  # the baseline
        frame(0, 0x201, struct.pack("<Hh", 0x0F, 50)),
        frame(1_000, 0x201, struct.pack("<Hh", 0x0F, 60)),
        frame(2_000, 0x080),
    ]
    rx = [frame(5_000, 0x281, struct.pack("<ih", 0, 60))]
    out = canopen_timing(rx, tx, period_s=0.02, nodes=(1,))
    assert out["superseded"] == 1 and out["changes"] == 1
    assert out["torque_to_effect_us"]["median"] == pytest.approx(4.0)


def test_the_window_leaves_out_boot_and_deactivation_syncs():
    syncs = [0, 1_000_000, 21_000_000, 41_000_000, 42_000_000]
    rx, tx = run(syncs, [{1: 0, 2: 0}] * 5)
    out = canopen_timing(rx, tx, period_s=0.02, nodes=NODES, window=(500_000, 41_500_000))
    assert out["sync"]["syncs"] == 3
    assert out["sync"]["period_error_us"]["max"] == pytest.approx(0.0)


def test_emcys_and_power_states_are_listed():
    tx = [frame(0, 0x080)]
    rx = [
        frame(1_000_000, 0x181, struct.pack("<Hi", 0x0637, 0)),
        frame(2_000_000, 0x081, struct.pack("<HB5s", 0x8700, 0x11, bytes(5))),
        frame(2_100_000, 0x181, struct.pack("<Hi", 0x0608, 0)),
        frame(3_000_000, 0x081, bytes(8)),
    ]
    out = canopen_timing(rx, tx, period_s=0.02, nodes=(1,), t0_ns=1_000_000)
    assert [(e["node"], e["code"], e["error_reset"]) for e in out["emcys"]] == [
        (1, "0x8700", False),
        (1, "0x0000", True),
    ]
    assert out["emcys"][0]["t_s"] == pytest.approx(0.001)
    assert out["drive_states"] == {"1": ["OPERATION ENABLED", "FAULT"]}


def test_frames_without_a_sync_are_not_a_canopen_log():
    assert canopen_timing([frame(0, 0x181, bytes(6))], [], period_s=0.02, nodes=NODES) is None
