"""The optimal control problem of eq. (30): hand-derived gradients against finite differences.

The finite differences are taken of the nominal model's own functions (``closed_loop_rhs``,
``stage_cost``, ``V``), so they check the compiled kernels and the NumPy reference independently.
"""

from __future__ import annotations

import numpy as np
import pytest

from rt_controller.control import state
from rt_controller.control.rhc import dynamics as dyn
from rt_controller.control.rhc import problem as pb
from rt_controller.control.rhc.residual import eval_F
from tests.support.nominal_model import NumpyModel
from tests.support.rhc_reference import ReferenceProblem, ReferenceSolver

EPS = 1e-6


def states(n: int = 6, seed: int = 3) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Random (x, u, lam) around the paper scenario's magnitudes (f ~ 200 px, xi ~ 5 rad/s)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        x = np.concatenate([rng.uniform(-2.5, 2.5, 2), rng.normal(0, 4, 2), rng.normal(0, 150, 2)])
        u = rng.normal(0, 5, 2)
        lam = rng.normal(size=6) * np.array([1.0, 1.0, 0.3, 0.3, 3e-3, 3e-3])
        out.append((x, u, lam))
    return out


@pytest.fixture
def model(cfg) -> NumpyModel:
    return NumpyModel.from_config(cfg)


@pytest.fixture
def params(model, cfg):
    return pb.pack_params(model, cfg)


def model_rhs(model: NumpyModel, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    return np.concatenate(model.closed_loop_rhs(x[0:2], x[2:4], x[4:6], u))


def model_H(model: NumpyModel, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> float:
    """H = l(x, u) + lam^T f(x, u) from the model's functions."""
    return model.stage_cost(x[0:2], x[2:4], x[4:6], u) + lam @ model_rhs(model, x, u)


def central(fun, z: np.ndarray, eps: float = EPS) -> np.ndarray:
    return np.array([(fun(z + eps * e) - fun(z - eps * e)) / (2 * eps) for e in np.eye(z.size)])


def test_dynamics_match_the_model(model, params):
    P, _ = params
    for x, u, _ in states():
        out = np.zeros(6)
        dyn.rhs(P, x, u, out)
        np.testing.assert_allclose(out, model_rhs(model, x, u), rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("case", range(6))
def test_hamiltonian_gradients_against_finite_differences(model, params, cfg, case):
    P, _ = params
    x, u, lam = states()[case]
    hx, hu, aux = np.zeros(6), np.zeros(6), np.zeros(state.NAUX)
    dyn.stage_forward(P, x, u, aux, np.zeros(6))
    dyn.stage_adjoint(P, x, u, lam, aux, hx, hu)
    fd_x = central(lambda z: model_H(model, z, u, lam), x)
    fd_u = central(lambda z: model_H(model, x, z, lam), u)
    scale_x = np.abs(fd_x).max()
    np.testing.assert_allclose(hx, fd_x, rtol=1e-6, atol=1e-7 * scale_x)
    np.testing.assert_allclose(hu[:2], fd_u, rtol=1e-6, atol=1e-7 * np.abs(fd_u).max())
    # The matrix-form reference agrees with the scalar kernel to rounding.
    rx, ru = ReferenceProblem(model, cfg).hamiltonian_grad(x, u, lam)
    np.testing.assert_allclose(rx, hx, rtol=1e-10, atol=1e-10 * scale_x)
    np.testing.assert_allclose(ru, hu[:2], rtol=1e-10)


@pytest.mark.parametrize("case", range(6))
def test_terminal_gradient_against_finite_differences(model, params, case):
    P, _ = params
    x = states()[case][0]
    g = np.zeros(6)
    dyn.terminal_grad(P, x, g)
    fd = central(lambda z: 4.0 * model.V(z[0:2], z[2:4], z[4:6]), x)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8 * np.abs(fd).max())


def sweep_work(N: int):
    """The (X, Lam, Aux, hx, hu, cnt) work tuple of :func:`eval_F` (one Euler step per stage)."""
    return (
        np.zeros((N + 1, 6)),
        np.zeros((N + 1, 6)),
        np.zeros((N, state.NAUX)),
        np.zeros(6),
        np.zeros(6),
        np.zeros(1),
    )


def discrete_cost(model: NumpyModel, x0: np.ndarray, u: np.ndarray, T: float) -> float:
    """sum dtau l(x_k, u_k) + 4 V(x_N) on the Euler discretisation, from the model's functions."""
    N = u.shape[0]
    dtau = T / N
    x, J = x0.copy(), 0.0
    for k in range(N):
        J += dtau * model.stage_cost(x[0:2], x[2:4], x[4:6], u[k])
        x = x + dtau * model_rhs(model, x, u[k])
    return J + 4.0 * model.V(x[0:2], x[2:4], x[4:6])


@pytest.mark.parametrize("T", [0.02, 0.1, 0.3])
def test_F_is_the_gradient_of_the_discretised_cost(model, params, T):
    """With mu = 0, F's input rows times dtau are dJ/du_k of the Euler-discretised problem."""
    P, iP = params
    N = int(iP[state.IP.N])
    rng = np.random.default_rng(7)
    x0 = np.array([np.pi / 6, -np.pi / 6, 3.1, 6.2, -120.0, -160.0])
    u = rng.normal(0, 3, (N, 2))
    U = np.zeros((N, state.NS))
    U[:, 0:2] = u
    U[:, 2:4] = 1.0
    F = np.zeros(N * state.NS)
    sw = sweep_work(N)
    eval_F(P, N, U.ravel(), x0, T, sw, F)
    grad = central(lambda z: discrete_cost(model, x0, z.reshape(N, 2), T), u.ravel(), 1e-5)
    dtau = T / N
    got = F.reshape(N, state.NS)[:, 0:2].ravel() * dtau
    np.testing.assert_allclose(got, grad, rtol=1e-5, atol=1e-6 * np.abs(grad).max())


def test_kernel_F_matches_the_reference(model, params, cfg):
    P, iP = params
    N = int(iP[state.IP.N])
    rng = np.random.default_rng(11)
    x0 = np.array([0.3, -0.8, 2.0, -4.0, 80.0, -150.0])
    U = np.column_stack(
        [rng.normal(0, 3, (N, 2)), rng.uniform(1, 10, (N, 2)), rng.uniform(0, 1, (N, 2))]
    ).ravel()
    F = np.zeros(N * state.NS)
    sw = sweep_work(N)
    eval_F(P, N, U, x0, 0.1, sw, F)
    ref = ReferenceSolver(model, cfg).F(U, x0, 0.1)
    np.testing.assert_allclose(F, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())


def test_horizon_growth(params, cfg):
    P, _ = params
    assert dyn.horizon_at(P, 0.0) == cfg.rhc.horizon
    grown = pb.pack_params(
        NumpyModel.from_config(cfg), cfg.with_overrides({"rhc.horizon_growth": 2.0})
    )[0]
    assert dyn.horizon_at(grown, 0.0) == 0.0
    assert dyn.horizon_at(grown, 0.5) == pytest.approx(cfg.rhc.horizon * (1 - np.exp(-1.0)))


def test_substeps_keep_each_euler_step_short():
    assert pb.substeps(0.1, 10) == 1
    assert pb.substeps(0.02, 10) == 1
    assert pb.substeps(1.0, 50) == 1
    assert pb.substeps(1.0, 20) == 2
    assert pb.substeps(1.0, 10) == 4
    for T, N in [(1.0, 10), (0.3, 3), (2.0, 7)]:
        assert T / N / pb.substeps(T, N) <= pb.MAX_SUBSTEP_S + 1e-12


def test_F_with_substeps_is_the_gradient_of_the_discretised_cost(model, params):
    """Each stage held over S substeps: dtau times F's input rows are dJ/du_k."""
    P, _ = params
    N, S, T = 4, 3, 0.3
    rng = np.random.default_rng(5)
    x0 = np.array([np.pi / 6, -np.pi / 6, 3.1, 6.2, -120.0, -160.0])
    u = rng.normal(0, 3, (N, 2))
    U = np.zeros((N, state.NS))
    U[:, 0:2] = u
    U[:, 2:4] = 1.0
    sw = (
        np.zeros((N * S + 1, 6)),
        np.zeros((N * S + 1, 6)),
        np.zeros((N * S, state.NAUX)),
        np.zeros(6),
        np.zeros(6),
        np.zeros(1),
    )
    F = np.zeros(N * state.NS)
    eval_F(P, N, U.ravel(), x0, T, sw, F)
    assert sw[5][0] == 1.0  # the call counter

    def cost(z: np.ndarray) -> float:
        uu = z.reshape(N, 2)
        h = T / (N * S)
        x, J = x0.copy(), 0.0
        for r in range(N * S):
            J += h * model.stage_cost(x[0:2], x[2:4], x[4:6], uu[r // S])
            x = x + h * model_rhs(model, x, uu[r // S])
        return J + 4.0 * model.V(x[0:2], x[2:4], x[4:6])

    grad = central(cost, u.ravel(), 1e-5)
    got = F.reshape(N, state.NS)[:, 0:2].ravel() * (T / N)
    np.testing.assert_allclose(got, grad, rtol=1e-5, atol=1e-6 * np.abs(grad).max())
