"""The CANopen section of hil report on a log whose raw CAN records are not all whole (a
hand-edited or foreign log: an id or a time stamp null or not a number): such a record is
counted as undecodable and left out of the timing, not a traceback."""

from __future__ import annotations

import pytest

from rt_controller.logtools.canopen_timing import canopen_timing


def _sync(t_ns):
    return {"t_ns": t_ns, "arbitration_id": 0x080, "data": ""}


@pytest.mark.parametrize(
    "bad",
    [
        {"t_ns": 30_000_000, "arbitration_id": None, "data": ""},
        {"t_ns": None, "arbitration_id": 0x080, "data": ""},
        {"t_ns": "soon", "arbitration_id": "0x80", "data": ""},
        {"arbitration_id": [1], "data": 5},
    ],
)
def test_a_broken_raw_record_is_undecodable_not_a_crash(bad):
    tx = [_sync(k * 20_000_000) for k in range(5)] + [bad]
    out = canopen_timing([], tx, period_s=0.02, nodes=(1, 2))
    assert out["sync"]["syncs"] == 5
    assert out["sync"]["interval_us"]["median"] == pytest.approx(20_000.0)
    assert out["undecodable"] == 1
