"""The compiled per-tick rule (``control/decide_kernel.py``) decides what the rule spelt out in
Python on the law objects decides (``tests/support/python_rule.py``, the oracle), on every
branch: the law for pbc, ioc and rhc, the hold, no state, a drive not enabled, the delay
compensation, C/GMRES's fallback, a law switch; and its outputs are what the record needs."""

from __future__ import annotations

import numpy as np
import pytest

from hal.config import LAW_NAMES, RigConfig
from rt_controller.control.controller import Controller, Decision
from rt_controller.control.state import OUTPUTS
from tests.support.python_rule import PythonRule

SAME = 1e-12
"""Both paths call the same compiled kernels in the same order on one machine: measured equal
to the last bit (0.0) here; the bound only leaves room for NumPy's own 2x2 products in the
Python path's closed-form laws and hold, which another BLAS may round differently."""


def scenario(cfg: RigConfig, ticks: int, seed: int = 1):
    """Per-tick inputs that visit every branch: noisy states converging, stale features, no
    state, a disarmed drive, and state and feature ages."""
    rng = np.random.default_rng(seed)
    q0, dq0, f0 = (np.array(v, float) for v in (cfg.scenario.q0, cfg.scenario.dq0, cfg.scenario.f0))
    for k in range(ticks):
        t = 0.02 * k
        yield (
            t,
            q0 + rng.normal(0, 0.01, 2),
            dq0 + rng.normal(0, 0.1, 2),
            f0 * (1 - k / ticks) + rng.normal(0, 1, 2),
            {
                "f_stale": k % 37 == 5,
                "state_stale": k % 53 == 7,
                "drive_mode": "disarmed" if k % 71 == 9 else "enabled",
                "state_age_s": 0.004 * (k % 5),
                "feature_age_s": 0.01 * (k % 3),
                "now_s": t + 0.0003,
            },
        )


def diff(a: Decision, b: Decision) -> float:
    """The largest difference over every declared output (the same ones NaN on both: what
    the branch did not act on); the mode, the flags and the iterations equal."""
    assert a.mode == b.mode
    d = 0.0
    for f in OUTPUTS:
        if f.record == "law":
            continue  # the mode: compared by name above
        va, vb = np.atleast_1d(getattr(a, f.name)), np.atleast_1d(getattr(b, f.name))
        assert np.array_equal(np.isnan(va), np.isnan(vb)), f.name
        if f.record in ("boolean", "integer"):
            assert np.array_equal(va, vb, equal_nan=True), f.name
        elif not np.all(np.isnan(va)):
            d = max(d, float(np.nanmax(np.abs(va - vb))))
    return d


@pytest.mark.parametrize("law", LAW_NAMES)
def test_the_compiled_rule_decides_what_the_python_rule_decides(law: str):
    cfg = RigConfig()
    compiled, python = Controller(cfg, law), PythonRule(cfg, law)
    compiled.warm_up()
    python.warm_up()
    modes = set()
    worst = 0.0
    for t, q, dq, f, kw in scenario(cfg, 300):
        a, b = compiled.decide(t, q, dq, f, **kw), python.decide(t, q, dq, f, **kw)
        worst = max(worst, diff(a, b))
        modes.add(a.mode)
    assert modes == {"control", "hold", "no_state", "disarmed"}
    assert worst <= SAME
    assert len(compiled.rule) == len(python.predictor) == 300


def test_a_fallback_and_a_law_switch_match_too():
    """A residual bound no solve meets: every rhc tick falls back to eq. (27), clipped; then a
    switch to ioc and back to rhc, at the same ticks on both paths."""
    cfg = RigConfig().with_overrides({"controller.law": "rhc", "rhc.residual_bound": 1e-300})
    compiled, python = Controller(cfg), PythonRule(cfg, "rhc")
    ioc = cfg.with_overrides({"controller.law": "ioc"})
    fallbacks = 0
    for k, (t, q, dq, f, kw) in enumerate(scenario(cfg, 120, seed=2)):
        if k in (40, 80):
            new = ioc if k == 40 else cfg
            compiled.reconfigure(new)
            python.reconfigure(new)  # a new law object
            assert python.law == new.controller.law
        a, b = compiled.decide(t, q, dq, f, **kw), python.decide(t, q, dq, f, **kw)
        assert diff(a, b) <= SAME
        if a.mode == "control" and a.fallback:
            fallbacks += 1
            assert np.all(np.abs(a.u) <= np.asarray(cfg.rhc.u_max))
    assert fallbacks > 50


def test_a_reset_forgets_the_warm_start_and_the_history():
    cfg = RigConfig().with_overrides({"controller.law": "rhc"})
    ctl = Controller(cfg)
    runs = []
    for _ in range(2):
        runs.append([ctl.decide(t, q, dq, f, **kw).tau for t, q, dq, f, kw in scenario(cfg, 60)])
        assert len(ctl.rule) == 60
        ctl.reset()
        assert len(ctl.rule) == 0
    assert np.array_equal(np.array(runs[0]), np.array(runs[1]))  # one machine: bit-identical
