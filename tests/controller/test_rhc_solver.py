"""C/GMRES solver: convergence, bounds, an independent NLP solution, the NumPy twin, fallbacks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from hal.config import RigConfig
from rt_controller.control.rhc import gmres, kernel, residual
from rt_controller.control.rhc.solver import CGMRESSolver, pack_state
from tests.support.nominal_model import NumpyModel
from tests.support.python_laws import Measurement, RecedingHorizonLaw, make_law
from tests.support.rhc_reference import ReferenceSolver

FROZEN = np.zeros(6)


def initial_state(cfg: RigConfig, model: NumpyModel) -> np.ndarray:
    q = np.array(cfg.scenario.q0)
    f = np.array(cfg.scenario.f0)
    return pack_state(q, model.xi(q, np.array(cfg.scenario.dq0), f), f)


def solver_for(cfg: RigConfig, **overrides) -> tuple[CGMRESSolver, NumpyModel, RigConfig]:
    cfg = cfg.with_overrides(overrides) if overrides else cfg
    model = NumpyModel.from_config(cfg)
    return CGMRESSolver(model, cfg), model, cfg


def test_newton_initialisation_reaches_init_tol(cfg):
    solver, model, cfg = solver_for(cfg)
    rep = solver.update(initial_state(cfg, model), 0.0, xdot=FROZEN)
    assert rep.initialised and rep.ok
    assert rep.residual <= cfg.rhc.init_tol
    assert not solver.needs_init


@pytest.mark.parametrize("T", [0.02, 0.1])
def test_frozen_state_updates_drive_the_residual_below_1e_6(cfg, T):
    """Start from the solution for another state; the continuation converges on the new one."""
    solver, model, cfg = solver_for(cfg, **{"rhc.horizon": T})
    x0 = initial_state(cfg, model)
    solver.update(x0, 0.0, xdot=FROZEN)
    x1 = x0 + np.array([0.05, -0.05, -1.0, 2.0, 30.0, -20.0])
    residuals = [solver.update(x1, 0.0, xdot=FROZEN).residual for _ in range(40)]
    assert residuals[0] > 1e-3
    assert residuals[-1] < 1e-6
    assert all(np.isfinite(residuals))


def test_first_input_near_inverse_optimal_for_short_horizon(cfg):
    """Eq. (31)-(32): the continuous optimum is u = -2 R xi; Euler with dtau = 2 ms is close."""
    solver, model, cfg = solver_for(cfg, **{"rhc.horizon": 0.02})
    x = initial_state(cfg, model)
    u = solver.update(x, 0.0, xdot=FROZEN).u
    np.testing.assert_allclose(u, -2 * model.R @ x[2:4], rtol=0.1)


def test_zero_horizon_is_exactly_inverse_optimal(cfg):
    """With horizon growth T(0) = 0, the problem's solution is eq. (27) (up to the dummy cost)."""
    solver, model, cfg = solver_for(cfg, **{"rhc.horizon_growth": 3.0})
    x = initial_state(cfg, model)
    u = solver.update(x, 0.0, xdot=FROZEN).u
    np.testing.assert_allclose(u, -2 * model.R @ x[2:4], rtol=1e-3)


@pytest.mark.parametrize(
    ("u_max", "at_bound"),
    [((2.0, 1.0), (True, True)), ((4.0, 2.5), (True, False)), ((0.5, 0.2), (True, True))],
)
def test_dummy_input_bounds_hold_at_convergence(cfg, u_max, at_bound):
    solver, model, cfg = solver_for(cfg, **{"rhc.u_max": list(u_max)})
    x = initial_state(cfg, model)
    for _ in range(10):
        rep = solver.update(x, 0.0, xdot=FROZEN)
    assert rep.residual < 1e-6
    S = solver.U.reshape(-1, 6)
    umax = np.array(u_max)
    u, v, mu = S[:, 0:2], S[:, 2:4], S[:, 4:6]
    assert np.all(np.abs(u) <= umax)
    assert np.all(v > 0) and np.all(mu > 0)
    np.testing.assert_allclose(u**2 + v**2, umax**2 * np.ones_like(u), rtol=1e-10)
    np.testing.assert_allclose(2 * mu * v, cfg.rhc.dummy_weight, rtol=1e-8)
    # The first input of the paper's initial state has the sign of the unconstrained optimum
    # -2 R xi (eq. 31, here (-4.09, -2.83)), which lies beyond every bound: it pushes against
    # the bound where the bound is tight, while the dummy-input barrier keeps it clearly inside
    # a loose one (u_max = (4, 2.5): joint 2 stays at ~92 % of its bound).
    u_star = -2 * model.R @ x[2:4]
    assert np.all(np.abs(u_star) > umax)
    assert np.array_equal(np.sign(rep.u), np.sign(u_star))
    assert tuple(bool(b) for b in np.abs(rep.u) > 0.99 * umax) == at_bound, rep.u
    for j in np.flatnonzero(~np.array(at_bound)):
        assert abs(rep.u[j]) < 0.95 * umax[j], rep.u


def direct_shooting(model: NumpyModel, cfg: RigConfig, x0: np.ndarray) -> np.ndarray:
    """The same Euler-discretised problem solved by scipy (L-BFGS-B, box bounds on u).

    The dummy inputs are eliminated: v_i = sqrt(umax_i^2 - u_i^2) maximises the dummy reward, so
    the stage cost gains ``-r_v sum sqrt(umax^2 - u^2)`` and the bounds become box constraints.
    The costs and dynamics come from the model; their gradient by central differences, the
    dummy term's (singular at the bound) in closed form.
    """
    N, T, rv = cfg.rhc.steps, cfg.rhc.horizon, cfg.rhc.dummy_weight
    umax = np.tile(np.array(cfg.rhc.u_max), N)
    dtau = T / N

    def smooth(z: np.ndarray) -> float:
        u = z.reshape(N, 2)
        x, J = x0.copy(), 0.0
        for k in range(N):
            q, xi, f = x[0:2], x[2:4], x[4:6]
            J += dtau * model.stage_cost(q, xi, f, u[k])
            x = x + dtau * np.concatenate(model.closed_loop_rhs(q, xi, f, u[k]))
        return J + 4.0 * model.V(x[0:2], x[2:4], x[4:6])

    def cost(z: np.ndarray) -> float:
        return smooth(z) - dtau * rv * np.sum(np.sqrt(umax**2 - z**2))

    def grad(z: np.ndarray) -> np.ndarray:
        h = 1e-6 * np.maximum(1.0, np.abs(z))
        fd = np.array(
            [(smooth(z + e) - smooth(z - e)) / (2 * e[i]) for i, e in enumerate(np.diag(h))]
        )
        return fd + dtau * rv * z / np.sqrt(umax**2 - z**2)

    z0 = np.clip(np.tile(-2 * model.R @ x0[2:4], N), -0.9 * umax, 0.9 * umax)
    lim = umax * (1 - 1e-10)
    res = minimize(
        cost,
        z0,
        method="L-BFGS-B",
        jac=grad,
        bounds=list(zip(-lim, lim, strict=True)),
        options={"ftol": 0.0, "gtol": 1e-12, "maxiter": 5000, "maxfun": 100_000},
    )
    return res.x.reshape(N, 2)


@pytest.mark.parametrize(
    ("horizon", "u_max"),
    [
        (0.1, (150.0, 15.0)),
        (0.02, (150.0, 15.0)),
        (0.1, (4.0, 2.5)),
        (0.1, (0.5, 0.2)),
        pytest.param(0.1, (2.0, 1.0), marks=pytest.mark.slow),
    ],
)
def test_first_input_agrees_with_an_independent_nlp_solution(cfg, horizon, u_max):
    solver, model, cfg = solver_for(cfg, **{"rhc.horizon": horizon, "rhc.u_max": list(u_max)})
    x = initial_state(cfg, model)
    rep = solver.update(x, 0.0, xdot=FROZEN)
    U = solver.U.reshape(-1, 6)[:, 0:2].copy()
    nlp = direct_shooting(model, cfg, x)
    np.testing.assert_allclose(rep.u, nlp[0], rtol=1e-3)
    np.testing.assert_allclose(U, nlp, rtol=1e-3)


def test_compiled_and_numpy_reference_agree_tick_by_tick(cfg):
    solver, model, cfg = solver_for(cfg)
    ref = ReferenceSolver(model, cfg)
    x = initial_state(cfg, model)
    period = 1.0 / cfg.rates.control_hz
    for k in range(4):
        a = solver.update(x, k * period)
        b = ref.update(x, k * period)
        np.testing.assert_allclose(a.u, b.u, rtol=1e-6)
        np.testing.assert_allclose(solver.U, ref.U, rtol=1e-5, atol=1e-6 * np.abs(ref.U).max())
        assert a.iterations == b.iterations and a.ok and b.ok
        dq, xid, fd = model.closed_loop_rhs(x[0:2], x[2:4], x[4:6], a.u)
        x = x + period * np.concatenate([dq, xid, fd])


def measurement(model: NumpyModel, x: np.ndarray, t: float = 0.0, **replace) -> Measurement:
    q, xi, f = x[0:2], x[2:4], x[4:6]
    dq = xi + model.alpha @ model.eta(q, f)
    fields = {"t": t, "q": q, "dq": dq, "f": f, "xi": xi, **replace}
    return Measurement(**fields)


def test_make_law_builds_the_rhc_law(cfg):
    model = NumpyModel.from_config(cfg)
    law = make_law("rhc", model, cfg)
    assert isinstance(law, RecedingHorizonLaw) and law.name == "rhc"
    out = law(measurement(model, initial_state(cfg, model)))
    assert not out.fallback and out.solve_ns > 0 and out.iterations > 0
    assert out.residual <= cfg.rhc.init_tol


def test_nan_measurement_falls_back_to_inverse_optimal_and_recovers(cfg):
    model = NumpyModel.from_config(cfg)
    law = RecedingHorizonLaw(model, cfg)
    x = initial_state(cfg, model)
    assert not law(measurement(model, x)).fallback
    bad = law(measurement(model, x, t=0.02, f=np.array([np.nan, 1.0])))
    assert bad.fallback and law.fallbacks == 1
    np.testing.assert_allclose(bad.u, -2 * model.R @ x[2:4])
    # The next good tick solves from scratch (Newton) and is used again.
    good = law(measurement(model, x, t=0.04))
    assert not good.fallback and good.residual <= cfg.rhc.init_tol
    # A NaN xi has no inverse-optimal input either: zero, never NaN.
    worse = law(measurement(model, x, t=0.06, xi=np.array([np.nan, 0.0])))
    assert worse.fallback and np.all(worse.u == 0.0) and law.fallbacks == 2
    law.reset()
    assert law.fallbacks == 0


def test_residual_above_the_bound_falls_back_every_tick(cfg):
    cfg = cfg.with_overrides({"rhc.residual_bound": 1e-300, "rhc.u_max": [3.0, 2.0]})
    model = NumpyModel.from_config(cfg)
    law = RecedingHorizonLaw(model, cfg)
    x = initial_state(cfg, model)
    for k in range(3):
        out = law(measurement(model, x, t=0.02 * k))
        assert out.fallback
        np.testing.assert_allclose(out.u, np.clip(-2 * model.R @ x[2:4], [-3, -2], [3, 2]))
    assert law.fallbacks == 3
    assert law.solver.needs_init


def kernel_setup(cfg: RigConfig, **overrides):
    """A solver solved from scratch at the initial state, and the arrays of one tick."""
    solver, model, cfg = solver_for(cfg, **overrides)
    x = initial_state(cfg, model)
    solver.update(x, 0.0, xdot=FROZEN)
    sw, ws, _vecs, pre, _ = kernel.work_views(solver.iP, solver.work)
    return solver, model, cfg, x, sw, ws, pre


def test_block_gmres_with_one_right_hand_side_is_gmres(cfg):
    solver, _model, cfg, x, sw, ws, pre = kernel_setup(cfg)
    P, N, U = solver.P, solver.N, solver.U.copy()
    x1 = x + np.array([0.02, -0.02, -0.5, 1.0, 10.0, -10.0])
    T = cfg.rhc.horizon
    F = np.zeros_like(U)
    residual.eval_F(P, N, U, x1, T, sw, F)
    residual.precond_setup(P, N, U, sw[0], T, pre)
    b, zero = -F, np.zeros_like(U)
    d1, d2, ref = np.zeros_like(U), np.ones_like(U), np.zeros_like(U)
    k = gmres.block_gmres(P, N, U, x1, T, F, b, zero, d1, d2, 5, pre, ws, sw)
    kg = gmres.fd_gmres(P, N, U, x1, T, F, b.copy(), ref, 5, 0.0, pre, ws, sw)
    assert k == kg == 5
    np.testing.assert_allclose(d1, ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())
    assert np.all(d2 == 0.0)


def test_block_gmres_solves_both_right_hand_sides(cfg):
    """With a Krylov space as large as the problem both solutions are exact up to the forward
    differences (step 1e-8, so to ~1e-3 here), and the correction cuts the residual."""
    solver, _model, cfg, x, sw, ws, pre = kernel_setup(cfg, **{"rhc.steps": 3})
    P, N, U = solver.P, solver.N, solver.U.copy()
    n = U.size
    x1 = x + np.array([0.02, -0.02, -0.5, 1.0, 10.0, -10.0])
    T = cfg.rhc.horizon
    F = np.zeros(n)
    residual.eval_F(P, N, U, x1, T, sw, F)
    residual.precond_setup(P, N, U, sw[0], T, pre)
    rng = np.random.default_rng(2)
    b2 = rng.normal(size=n) * np.abs(F).max()
    d1, d2 = np.zeros(n), np.zeros(n)
    k = gmres.block_gmres(P, N, U, x1, T, F, -F, b2, d1, d2, n, pre, ws, sw)
    assert k == n
    for b, d in ((-F, d1), (b2, d2)):
        Ad = np.zeros(n)
        scale = 1.0 / np.linalg.norm(d)
        gmres.jvp(P, N, U, x1, T, F, d, scale, Ad, np.zeros(n), sw)
        assert np.linalg.norm(Ad - b) <= 1e-3 * np.linalg.norm(b)
    # The Newton step d1 cuts the residual at the new state by orders of magnitude.
    F1 = np.zeros(n)
    Un = U + d1
    residual.clip_dummies(P, N, Un)
    residual.eval_F(P, N, Un, x1, T, sw, F1)
    assert np.linalg.norm(F1) < 1e-2 * np.linalg.norm(F)


def test_a_continuation_tick_evaluates_F_kmax_plus_3_times(cfg):
    solver, model, cfg = solver_for(cfg)
    x = initial_state(cfg, model)
    solver.update(x, 0.0)
    period = 1.0 / cfg.rates.control_hz
    for k in range(1, 5):
        rep = solver.update(x, k * period)
        assert rep.ok and not rep.initialised
        assert solver.last_fevals == cfg.rhc.kmax + 3
        assert rep.iterations == cfg.rhc.kmax


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"rhc.horizon": 1.0, "rhc.steps": 10},  # 4 Euler substeps per stage
        {"rhc.u_max": [2.0, 1.0]},  # bounds active
    ],
)
def test_compiled_and_numpy_reference_agree_on_one_tick(cfg, overrides):
    """Newton start, then one continuation tick away from the solution: same u, U, Udot."""
    solver, model, cfg = solver_for(cfg, **overrides)
    ref = ReferenceSolver(model, cfg)
    x = initial_state(cfg, model)
    a, b = solver.update(x, 0.0), ref.update(x, 0.0)
    assert a.ok and b.ok
    x1 = x + np.array([0.01, -0.01, -0.3, 0.5, 5.0, -5.0])
    a, b = solver.update(x1, 0.02), ref.update(x1, 0.02)
    assert a.ok and b.ok and a.iterations == b.iterations
    assert solver.last_fevals == ref.last_fevals
    # Agreement to the forward differences' rounding (step 1e-8), as tick by tick above.
    np.testing.assert_allclose(a.u, b.u, rtol=1e-6)
    assert a.residual == pytest.approx(b.residual, rel=1e-3, abs=1e-8)
    A, B = solver.U.reshape(-1, 6), ref.U.reshape(-1, 6)
    np.testing.assert_allclose(A[:, 0:4], B[:, 0:4], rtol=1e-5, atol=1e-6 * np.abs(B).max())
    # Multipliers of active bounds (mu = r_v / 2v, v ~ 0) are the most sensitive unknowns.
    np.testing.assert_allclose(A[:, 4:6], B[:, 4:6], rtol=1e-4, atol=1e-6 * np.abs(B).max())
    np.testing.assert_allclose(solver.Udot, ref.Udot, rtol=1e-3, atol=1e-4 * np.abs(ref.Udot).max())


def test_ticks_are_deterministic(cfg):
    """Replay needs the output to be a function of the inputs: two solvers, same inputs."""
    x = None
    outs = []
    for _ in range(2):
        solver, model, c = solver_for(cfg)
        x = initial_state(c, model)
        reps = [solver.update(x + 0.01 * k, 0.02 * k) for k in range(6)]
        outs.append((np.array([r.u for r in reps]), solver.U.copy()))
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])


def test_direct_compiled_entry_gives_the_dispatcher_results(cfg):
    """After warm_up the tick skips numba's dispatcher; the results are bit for bit the same."""
    fast, model, c = solver_for(cfg)
    fast.warm_up()
    assert fast.dispatch_free
    slow, _, _ = solver_for(cfg)
    assert not slow.dispatch_free
    x = initial_state(c, model)
    for k in range(5):
        a, b = fast.update(x + 0.01 * k, 0.02 * k), slow.update(x + 0.01 * k, 0.02 * k)
        assert np.array_equal(a.u, b.u) and a.residual == b.residual
        assert a.iterations == b.iterations and a.ok == b.ok
    assert np.array_equal(fast.st, slow.st)
