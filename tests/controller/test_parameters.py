"""The parameter layer's judging rules and hand-over (rt_controller/calibration/parameters.py)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from hal.config import RigConfig
from rt_controller.calibration.parameters import (
    TUNABLE,
    ParameterRefused,
    ParameterService,
    Request,
    accepted_changes,
    judge,
    refusal,
)
from rt_controller.control.controller import Controller


def test_tunable_keys_are_config_keys_and_others_are_refused_with_reason():
    known = RigConfig().to_dict()
    for key in TUNABLE:
        section, _, name = key.partition(".")
        assert name in known[section], key
    assert "restart" in refusal("rates.control_hz")
    assert "transport" in refusal("transport.key_file")
    assert "geometry" in refusal("robot.l1")
    assert "unknown" in refusal("gains.nope")
    assert refusal("gains.kp") is None


def test_judge_applies_the_toml_rules():
    cfg = RigConfig()
    new = judge(cfg, {"gains.kp": 0.2, "gains.alpha": [0.1, 0.2]})
    assert new.gains.kp == 0.2 and new.gains.alpha == ((0.1, 0.0), (0.0, 0.2))
    with pytest.raises(ParameterRefused, match=r"gains\.alpha"):
        judge(cfg, {"gains.alpha": [[1.0, 2.0], [2.0, 1.0]]})  # not positive definite
    with pytest.raises(ParameterRefused, match=r"gains\.kp"):
        judge(cfg, {"gains.kp": -1.0})
    with pytest.raises(ParameterRefused, match=r"not online-tunable"):
        judge(cfg, {"gains.kp": 0.2, "rates.control_hz": 100.0})
    with pytest.raises(ParameterRefused, match="law"):
        judge(cfg, {"controller.law": "pid"})


def test_a_change_set_applies_whole_or_not_at_all_and_at_its_tick():
    svc = ParameterService(RigConfig())
    replies = []
    svc.submit(
        Request({"gains.kp": 0.2, "gains.alpha": [[1, 2], [2, 1]]}, "t", reply=replies.append)
    )
    svc.submit(Request({"gains.kp": 0.3, "rhc.steps": 20}, "t", at_tick=5, reply=replies.append))
    cfg, outs = svc.due(0)
    assert cfg is None and len(outs) == 1 and not outs[0].accepted
    assert "gains.alpha" in outs[0].reason and svc.cfg.gains.kp == 0.13 and svc.param_set == 0
    assert svc.due(4) == (None, [])
    cfg, outs = svc.due(7)
    assert cfg.gains.kp == 0.3 and cfg.rhc.steps == 20 and svc.param_set == 1
    assert outs[0].tick == 7 and outs[0].accepted and outs[0].param_set == 1
    assert {c["key"]: (c["old"], c["new"]) for c in outs[0].changes} == {
        "gains.kp": (0.13, 0.3),
        "rhc.steps": (10, 20),
    }
    assert [r.accepted for r in replies] == [False, True]
    assert svc.counters.as_dict() == {"accepted": 1, "refused": 1, "unauthenticated": 0}
    assert accepted_changes([o.record() for o in outs]) == [(7, {"gains.kp": 0.3, "rhc.steps": 20})]


def test_requests_from_other_threads_are_handed_over():
    svc = ParameterService(RigConfig())
    threads = [
        threading.Thread(target=svc.submit, args=(Request({"gains.kp": 0.1 + i / 100}, f"t{i}"),))
        for i in range(8)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    cfg, outs = svc.due(3)
    assert len(outs) == 8 and all(o.accepted and o.tick == 3 for o in outs)
    assert svc.param_set == 8 and cfg is svc.cfg


@pytest.mark.parametrize("law", ["rhc", "ioc", "pbc"])
def test_reconfigure_rebuilds_the_law_and_keeps_the_torque_history(law):
    cfg = RigConfig()
    ctl = Controller(cfg)
    q, dq, f = np.array(cfg.scenario.q0), np.zeros(2), np.array(cfg.scenario.f0)
    ctl.decide(0.0, q, dq, f, f_stale=False, state_stale=False)
    n = len(ctl.rule)
    new = judge(cfg, {"controller.law": law, "gains.kp": 0.2})
    ctl.reconfigure(new)
    assert ctl.law == law and ctl.model.kp == 0.2 and len(ctl.rule) == n
    d = ctl.decide(0.02, q, dq, f, f_stale=False, state_stale=False)
    fresh = Controller(new).decide(0.02, q, dq, f, f_stale=False, state_stale=False)
    assert np.all(np.isfinite(d.tau)) and np.allclose(d.tau, fresh.tau)
