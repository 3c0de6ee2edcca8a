"""The realtime cadence and pacer on a fake clock, at their edges: a wake-up later than a whole
period, an overrun that skips past the planned end, a duration shorter than a period, periods
lost before the first law tick, and a stop request that arrives during a wait. The loop runs
through the hardware seam with a scripted profile."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest

from hal.config import RigConfig, load_config
from hal.hardware_interface import InputJudge, Observation, StopFlag
from rt_controller.calibration.parameters import ParameterService
from rt_controller.control.controller import Controller
from rt_controller.runtime.cadence import Cadence
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.loop import ControlLoop
from rt_controller.runtime.pacers import RealtimePacer
from tests.support.fake_clock import FakeClock
from tests.support.loop_seam import ListRecorder, at_rest

P = 20_000_000  # 50 Hz
T0 = 1_000_000_000


class OversleepingClock(FakeClock):
    """A fake clock whose n-th wait (from 0) wakes ``late_ns`` after its deadline (a host that
    paused the process), every other one on time; ``on_wait`` is called in each wait."""

    def __init__(self, start_ns: int = 0, late: dict[int, int] | None = None, on_wait=None):
        super().__init__(start_ns)
        self.late = late or {}
        self.waits = 0
        self.on_wait = on_wait

    def sleep_until(self, deadline_ns: int, idle=None) -> None:
        n, self.waits = self.waits, self.waits + 1
        if self.on_wait is not None:
            self.on_wait(n)
        if deadline_ns > self.t:
            self.t = deadline_ns + self.late.get(n, 0)


class Hardware:
    """A profile armed at its ``armed_at``-th activate call; ``work`` adds time (ns) to the
    clock in the write of the given tick (by count of writes), ``activate_work`` in the given
    activate call (by count, from 1)."""

    def __init__(self, clock: FakeClock, armed_at: int = 3, work=None, activate_work=None):
        self.clock = clock
        self.armed_at = armed_at
        self.work: dict[int, int] = work or {}
        self.activate_work: dict[int, int] = activate_work or {}
        self.activations = 0
        self.writes = 0
        self.activate_after_stop = 0
        self.stop: StopFlag | None = None

    def configure(self, stop: StopFlag) -> None:
        self.stop = stop

    def activate(self, now_ns: int) -> bool:
        self.activations += 1
        if self.stop is not None and self.stop.is_set():
            self.activate_after_stop += 1
        self.clock.advance(self.activate_work.get(self.activations, 0))
        return self.activations >= self.armed_at

    def wait_inputs(self, until_ns: int) -> None:
        pass

    def step(self, timeout_s: float) -> int | None:
        return None

    def why_silent(self) -> str:
        return ""

    def read(self, now_ns: int, judge: InputJudge) -> Observation:
        return at_rest(now_ns)

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> None:
        self.clock.advance(self.work.get(self.writes, 0))
        self.writes += 1

    def command(self, action: str) -> str | None:
        return None

    def deactivate(self) -> None:
        pass

    def diagnostics(self) -> dict[str, dict[str, Any]]:
        return {"can_rx": {}, "features": {}, "dsp": {}}


@pytest.fixture(scope="module")
def cfg() -> RigConfig:
    cfg = load_config().with_overrides({"controller.law": "ioc"})
    assert cfg.rates.control_period_ns == P
    return cfg


def _loop(cfg: RigConfig, clock: FakeClock, hw: Hardware):
    ctx = RunContext(cfg, clock, threading.Event(), RunCounters(), ListRecorder())
    hw.configure(ctx.stop)
    pacer = RealtimePacer(ctx, hw.wait_inputs)
    return ControlLoop(ctx, Controller(cfg), hw, pacer, ParameterService(cfg)), ctx


def _periods_accounted(ctx: RunContext) -> None:
    """Every period of the run from t = 0 to its last tick is a tick or a missed period, and
    each tick starts within its own period."""
    cycles = ctx.recorder.cycles
    assert ctx.counters.ticks + ctx.counters.missed_periods == cycles[-1]["tick"] + 1
    assert sum(c["missed_periods"] for c in cycles) == ctx.counters.missed_periods
    for c in cycles:
        assert 0 <= c["lateness_us"] * 1e3 < P, c


def test_a_wake_up_a_whole_period_late_skips_that_period_instead_of_bursting():
    """Woken 1.5 periods after release 1 (a paused host): release 1's period is over, so the
    tick is release 2's, half a period late, with one missed period; release 3 is on time."""
    clock = OversleepingClock(late={1: P + P // 2})
    cad = Cadence(P, clock, start_ns=0)
    ticks = [cad.wait() for _ in range(3)]
    assert [(t.index, t.missed) for t in ticks] == [(0, 0), (2, 1), (3, 0)]
    assert [t.lateness_ns for t in ticks] == [0, P // 2, 0]
    assert ticks[2].wake_ns - ticks[1].wake_ns == P // 2  # not back to back


def test_a_loop_tick_never_starts_after_its_own_period(cfg):
    """Through the loop: a late wake-up of 2.25 periods is one tick and two missed periods,
    never a stale tick followed at once by the next one."""
    clock = OversleepingClock(T0, late={5: 2 * P + P // 4})
    hw = Hardware(clock, armed_at=3)
    loop, ctx = _loop(cfg, clock, hw)
    loop.run(max_ticks=10)
    _periods_accounted(ctx)
    assert ctx.counters.missed_periods == 2
    wakes = [c["t_ns"] for c in ctx.recorder.cycles]
    assert min(np.diff(wakes)) >= P - P // 4


def test_an_overrun_never_runs_a_tick_past_the_planned_end(cfg):
    """10 planned periods; tick 8 overruns by 2.5 periods: the run ends with it (periods 9 and
    10 are gone), it never runs a tick at t = 10 periods, past its duration."""
    clock = FakeClock(T0)
    hw = Hardware(clock, armed_at=3, work={8: 2 * P + P // 2})
    loop, ctx = _loop(cfg, clock, hw)
    loop.run(max_ticks=10)
    ticks = [c["tick"] for c in ctx.recorder.cycles]
    assert ticks == list(range(9))
    assert all(c["sim_time_s"] < 10 * P / 1e9 for c in ctx.recorder.cycles)
    assert ctx.counters.deadline_misses == 1


def test_a_duration_shorter_than_a_period_runs_no_tick(cfg):
    """``planned_ticks`` 0 (e.g. ``--duration 0.5`` at ``rates.control_hz = 1``): no tick, as
    in lockstep."""
    clock = FakeClock(T0)
    hw = Hardware(clock, armed_at=3)
    loop, ctx = _loop(cfg, clock, hw)
    loop.run(max_ticks=0)
    assert ctx.counters.ticks == 0 and ctx.recorder.cycles == []
    assert hw.writes == 0


@pytest.mark.parametrize("armed_at", [1, 3])
def test_time_before_the_first_law_tick_is_not_missed_periods(cfg, armed_at):
    """Warm-up and configure take 5 s after the pacer was built, and the arming step before
    the one that armed took 2.5 periods: none of it is a missed period of the run (tick 0
    is t = 0; nothing before it is a period of the run)."""
    clock = FakeClock(T0)
    hw = Hardware(clock, armed_at=armed_at, activate_work={armed_at - 1: 2 * P + P // 2})
    loop, ctx = _loop(cfg, clock, hw)
    clock.advance(5_000_000_000)  # the daemon's warm-up and configure, after the pacer exists
    loop.run(max_ticks=5)
    assert [c["tick"] for c in ctx.recorder.cycles] == [0, 1, 2, 3, 4]
    assert ctx.counters.missed_periods == 0
    assert ctx.recorder.cycles[0]["missed_periods"] == 0
    _periods_accounted(ctx)


def test_a_stop_during_the_wait_for_an_arming_step_sends_nothing_more(cfg):
    """A stop request (Ctrl-C) that arrives while the pacer sleeps to the second arming step:
    the hardware is not activated again after it (no further ENABLE or command)."""
    holder: dict[str, threading.Event] = {}

    def stop_in_second_wait(n: int) -> None:
        if n == 1:
            holder["stop"].set()

    clock = OversleepingClock(T0, on_wait=stop_in_second_wait)
    hw = Hardware(clock, armed_at=10**9)
    loop, ctx = _loop(cfg, clock, hw)
    holder["stop"] = ctx.stop
    loop.run(max_ticks=None)
    assert hw.activations == 1 and hw.activate_after_stop == 0
    assert ctx.counters.ticks == 0


class WriteTimes(Hardware):
    """Keeps, for each write, the clock's time and the release it answers."""

    def __init__(self, clock: FakeClock, **kw: Any) -> None:
        super().__init__(clock, **kw)
        self.sent: list[tuple[int, int]] = []

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> None:
        self.sent.append((self.clock.now_ns(), release_ns))
        super().write(tau, sync=sync, release_ns=release_ns)


def test_an_arming_step_that_took_its_period_is_not_followed_by_a_burst(cfg):
    """The activate call that armed took 1.5 periods: tick 0 is the current period's, never
    two torque commands in one period at the hand-over, and tick 0's lateness is the time it
    started after its release (not the arming step's wake-up)."""
    clock = FakeClock(T0)
    hw = WriteTimes(clock, armed_at=3, activate_work={3: P + P // 2})
    loop, ctx = _loop(cfg, clock, hw)
    loop.run(max_ticks=4)
    periods = [(t - hw.sent[0][1]) // P for t, _ in hw.sent]
    assert len(set(periods)) == len(periods), periods  # one command per period
    assert all(0 <= t - release < P for t, release in hw.sent)
    _periods_accounted(ctx)
    assert ctx.recorder.cycles[0]["lateness_us"] * 1e3 == P // 2
    assert ctx.counters.deadline_misses == 0
