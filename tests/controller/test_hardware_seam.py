"""The control loop through the hardware seam alone (:class:`hal.hardware_interface.
HardwareInterface`): a scripted profile, a fake clock, the real pacers, rule and parameter
service. What the loop asks of a profile, in which order, and what it makes of the answers;
and that each profile of the product has the seam's methods with the seam's signatures."""

from __future__ import annotations

import dataclasses
import inspect
import threading
from typing import Any

import numpy as np
import pytest

from hal.config import RigConfig, load_config
from hal.hardware_interface import HardwareInterface, InputJudge, Observation, StopFlag
from rt_controller.calibration.parameters import ParameterService, Request
from rt_controller.control.controller import Controller
from rt_controller.runtime.cia402_hardware import Cia402Hardware
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.hardware import DspHardware
from rt_controller.runtime.loop import ControlLoop
from rt_controller.runtime.pacers import LockstepPacer, RealtimePacer
from tests.support.fake_clock import FakeClock
from tests.support.loop_seam import ListRecorder, at_rest

T0 = 1_000_000_000


class WaitingClock(FakeClock):
    """Runs the wait work once per wait, at its deadline, as the real clock's sleep does."""

    def sleep_until(self, deadline_ns: int, idle=None) -> None:
        if idle is not None:
            idle(deadline_ns)
        super().sleep_until(deadline_ns)


class ScriptedHardware:
    """A profile that logs every call of the seam: armed at the ``armed_at``-th activate
    call, a joint state at rest (``late`` reads: none new), lockstep steps from ``steps``."""

    def __init__(self, armed_at: int = 3, late: frozenset[int] = frozenset(), steps=()) -> None:
        self.calls: list[tuple[str, Any]] = []
        self.armed_at = armed_at
        self.late = late
        self.steps = list(steps)
        self.judges: list[tuple[float, float | None]] = []
        self.reads = 0

    def configure(self, stop: StopFlag) -> None:
        self.calls.append(("configure", None))

    def activate(self, now_ns: int) -> bool:
        self.calls.append(("activate", now_ns))
        return sum(c[0] == "activate" for c in self.calls) >= self.armed_at

    def wait_inputs(self, until_ns: int) -> None:
        self.calls.append(("wait_inputs", until_ns))

    def step(self, timeout_s: float) -> int | None:
        self.calls.append(("step", timeout_s))
        return self.steps.pop(0) if self.steps else None

    def why_silent(self) -> str:
        return ""

    def read(self, now_ns: int, judge: InputJudge) -> Observation:
        self.calls.append(("read", now_ns))
        self.judges.append((judge.state_limit_s, judge.status_limit_s))
        new = self.reads not in self.late
        self.reads += 1
        return at_rest(now_ns, new=new)

    def write(self, tau: tuple[float, float], *, sync: int | None, release_ns: int) -> None:
        self.calls.append(("write", (tau, sync, release_ns)))

    def command(self, action: str) -> str | None:
        self.calls.append(("command", action))
        return None

    def deactivate(self) -> None:
        self.calls.append(("deactivate", None))

    def diagnostics(self) -> dict[str, dict[str, Any]]:
        return {"can_rx": {}, "features": {}, "dsp": {}}


@pytest.fixture(scope="module")
def cfg() -> RigConfig:
    return load_config().with_overrides({"controller.law": "ioc"})


def _loop(cfg: RigConfig, hw: ScriptedHardware, lockstep: bool):
    ctx = RunContext(cfg, WaitingClock(T0), threading.Event(), RunCounters(), ListRecorder())
    pacer = (
        LockstepPacer(ctx, hw.step, hw.why_silent)
        if lockstep
        else RealtimePacer(ctx, hw.wait_inputs)
    )
    params = ParameterService(cfg)
    return ControlLoop(ctx, Controller(cfg), hw, pacer, params), ctx, params


def test_realtime_arms_on_the_cadence_and_its_armed_release_is_tick_0(cfg):
    """One activate call per period until armed; the release of the call that armed is tick 0
    (t = 0), then one read and one write per release, each on the next period, and the
    hardware's read-ahead between releases; the loop never activates again."""
    hw = ScriptedHardware(armed_at=3)
    loop, ctx, _ = _loop(cfg, hw, lockstep=False)
    loop.run(max_ticks=4)
    period = cfg.rates.control_period_ns
    names = [c[0] for c in hw.calls if c[0] != "wait_inputs"]
    assert names == ["activate"] * 3 + ["read", "write"] * 4
    arming = [c[1] for c in hw.calls if c[0] == "activate"]
    assert np.diff(arming).tolist() == [period, period]
    writes = [c[1] for c in hw.calls if c[0] == "write"]
    assert [w[2] - arming[-1] for w in writes] == [0, period, 2 * period, 3 * period]
    assert all(w[1] is None for w in writes)  # no sync in realtime
    assert [c["tick"] for c in ctx.recorder.cycles] == [0, 1, 2, 3]
    assert ctx.counters.ticks == 4
    waits = [i for i, c in enumerate(hw.calls) if c[0] == "wait_inputs"]
    assert len(waits) == 3  # the read-ahead: in each wait between releases, not while arming
    assert all(hw.calls[i - 1][0] == "write" and hw.calls[i + 1][0] == "read" for i in waits)


def test_lockstep_ticks_on_the_hardwares_steps_and_answers_each(cfg):
    """After arming, one release per step k: the write answers k; a gap in k is counted as
    missed periods; the run ends when the steps stop (the duration not reached: not clean)."""
    hw = ScriptedHardware(armed_at=2, steps=[0, 1, 3])
    loop, ctx, _ = _loop(cfg, hw, lockstep=True)
    ctx.counters.planned_ticks = 10
    loop.run(max_ticks=10)
    syncs = [c[1][1] for c in hw.calls if c[0] == "write"]
    assert syncs == [0, 1, 3]
    assert ctx.counters.missed_periods == 1 and ctx.counters.ticks == 3
    assert ctx.counters.end_reason.startswith("no Sync")
    assert [c[0] for c in hw.calls][:2] == ["activate", "activate"]


def test_a_stop_during_arming_runs_no_tick(cfg):
    hw = ScriptedHardware(armed_at=10**9)
    loop, ctx, _ = _loop(cfg, hw, lockstep=False)
    calls = 0
    activate = hw.activate

    def stop_after_five(now_ns: int) -> bool:
        nonlocal calls
        calls += 1
        if calls == 5:
            ctx.stop.set()
        return activate(now_ns)

    hw.activate = stop_after_five
    loop.run(max_ticks=None)
    assert calls == 5 and ctx.counters.ticks == 0
    assert not any(c[0] in ("read", "write") for c in hw.calls)


def test_late_states_are_counted_from_the_observation(cfg):
    hw = ScriptedHardware(armed_at=1, late=frozenset({2, 5}))
    loop, ctx, _ = _loop(cfg, hw, lockstep=False)
    loop.run(max_ticks=8)
    assert ctx.counters.late_states == 2


def test_a_parameter_change_reaches_the_judge_through_the_context(cfg):
    """An accepted change of ``controller.state_timeout_s`` at tick 3: the run context holds
    the new configuration, and the hardware's read at tick 3 is judged with it (the pacer
    reads it from the context; nobody pushes it)."""
    hw = ScriptedHardware(armed_at=1)
    loop, ctx, params = _loop(cfg, hw, lockstep=False)
    old = cfg.controller.state_timeout_s
    params.submit(Request({"controller.state_timeout_s": old * 2}, "test", at_tick=3))
    loop.run(max_ticks=5)
    assert [j[0] for j in hw.judges] == [old] * 3 + [old * 2] * 2
    assert ctx.cfg.controller.state_timeout_s == old * 2
    assert ctx.recorder.parameters and ctx.recorder.parameters[0]["accepted"]


SEAM = [
    name
    for name, member in inspect.getmembers(HardwareInterface, inspect.isfunction)
    if not name.startswith("_")
]


def test_the_seam_has_the_lifecycle():
    assert set(SEAM) >= {"configure", "activate", "read", "write", "deactivate", "step"}


@pytest.mark.parametrize(
    "profile", [DspHardware, Cia402Hardware, ScriptedHardware], ids=lambda p: p.__name__
)
def test_a_profile_has_every_method_of_the_seam_with_its_signature(profile):
    """Structural conformance (a Protocol is not checked at run time): same names, same
    parameters, in the same order and of the same kind."""
    for name in SEAM:
        want = inspect.signature(getattr(HardwareInterface, name))
        got = inspect.signature(getattr(profile, name))
        assert [(p.name, p.kind) for p in got.parameters.values()] == [
            (p.name, p.kind) for p in want.parameters.values()
        ], name


class MovingFeatures(ScriptedHardware):
    """f as the start of a hand-started run saw it: a 62 px step at 0.2 s (f held on one
    frame for a few ticks while the arm moved fast), then the target's jump at 3 s."""

    def read(self, now_ns: int, judge: InputJudge) -> Observation:
        t_s = self.reads / 50.0
        obs = super().read(now_ns, judge)
        f = (-120.0, -160.0) if t_s < 0.2 else (-70.0, -123.0) if t_s < 3.0 else (60.0, 40.0)
        return dataclasses.replace(obs, f=np.array(f))


def test_the_jump_is_seen_when_the_target_jumps_not_at_a_start_up_step(cfg):
    """A step of more than half the jump before ``scenario.jump_time`` is the arm's start, not
    the target's jump (a hand-started run reported jump_seen_s 0.22 for 3.02)."""
    hw = MovingFeatures(armed_at=1, steps=range(200))
    loop, ctx, _ = _loop(cfg, hw, lockstep=True)
    loop.run(max_ticks=200)
    assert ctx.counters.jump_seen_s == pytest.approx(3.0)
