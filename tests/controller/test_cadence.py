"""The cadence on a fake clock: absolute deadlines, no drift, skipped (never burst) periods."""

from __future__ import annotations

import pytest

from rt_controller.runtime.cadence import Cadence, FakeClock, MonotonicClock
from rt_controller.runtime.realtime import GcPaused, apply_realtime

P = 20_000_000  # 50 Hz


def test_releases_are_absolute_and_do_not_drift():
    clock = FakeClock(start_ns=1_000, wake_latency_ns=7_000)
    cad = Cadence(P, clock, start_ns=P)
    for k in range(100):
        tick = cad.wait()
        assert tick.index == k
        assert tick.release_ns == P + k * P
        assert tick.lateness_ns == 7_000
        clock.advance(3_000_000)  # work shorter than a period
    assert cad.missed_total == 0


def test_overrun_skips_missed_periods_instead_of_bursting():
    clock = FakeClock()
    cad = Cadence(P, clock, start_ns=0)
    t0 = cad.wait()
    clock.advance(P + P // 2)  # tick 0 overran into tick 1's period: tick 1 runs late
    t1 = cad.wait()
    assert (t1.index, t1.missed) == (1, 0)
    assert t1.lateness_ns == P // 2
    clock.advance(3 * P + 5)  # tick 1 overran by more than two whole periods
    t2 = cad.wait()
    assert t2.missed == 2 and t2.index == 4
    assert t2.release_ns == t0.release_ns + 4 * P
    assert cad.missed_total == 2
    assert cad.deadline_of(t2) == t2.release_ns + P
    # After a skip the cadence is back on its grid.
    t3 = cad.wait()
    assert (t3.index, t3.missed, t3.lateness_ns) == (5, 0, 0)


def test_rejects_bad_period():
    with pytest.raises(ValueError, match="period must be positive"):
        Cadence(0, FakeClock())


def test_monotonic_clock_never_wakes_early():
    clock = MonotonicClock(spin_ns=200_000)
    cad = Cadence(2_000_000, clock)
    for _ in range(5):
        tick = cad.wait()
        assert tick.lateness_ns >= 0


def test_realtime_settings_are_best_effort():
    with GcPaused():
        rep = apply_realtime(priority=10, cpu=0, lock_memory=False)
    assert rep.applied or rep.warnings
    assert all(isinstance(w, str) for w in rep.warnings)
    import gc
    import os

    gc.unfreeze()
    # Leave the test process as it was.
    if "SCHED_FIFO priority 10" in rep.applied:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.sched_setaffinity(0, range(os.cpu_count() or 1))
