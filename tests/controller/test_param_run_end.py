"""Requests the run will never reach (live-calibration.md): a change set or an action for a
tick past the run's planned end is refused at the first tick boundary, and those still waiting
when the run ends are refused as not applied; each is answered and in the log. Also what
``hil param set`` makes of its KEY=VALUE items, and the client's word on a late answer."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from hal.config import RigConfig, load_config
from rt_controller.calibration.link import ParameterLinkError, request
from rt_controller.calibration.operator import Action
from rt_controller.calibration.parameters import ParameterService, Request
from rt_controller.control.controller import Controller
from rt_controller.runtime.context import RunContext
from rt_controller.runtime.counters import RunCounters
from rt_controller.runtime.loop import ControlLoop
from rt_controller.runtime.pacers import RealtimePacer
from tests.controller.test_hardware_seam import T0, ListRecorder, ScriptedHardware, WaitingClock

ROOT = Path(__file__).resolve().parents[2]


class EventRecorder(ListRecorder):
    def __init__(self) -> None:
        super().__init__()
        self.events: list[dict[str, Any]] = []

    def record_event(self, record: dict[str, Any]) -> None:
        self.events.append(record)


class StoppingHardware(ScriptedHardware):
    """Sets the run's stop after ``writes`` writes (a run without a planned end)."""

    def __init__(self, stop: threading.Event, writes: int) -> None:
        super().__init__(armed_at=1)
        self.stop, self.left = stop, writes

    def write(self, tau, *, sync, release_ns) -> None:
        super().write(tau, sync=sync, release_ns=release_ns)
        self.left -= 1
        if self.left == 0:
            self.stop.set()


@pytest.fixture(scope="module")
def cfg() -> RigConfig:
    return load_config().with_overrides({"controller.law": "ioc"})


def _loop(cfg: RigConfig, hw=None, stop: threading.Event | None = None):
    stop = stop or threading.Event()
    ctx = RunContext(cfg, WaitingClock(T0), stop, RunCounters(), EventRecorder())
    hw = hw or ScriptedHardware(armed_at=1)
    params = ParameterService(cfg)
    loop = ControlLoop(ctx, Controller(cfg), hw, RealtimePacer(ctx, hw.wait_inputs), params)
    return loop, ctx.recorder, params


def test_a_request_past_the_planned_end_is_refused_at_the_first_boundary(cfg):
    loop, rec, params = _loop(cfg)
    answers: list[Any] = []
    params.submit(Request({"gains.kp": 0.14}, "test", at_tick=10**8, reply=answers.append))
    params.actions.submit(Action("mark", note="x", at_tick=10**8, reply=answers.append))
    loop.run(max_ticks=5)
    (p,) = rec.parameters
    (e,) = rec.events
    for r in (p, e):
        assert not r["accepted"] and r["tick"] == 0 and r["at_tick"] == 10**8
        assert "beyond the run's end: it plans 5 ticks (0..4)" in r["reason"]
    assert p["param_set"] == 0 and params.cfg.gains.kp == cfg.gains.kp
    assert len(answers) == 2 and params.counters.refused == 1
    assert ("command", "mark") not in loop.hw.calls


def test_a_request_for_the_last_planned_tick_still_waits_for_it(cfg):
    loop, rec, params = _loop(cfg)
    params.submit(Request({"gains.kp": 0.14}, "test", at_tick=4))
    loop.run(max_ticks=5)
    (p,) = rec.parameters
    assert p["accepted"] and p["tick"] == 4


def test_requests_still_waiting_when_the_run_ends_are_logged_as_not_applied(cfg):
    """A run without a planned end (stopped after 3 ticks): the waiting ones are answered
    and logged at its last tick."""
    stop = threading.Event()
    loop, rec, params = _loop(cfg, StoppingHardware(stop, writes=3), stop)
    answers: list[Any] = []
    params.submit(Request({"gains.kp": 0.14}, "test", at_tick=1000, reply=answers.append))
    params.actions.submit(Action("disarm", at_tick=1000, reply=answers.append))
    loop.run(max_ticks=None)
    (p,) = rec.parameters
    (e,) = rec.events
    for r in (p, e):
        assert not r["accepted"] and r["tick"] == 2
        assert r["reason"] == "not applied: the run ended at tick 2, before tick 1000"
    assert len(answers) == 2 and params.counters.refused == 1


class SlowSession:
    """zenoh's ``session.get`` that ends its query at the timeout without an answer."""

    def __init__(self) -> None:
        self.session = self

    def get(self, _key, payload, timeout):
        time.sleep(timeout)
        return []


def test_a_scheduled_request_unanswered_in_time_may_still_be_pending():
    """The controller answers a set for a later tick when that tick comes: the client's
    timeout does not say the link failed, and says the change may still take effect."""
    with pytest.raises(ParameterLinkError) as late:
        request(
            SlowSession(), bytes(32), "set", changes={"gains.kp": 0.2}, at_tick=9, timeout_s=0.05
        )
    text = str(late.value)
    assert "tick 9" in text and "may still be waiting" in text
    assert "is it running" not in text


def _hil_param(tmp_path: Path, *items: str) -> subprocess.CompletedProcess:
    key = tmp_path / "rig.key"
    key.write_text("00" * 32)
    key.chmod(0o600)
    argv = [sys.executable, "-m", "rt_controller.cli", "param", "set", *items]
    argv += ["--key-file", str(key), "--zenoh-endpoint", "tcp/127.0.0.1:9", "--timeout", "1"]
    return subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize(
    ("items", "said"),
    [
        (("gains.kp=0.2", "gains.kp=0.3"), "set: gains.kp given twice"),
        (("gains.kp=0.2", " gains.kp =0.3"), "set: gains.kp given twice"),
        (("gains.kp",), "set expects KEY=VALUE (e.g. gains.kp=0.2), got 'gains.kp'"),
    ],
)
def test_hil_param_set_refuses_a_bad_change_set_before_asking(tmp_path, items, said):
    got = _hil_param(tmp_path, *items)
    lines = got.stderr.strip().splitlines()
    assert got.returncode == 2 and len(lines) == 1, got.stderr
    assert lines[0].startswith(f"hil param: error: {said}"), got.stderr
    assert "--set" not in got.stderr
