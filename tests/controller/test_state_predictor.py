"""Delay compensation (:func:`rt_controller.control.model_kernels.compensate`, through the
oracle's :mod:`tests.support.state_predictor`): the compiled prediction
against an accurate integration of the nominal model (eq. 1), the torque history it uses, and
the property that matters: a law fed an old state and its age decides as on the fresh one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from hal.config import RigConfig
from rt_controller.control import model_kernels
from rt_controller.control.controller import Controller
from rt_controller.control.decide_kernel import CAPACITY
from rt_controller.control.state import pack_params
from tests.support.nominal_model import NumpyModel
from tests.support.state_predictor import StatePredictor, predictor_of


@pytest.fixture(scope="module")
def model() -> NumpyModel:
    return NumpyModel.from_config(RigConfig())


def _reference(model: NumpyModel, q, dq, pieces) -> tuple[np.ndarray, np.ndarray]:
    """(q, dq) after each (tau, seconds) piece, by an adaptive 8th-order integrator."""
    x = np.r_[q, dq]

    def rhs(_t, x, tau):
        q, dq = x[:2], x[2:]
        ddq = np.linalg.solve(model.M(q), tau - model.C(q, dq) @ dq - model.g(q))
        return np.r_[dq, ddq]

    for tau, dur in pieces:
        tau = np.asarray(tau, dtype=float)
        x = solve_ivp(rhs, (0.0, dur), x, method="DOP853", rtol=1e-12, atol=1e-12, args=(tau,)).y[
            :, -1
        ]
    return x[:2], x[2:]


def test_the_compiled_prediction_integrates_the_nominal_model(model):
    p = pack_params(model)
    q, dq = np.array([0.4, -1.1]), np.array([0.8, -3.0])
    pieces = [((1.5, -0.4), 0.0027), ((-2.0, 0.9), 0.02), ((0.3, 0.1), 0.0113)]
    taus = np.array([t for t, _ in pieces])
    durations = np.array([d for _, d in pieces])
    got_q, got_dq = model_kernels.predict(p, q, dq, taus, durations, 1e-3)
    ref_q, ref_dq = _reference(model, q, dq, pieces)
    assert np.allclose(got_q, ref_q, atol=1e-9) and np.allclose(got_dq, ref_dq, atol=1e-8)


def test_the_torques_held_over_the_age_come_from_the_history(model):
    pred = StatePredictor(pack_params(model), horizon_s=0.05)
    pred.sent(1.00, np.array([1.0, 0.1]))
    pred.sent(1.02, np.array([2.0, 0.2]))
    pred.sent(1.04, np.array([3.0, 0.3]))
    taus, durations = pred.segments(1.025, 1.05)  # the 1.02 torque, then 1.04's
    assert np.array_equal(taus, [[2.0, 0.2], [3.0, 0.3]])
    assert np.allclose(durations, [0.015, 0.01]) and np.isclose(durations.sum(), 0.025)
    taus, durations = pred.segments(0.99, 1.01)  # nothing sent yet, then 1.00's
    assert np.array_equal(taus, [[0.0, 0.0], [1.0, 0.1]])
    assert np.allclose(durations, [0.01, 0.01])


def test_old_torques_are_forgotten_but_the_one_still_held_is_kept(model):
    pred = StatePredictor(pack_params(model), horizon_s=0.05)
    n = CAPACITY + 10
    for k in range(n):
        pred.sent(k * 0.02, np.array([k, 0.0]))
    assert len(pred) <= 16  # dropped when the history filled up
    t_last = (n - 1) * 0.02
    taus, durations = pred.segments(t_last - 0.045, t_last + 0.005)
    assert taus[0][0] == n - 4  # held from t_last - 0.06, before the window opened
    assert [t[0] for t in taus] == [n - 4, n - 3, n - 2, n - 1]
    assert np.isclose(durations.sum(), 0.05)


def test_no_age_no_prediction(model):
    pred = StatePredictor(pack_params(model), horizon_s=0.05)
    q, dq = np.array([0.1, 0.2]), np.array([0.3, 0.4])
    assert pred.predict(1.0, q, dq, 0.0) == (q, dq)
    assert pred.predict(1.0, q, dq, -0.002) == (q, dq)
    with pytest.raises(ValueError, match="horizon"):
        StatePredictor(pack_params(model), horizon_s=0.0)


@pytest.mark.parametrize("law", ["ioc", "rhc"])
def test_a_law_fed_an_old_state_and_its_age_decides_as_on_the_fresh_state(model, law):
    """The nominal arm under the controller's own torques, run for 40 ticks; the controller is
    given each tick's state as it was 18 ms before, with that age. Its torques match a
    controller given the fresh state to integration accuracy; told nothing, it is far off."""
    cfg = RigConfig().with_overrides({"controller.law": law})
    fresh, compensated, blind = Controller(cfg), Controller(cfg), Controller(cfg)
    q, dq = np.array(cfg.scenario.q0), np.array(cfg.scenario.dq0)
    target = model.camera_position(q) + model.R_wc(q) @ np.array(cfg.scenario.f0) / model.gain
    period, age = 0.02, 0.018
    worst_comp = worst_blind = 0.0
    for k in range(40):
        t = k * period
        f = model.features(q, target)
        if k == 0:
            old_q, old_dq = q, dq
        d = fresh.decide(t, q, dq, f, f_stale=False, state_stale=False)
        dc = compensated.decide(
            t, old_q, old_dq, f, f_stale=False, state_stale=False, state_age_s=age if k else 0
        )
        db = blind.decide(t, old_q, old_dq, f, f_stale=False, state_stale=False)
        if k:
            worst_comp = max(worst_comp, float(np.abs(dc.tau - d.tau).max()))
            worst_blind = max(worst_blind, float(np.abs(db.tau - d.tau).max()))
        # the state 18 ms after this tick is what the next tick is given, 2 ms before its own
        old_q, old_dq = _reference(model, q, dq, [(d.tau, period - age)])
        q, dq = _reference(model, old_q, old_dq, [(d.tau, age)])
    assert worst_comp < 1e-6
    assert worst_blind > 0.05


def test_the_decision_carries_the_state_it_acted_on(model):
    """The record's ``q_pred``/``dq_pred``: the predicted state for the law and for the hold
    (its damper opposes that velocity), NaN when the drive is off."""
    cfg = RigConfig()
    ctl = Controller(cfg)
    q, dq, f = np.array(cfg.scenario.q0), np.array([0.5, -2.0]), np.array(cfg.scenario.f0)
    ctl.decide(0.0, q, dq, f, f_stale=False, state_stale=False)
    d = ctl.decide(0.02, q, dq, f, f_stale=False, state_stale=False, state_age_s=0.015)
    want = predictor_of(ctl).predict(0.02, q, dq, 0.015)  # same history: the 0.02 torque is later
    assert d.mode == "control" and not np.allclose(d.dq_pred, dq)
    assert np.allclose(d.q_pred, want[0]) and np.allclose(d.dq_pred, want[1])
    h = ctl.decide(0.04, q, dq, f, f_stale=True, state_stale=False, state_age_s=0.015)
    assert h.mode == "hold" and np.all(h.tau * h.dq_pred <= 0.0)
    assert not np.allclose(h.dq_pred, dq)
    off = ctl.decide(0.06, q, dq, f, f_stale=False, state_stale=False, drive_mode="fault")
    assert np.all(np.isnan(off.q_pred)) and np.all(np.isnan(off.dq_pred))


def test_a_static_target_seen_from_another_pose_is_what_the_camera_model_sees_there(model):
    p = pack_params(model)
    target = np.array([0.41, 0.23])
    q_then, q_now = np.array([0.5, -0.4]), np.array([0.62, -0.71])
    f_then = model.features(q_then, target)
    got = model_kernels.reproject(p, q_then, q_now, f_then)
    assert np.allclose(got, model.features(q_now, target), atol=1e-9)
    assert np.allclose(model_kernels.reproject(p, q_now, q_now, f_then), f_then, atol=1e-12)


def test_advancing_backwards_retraces_the_motion(model):
    pred = StatePredictor(pack_params(model), horizon_s=0.1)
    pred.sent(0.0, np.array([1.0, -0.2]))
    pred.sent(0.02, np.array([-0.5, 0.3]))
    q, dq = np.array([0.3, 0.9]), np.array([0.4, -1.5])
    q1, dq1 = pred.advance(q, dq, 0.005, 0.035)
    ref_q, ref_dq = _reference(model, q, dq, [((1.0, -0.2), 0.015), ((-0.5, 0.3), 0.015)])
    assert np.allclose(q1, ref_q, atol=1e-9) and np.allclose(dq1, ref_dq, atol=1e-8)
    q0, dq0 = pred.advance(q1, dq1, 0.035, 0.005)
    assert np.allclose(q0, q, atol=1e-9) and np.allclose(dq0, dq, atol=1e-8)


def test_a_state_older_than_the_horizon_is_predicted_over_the_horizon_only(model):
    pred = StatePredictor(pack_params(model), horizon_s=0.05)
    q, dq = np.array([0.3, 0.9]), np.array([0.4, -1.5])
    assert np.array_equal(pred.predict(1.0, q, dq, 0.5)[0], pred.predict(1.0, q, dq, 0.05)[0])


@pytest.mark.parametrize("law", ["ioc", "rhc"])
def test_a_law_fed_old_features_and_their_age_decides_as_on_fresh_ones(model, law):
    """Features captured 46 ms before the tick (older than the joint state, 12 ms) with both
    ages given: the same torques as on fresh measurements, to integration accuracy."""
    cfg = RigConfig().with_overrides({"controller.law": law})
    fresh, compensated = Controller(cfg), Controller(cfg)
    q, dq = np.array(cfg.scenario.q0), np.array(cfg.scenario.dq0)
    target = model.camera_position(q) + model.R_wc(q) @ np.array(cfg.scenario.f0) / model.gain
    period, state_age, f_age = 0.02, 0.012, 0.046
    history = [(0.0, q, dq)]  # (t, q, dq) at 2 ms resolution
    worst = 0.0
    for k in range(30):
        t = k * period

        def at(time):
            return min(history, key=lambda h: abs(h[0] - time))

        d = fresh.decide(t, q, dq, model.features(q, target), f_stale=False, state_stale=False)
        if k >= 3:
            _, q_s, dq_s = at(t - state_age)
            f_old = model.features(at(t - f_age)[1], target)
            dc = compensated.decide(
                t,
                q_s,
                dq_s,
                f_old,
                f_stale=False,
                state_stale=False,
                state_age_s=state_age,
                feature_age_s=f_age,
            )
            worst = max(worst, float(np.abs(dc.tau - d.tau).max()))
        else:
            compensated.decide(
                t, q, dq, model.features(q, target), f_stale=False, state_stale=False
            )
        for i in range(10):
            q, dq = _reference(model, q, dq, [(d.tau, period / 10)])
            history.append((t + (i + 1) * period / 10, q, dq))
    assert worst < 1e-6
