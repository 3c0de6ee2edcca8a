"""The paper's analytic properties, checked numerically on the controller's nominal model."""

from __future__ import annotations

import numpy as np
import pytest

from hal.config import RigConfig
from tests.support.nominal_model import NumpyModel
from tests.support.python_laws import inverse_optimal, passivity_based

RNG = np.random.default_rng(20261122)
SAMPLES = 200


@pytest.fixture
def model(cfg: RigConfig) -> NumpyModel:
    return NumpyModel.from_config(cfg)


def random_states(n: int = SAMPLES):
    for _ in range(n):
        q = RNG.uniform(-np.pi, np.pi, 2)
        # Keep away from the singular elbow (Assumption 2: J_b nonsingular).
        if abs(np.sin(q[1])) < 0.1:
            q[1] += 0.5
        yield q, RNG.normal(0, 3, 2), RNG.uniform(-300, 300, 2), RNG.normal(0, 2, 2)


def test_inertia_is_symmetric_positive_definite(model):
    for q, *_ in random_states():
        M = model.M(q)
        np.testing.assert_allclose(M, M.T)
        assert np.all(np.linalg.eigvalsh(M) > 0)


def test_property2_mdot_minus_2c_is_skew_symmetric(model):
    for q, dq, *_ in random_states():
        S = model.M_dot(q, dq) - 2 * model.C(q, dq)
        np.testing.assert_allclose(S, -S.T, atol=1e-12)
        x = RNG.normal(size=2)
        assert abs(x @ S @ x) < 1e-12


def test_mdot_matches_finite_difference(model):
    h = 1e-6
    for q, dq, *_ in random_states(20):
        fd = (model.M(q + h * dq) - model.M(q - h * dq)) / (2 * h)
        np.testing.assert_allclose(model.M_dot(q, dq), fd, atol=1e-8)


def test_property3_rotation_rate_is_skew_symmetric(model):
    for q, dq, *_ in random_states():
        S = model.R_wc(q).T @ model.R_wc_dot(q, dq)
        np.testing.assert_allclose(S, -S.T, atol=1e-12)


def test_feature_dynamics_eq8_matches_differentiated_camera_model(model):
    h = 1e-6
    target = np.array([0.3, 0.25])
    for q, dq, *_ in random_states(50):
        f = model.features(q, target)
        fd = (model.features(q + h * dq, target) - model.features(q - h * dq, target)) / (2 * h)
        np.testing.assert_allclose(model.f_dot(q, dq, f), fd, rtol=1e-6, atol=1e-5)


def test_eta_dot_is_the_analytic_derivative_of_eta(model):
    h = 1e-6
    target = np.array([0.4, 0.1])
    for q, dq, *_ in random_states(50):
        f = model.features(q, target)

        def eta_at(s: float, q=q, dq=dq) -> np.ndarray:
            qs = q + s * dq
            return model.eta(qs, model.features(qs, target))

        fd = (eta_at(h) - eta_at(-h)) / (2 * h)
        np.testing.assert_allclose(model.eta_dot(q, dq, f), fd, rtol=1e-6, atol=1e-5)


def test_torque_law_eq11_yields_closed_loop_eq12(model):
    """M qdd + C dq + g = tau(eq. 11) implies xi_dot = M^-1 (u - C xi) and eq. (12) for f."""
    h = 1e-6
    target = np.array([0.35, 0.2])
    for q, dq, _, u in random_states(30):
        f = model.features(q, target)
        tau = model.torque(q, dq, f, u)
        qdd = np.linalg.solve(model.M(q), tau - model.C(q, dq) @ dq - model.g(q))
        xi = model.xi(q, dq, f)
        dq_rhs, xi_dot, f_dot = model.closed_loop_rhs(q, xi, f, u)
        np.testing.assert_allclose(dq_rhs, dq, atol=1e-10)
        np.testing.assert_allclose(f_dot, model.f_dot(q, dq, f), rtol=1e-9, atol=1e-8)

        def xi_at(s: float, q=q, dq=dq, qdd=qdd) -> np.ndarray:
            qs, dqs = q + s * dq + 0.5 * s * s * qdd, dq + s * qdd
            return model.xi(qs, dqs, model.features(qs, target))

        fd = (xi_at(h) - xi_at(-h)) / (2 * h)
        np.testing.assert_allclose(xi_dot, fd, rtol=1e-5, atol=1e-5)


def test_vdot_under_passivity_law_is_minus_xqx_eq16(model):
    for q, _, f, xi in random_states():
        u = passivity_based(model, xi)
        x = np.concatenate([xi, f])
        vdot = model.V_dot(q, xi, f, u)
        assert vdot == pytest.approx(-x @ model.Q(q) @ x, rel=1e-9, abs=1e-12)
        assert vdot <= 1e-12


def test_vdot_eq14_matches_differentiating_v_along_eq12(model):
    h = 1e-6
    for q, _, f, xi in random_states(30):
        u = RNG.normal(0, 1, 2)
        dq, xi_dot, f_dot = model.closed_loop_rhs(q, xi, f, u)
        fd = (
            model.V(q + h * dq, xi + h * xi_dot, f + h * f_dot)
            - model.V(q - h * dq, xi - h * xi_dot, f - h * f_dot)
        ) / (2 * h)
        assert model.V_dot(q, xi, f, u) == pytest.approx(fd, rel=1e-5, abs=1e-8)


def test_q_is_positive_definite_eq18(model):
    for q, *_ in random_states():
        assert np.all(np.linalg.eigvalsh(model.Q(q)) > 0)


def test_inverse_optimal_law_makes_l_plus_4vdot_vanish_eq22(model):
    """With u = -2 R xi the integrand of eq. (26) is zero: l + 4 Vdot = ||u + 2 R xi||^2 = 0."""
    for q, _, f, xi in random_states():
        u = inverse_optimal(model, xi)
        total = model.stage_cost(q, xi, f, u) + 4 * model.V_dot(q, xi, f, u)
        assert total == pytest.approx(0.0, abs=1e-9 * (1 + model.stage_cost(q, xi, f, u)))


def test_eq22_holds_for_any_input(model):
    for q, _, f, xi in random_states(50):
        u = RNG.normal(0, 2, 2)
        lhs = 4 * model.V_dot(q, xi, f, u) + model.stage_cost(q, xi, f, u)
        e = u + 2 * model.R @ xi
        assert lhs == pytest.approx(e @ model.R_inv @ e, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_compiled_tick_terms_equal_the_numpy_model(cfg: RigConfig, gravity: float):
    from rt_controller.control import model_kernels
    from rt_controller.control.state import pack_params

    cfg = cfg.with_overrides(
        {"robot.gravity": gravity, "gains.alpha": [[0.05, 0.01], [0.01, 0.15]]}
    )
    model = NumpyModel.from_config(cfg)
    p = pack_params(model)
    for q, dq, f, u in random_states(100):
        xi, tau_ff = model_kernels.prepare(p, q, dq, f)
        np.testing.assert_allclose(xi, model.xi(q, dq, f), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(tau_ff + u, model.torque(q, dq, f, u), rtol=1e-10, atol=1e-10)
        cost, energy = model_kernels.costs(p, q, xi, f, u)
        assert cost == pytest.approx(model.stage_cost(q, xi, f, u), rel=1e-10)
        assert energy == pytest.approx(model.V(q, xi, f), rel=1e-12)
