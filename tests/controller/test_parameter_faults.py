"""A fault of the controller's own while it takes a change set (judging it, or answering it)
never ends the run: the request is counted as ``failed`` (the component's error), a set it
could not judge is refused with the fault named, and the next set is taken as usual."""

from __future__ import annotations

import pytest

from hal.config import RigConfig
from rt_controller.calibration.parameters import ParameterService, Request


def _broken_reply(outcome: object) -> None:
    raise ConnectionError("the zenoh query was dropped")


def test_an_answer_that_fails_leaves_the_change_in_force_and_is_counted() -> None:
    svc = ParameterService(RigConfig())
    svc.submit(Request({"gains.kp": 0.2}, reply=_broken_reply))
    cfg, outcomes = svc.due(5)
    assert cfg is not None and cfg.gains.kp == pytest.approx(0.2)
    assert [o.accepted for o in outcomes] == [True]
    assert svc.counters.as_dict()["failed"] == 1
    svc.submit(Request({"gains.kp": 0.3}))
    cfg, outcomes = svc.due(6)
    assert cfg is not None and cfg.gains.kp == pytest.approx(0.3)


def test_a_set_the_controller_cannot_judge_is_refused_with_the_fault_named() -> None:
    svc = ParameterService(RigConfig())
    answers: list[object] = []
    svc.submit(Request({("gains", "kp"): 0.2}, reply=answers.append))  # type: ignore[dict-item]
    cfg, outcomes = svc.due(5)
    assert cfg is None and svc.param_set == 0
    (out,) = outcomes
    assert not out.accepted and "controller failed" in (out.reason or "")
    assert answers == [out]
    assert svc.counters.as_dict()["failed"] == 1
    assert out.record()["changes"][0]["key"] == "('gains', 'kp')"  # the log can write it
