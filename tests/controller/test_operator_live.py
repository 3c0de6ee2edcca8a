"""Operator actions in the daemon's real loop on the fake clock: a mark is logged on
``/controller/events`` at its tick and listed by ``hil report``; a disarm takes the torque off at
its tick and holds it off (no automatic re-arm) until an arm; a scenario reset is refused."""

from __future__ import annotations

import numpy as np
import pytest

from hal.config import LAW_NAMES, load_config
from rt_controller.calibration.operator import Action
from rt_controller.logtools.deadline_report import summarize
from rt_controller.logtools.replay import replay_loaded
from tests.controller.test_parameters_live import run_submitting


def _run(tmp_path, cfg, actions, duration_s=3.0):
    def submit(service):
        for a in actions:
            service.actions.submit(a)

    return run_submitting(tmp_path, cfg, submit, duration_s)


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def test_mark_disarm_arm_and_a_refused_reset(tmp_path, cfg):
    _, log0, _ = _run(tmp_path / "a", cfg, [])
    t0 = int(log0.cycles["tick"][0])
    acts = [
        Action("mark", note="step", source="test", at_tick=t0 + 20),
        Action("disarm", source="test", at_tick=t0 + 40),
        Action("reset_scenario", source="test", at_tick=t0 + 50),
        Action("arm", source="test", at_tick=t0 + 60),
    ]
    _, log, _ = _run(tmp_path / "b", cfg, acts)
    events = [(e["action"], e["tick"], e["accepted"]) for e in log.events]
    assert events == [
        ("mark", t0 + 20, True),
        ("disarm", t0 + 40, True),
        ("reset_scenario", t0 + 50, False),
        ("arm", t0 + 60, True),
    ]
    assert "reset" in log.events[2]["reason"]
    ticks = np.asarray(log.cycles["tick"])
    laws = np.asarray(log.cycles["law"])  # the drive mode when the law did not run
    tau0, tau = np.asarray(log0.cycles["tau"]), np.asarray(log.cycles["tau"])
    k = int(np.flatnonzero(ticks == t0 + 40)[0])
    assert np.array_equal(tau0[:k], tau[:k])
    off = (ticks > t0 + 45) & (ticks < t0 + 60)
    assert off.any() and not np.isin(laws[off], LAW_NAMES).any()
    assert np.isin(laws[ticks > t0 + 80], LAW_NAMES).all()  # armed again
    result = replay_loaded(log, tol=1e-9)
    assert result.ok, result.failure_line()
    marks = summarize(log)["events"]
    assert [m["action"] for m in marks] == ["mark", "disarm", "reset_scenario", "arm"]
    assert marks[0]["note"] == "step" and marks[0]["tick"] == t0 + 20
    from rich.console import Console

    from rt_controller.logtools.report_text import render_text

    con = Console(record=True, width=200)
    render_text(summarize(log), con)
    text = con.export_text()
    assert "Operator events" in text and "step" in text


def test_report_plots_mark_the_changes_accepted_refused_and_events(tmp_path, cfg):
    from rt_controller.calibration.parameters import Request
    from rt_controller.logtools.deadline_report import time_axis
    from rt_controller.logtools.report_plots import change_lines, write_plots

    def submit(service):
        service.submit(Request({"gains.kp": 0.3}, "test", at_tick=30))
        service.submit(Request({"gains.kp": -1.0}, "test", at_tick=40))
        service.actions.submit(Action("mark", note="here", source="test", at_tick=50))

    _, log, _ = run_submitting(tmp_path, cfg, submit, 2.0)
    t, _ = time_axis(log)
    ticks = list(np.asarray(log.cycles["tick"]))
    lines = change_lines(log)
    assert [(ln.kind, ln.t) for ln in lines] == [
        ("accepted", t[ticks.index(30)]),
        ("refused", t[ticks.index(40)]),
        ("event", t[ticks.index(50)]),
    ]
    assert "gains.kp" in lines[0].label and "here" in lines[2].label
    assert len(write_plots(log, tmp_path / "figs")) >= 5
