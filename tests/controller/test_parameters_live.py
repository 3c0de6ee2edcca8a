"""Online parameter changes in the daemon's real loop on the fake clock
(tests/controller/test_daemon_fake_clock.py's harness): taken at a tick boundary, logged on
``/controller/parameters``, counted in ``/diagnostics`` and replayed exactly."""

from __future__ import annotations

import numpy as np
import pytest

import rt_controller.runtime.daemon as daemon_mod
from hal.config import load_config
from rt_controller.calibration.parameters import Request
from rt_controller.logtools.deadline_report import summarize
from rt_controller.logtools.replay import replay_loaded
from tests.controller.test_daemon_fake_clock import run_daemon


def run_submitting(tmp_path, cfg, submit, duration_s=3.0):
    """A fake-clock run; ``submit(service)`` is called with the daemon's parameter service
    during its first tick (as another thread would: what it queues waits for its
    ``at_tick``)."""
    seen: dict = {}
    init = daemon_mod.ControllerDaemon.__init__

    def spy_init(self, *a, **kw):
        init(self, *a, **kw)
        seen["params"] = self.params

    def on_tick(ticks, node):
        if ticks == 0 and not seen.get("sent"):
            seen["sent"] = True
            submit(seen["params"])

    daemon_mod.ControllerDaemon.__init__ = spy_init
    try:
        return run_daemon(tmp_path, cfg, duration_s, {}, on_tick=on_tick)
    finally:
        daemon_mod.ControllerDaemon.__init__ = init


def _run(tmp_path, cfg, requests, duration_s=3.0):
    def submit(service):
        for r in requests:
            service.submit(r)

    return run_submitting(tmp_path, cfg, submit, duration_s)


def _at(log, tick):
    return int(np.flatnonzero(np.asarray(log.cycles["tick"]) == tick)[0])


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def test_kp_change_takes_effect_at_its_tick_is_logged_and_replays(tmp_path, cfg):
    base, log0, _ = _run(tmp_path / "a", cfg, [])
    t0 = int(log0.cycles["tick"][0])
    summary, log, node = _run(
        tmp_path / "b", cfg, [Request({"gains.kp": 0.3}, "test", at_tick=t0 + 100)]
    )
    assert summary["problems"] == [] and node.stats.watchdog_trips == 0
    (rec,) = log.parameters
    assert rec["accepted"] and rec["tick"] == t0 + 100 and rec["param_set"] == 1
    assert rec["changes"] == [{"key": "gains.kp", "old": 0.13, "new": 0.3}]
    ps = np.asarray(log.cycles["param_set"])
    k = _at(log, t0 + 100)
    assert set(ps[:k]) == {0} and set(ps[k:]) == {1}
    u0, u = np.asarray(log0.cycles["u"]), np.asarray(log.cycles["u"])
    assert np.array_equal(u0[:k], u[:k]) and not np.allclose(u0[k:], u[k:])
    assert summary["J"] != base["J"]
    result = replay_loaded(log, tol=1e-9)
    assert result.ok, result.failure_line()
    (listed,) = summarize(log)["parameter_changes"]
    assert listed["tick"] == t0 + 100 and listed["changes"] == "gains.kp 0.13 -> 0.3"
    final = log.diagnostics[-1]
    params = next(s for s in final["status"] if s["name"] == "parameters")
    assert params["values"] == {"accepted": 1, "refused": 0, "unauthenticated": 0}


def test_a_refused_change_leaves_the_cycles_as_untouched(tmp_path, cfg):
    _, log0, _ = _run(tmp_path / "a", cfg, [], duration_s=2.0)
    bad = Request({"gains.kp": 0.3, "gains.alpha": [[1.0, 2.0], [2.0, 1.0]]}, "test", at_tick=20)
    _, log, _ = _run(tmp_path / "b", cfg, [bad], duration_s=2.0)
    (rec,) = log.parameters
    assert not rec["accepted"] and "gains.alpha" in rec["reason"] and rec["param_set"] == 0
    for key in ("u", "tau", "q", "law", "param_set"):
        a, b = np.asarray(log0.cycles[key]), np.asarray(log.cycles[key])
        assert np.array_equal(a, b), key


def test_law_switch_rhc_ioc_rhc_at_one_tick_boundary_trips_nothing(tmp_path, cfg):
    rhc = cfg.with_overrides({"controller.law": "rhc"})
    reqs = [
        Request({"controller.law": "ioc"}, "test", at_tick=60),
        Request({"controller.law": "rhc", "rhc.horizon": 0.2, "rhc.steps": 8}, "test", at_tick=120),
    ]
    summary, log, node = _run(tmp_path, rhc, reqs)
    assert summary["problems"] == [] and node.stats.watchdog_trips == 0
    assert [(r["tick"], r["accepted"]) for r in log.parameters] == [(60, True), (120, True)]
    ticks, law = np.asarray(log.cycles["tick"]), np.asarray(log.cycles["law"])
    assert set(law[ticks < 60]) == {"rhc"}
    assert set(law[(ticks >= 60) & (ticks < 120)]) == {"ioc"}
    assert set(law[ticks >= 120]) == {"rhc"}
    assert not np.any(np.asarray(log.cycles["fallback"]))
    tau = np.asarray(log.cycles["tau"])
    assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= np.array(cfg.robot.tau_max))
    result = replay_loaded(log, tol=1e-9)
    assert result.ok, result.failure_line()
