"""The CANopen section of a lockstep cia402 log: its SYNCs follow the world's steps, not a
clock, so their "period error" against the control period is not reported (it read as a
jitter of ~15 ms on a healthy lockstep run); a realtime log keeps it."""

from __future__ import annotations

import struct
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from hal.config import RigConfig
from rt_controller.logtools.canopen_timing import log_timing


def _frames(interval_ns: int, n: int):
    tx, rx = [], []
    for k in range(n):
        t = 1_000_000_000 + k * interval_ns
        tx.append(
            {"t_ns": t - 10_000, "arbitration_id": 0x201, "data": struct.pack("<Hh", 15, 0).hex()}
        )
        tx.append({"t_ns": t, "arbitration_id": 0x080, "data": ""})
        rx.append(
            {
                "t_ns": t + 500_000,
                "arbitration_id": 0x181,
                "data": struct.pack("<Hi", 0x0637, 0).hex(),
            }
        )
    return rx, tx


def _log(clock: str, interval_ns: int):
    base = RigConfig()
    cfg = replace(
        base,
        hardware=replace(base.hardware, profile="cia402"),
        controller=replace(base.controller, clock=clock),
    )
    rx, tx = _frames(interval_ns, 10)
    t = np.array([1_000_000_000 + k * interval_ns for k in range(10)], dtype=np.int64)
    cycles = {"t_ns": t, "cycle_us": np.full(10, 100.0)}
    return SimpleNamespace(
        config=cfg, can_rx=rx, can_tx=tx, cycles=cycles, run_info={"clock": clock}
    )


def test_a_lockstep_log_has_no_sync_period_error():
    out = log_timing(_log("lockstep", 5_000_000))  # SYNCs as fast as the world steps: 5 ms
    assert out["sync"]["interval_us"]["median"] == pytest.approx(5000.0)
    assert all(v is None for v in out["sync"]["period_error_us"].values())


def test_a_realtime_log_keeps_its_sync_period_error():
    out = log_timing(_log("realtime", 20_500_000))
    assert out["sync"]["period_error_us"]["median"] == pytest.approx(500.0)
