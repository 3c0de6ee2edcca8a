"""The cadence on a fake clock: absolute deadlines, no drift, skipped (never burst) periods."""

from __future__ import annotations

import gc
import json
import subprocess
import sys
import textwrap

import pytest

from rt_controller.runtime.cadence import Cadence, MonotonicClock
from rt_controller.runtime.realtime import GcPaused
from tests.support import REPO
from tests.support.fake_clock import FakeClock

P = 20_000_000  # 50 Hz


def test_releases_are_absolute_and_do_not_drift():
    clock = FakeClock(start_ns=1_000, wake_latency_ns=7_000)
    cad = Cadence(P, clock, start_ns=P)
    for k in range(100):
        tick = cad.wait()
        assert tick.index == k and tick.missed == 0
        assert tick.release_ns == P + k * P
        assert tick.lateness_ns == 7_000
        clock.advance(3_000_000)  # work shorter than a period


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


PROBE = textwrap.dedent(
    """
    import ctypes, ctypes.util, gc, json, os
    from rt_controller.runtime.realtime import apply_realtime

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    PR_GET_TIMERSLACK = 30
    rep = apply_realtime(priority=10, cpu=0, lock_memory=False)
    print(json.dumps({
        "applied": rep.applied,
        "warnings": rep.warnings,
        "policy": os.sched_getscheduler(0),
        "fifo": os.SCHED_FIFO,
        "affinity": sorted(os.sched_getaffinity(0)),
        "slack_ns": libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0),
        "frozen": gc.get_freeze_count(),
    }))
    """
)


def test_realtime_settings_are_best_effort():
    """``apply_realtime`` in a child process (the settings are per process and would otherwise
    leak into the rest of the session): every setting asked for is reported exactly once,
    applied or refused with a reason, and what it reports as applied is what the kernel says."""
    done = subprocess.run(
        [sys.executable, "-c", PROBE],
        capture_output=True,
        text=True,
        check=False,
        cwd=REPO,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    applied, warnings = got["applied"], got["warnings"]
    assert all(isinstance(w, str) and w for w in warnings)
    fifo_slack = 0 if got["policy"] == got["fifo"] else 1
    settings = {  # name -> (text when applied, start of the warning when refused, kernel says)
        "fifo": ("SCHED_FIFO priority 10", "SCHED_FIFO refused", got["policy"] == got["fifo"]),
        "cpu": ("pinned to CPU 0", "CPU affinity 0 refused", got["affinity"] == [0]),
        # Linux >= 6.7 runs SCHED_FIFO tasks with no timer slack at all (and reports 0)
        "slack": ("timer slack 1 ns", "timer slack refused", got["slack_ns"] in (1, fifo_slack)),
    }
    for name, (ok_text, refused, in_effect) in settings.items():
        n_ok = applied.count(ok_text)
        n_refused = sum(w.startswith(refused) for w in warnings)
        assert n_ok + n_refused == 1, (name, applied, warnings)
        assert bool(n_ok) == in_effect, (name, got)
    assert "GC heap frozen" in applied and got["frozen"] > 0
    assert not any("mlockall" in s for s in applied + warnings)  # lock_memory=False
    assert len(applied) + len(warnings) == 4  # nothing else reported


def test_gc_paused_restores_the_collector():
    was = gc.isenabled()
    try:
        for start in (True, False):
            (gc.enable if start else gc.disable)()
            with GcPaused():
                assert not gc.isenabled()
            assert gc.isenabled() == start
    finally:
        (gc.enable if was else gc.disable)()


def test_the_wait_for_a_release_runs_the_idle_work_until_the_spin_window():
    """MonotonicClock with ``idle``: called (with the spin window's start) until that time has
    come, then the rest is spun; the release is never before the deadline. Cadence passes it."""
    import time

    clock = MonotonicClock(spin_ns=200_000)
    calls: list[int] = []

    def idle(until_ns: int) -> None:
        calls.append(until_ns)
        time.sleep(max(0, until_ns - time.monotonic_ns()) / 2e9)  # returns early: called again

    deadline = time.monotonic_ns() + 5_000_000
    clock.sleep_until(deadline, idle)
    assert time.monotonic_ns() >= deadline
    assert calls and set(calls) == {deadline - 200_000}
    cadence = Cadence(2_000_000, clock)
    seen: list[int] = []
    tick = cadence.wait(seen.append)
    assert tick.wake_ns >= tick.release_ns
    # the spin window of the release it slept to: on the grid, at or before the tick's own (a
    # wake-up a whole period late moves the tick to the current period, counted as missed)
    (slept_to,) = {s + 200_000 for s in seen}
    assert (slept_to - cadence.start_ns) % 2_000_000 == 0 and slept_to <= tick.release_ns
    assert (tick.release_ns - slept_to) // 2_000_000 <= tick.missed
