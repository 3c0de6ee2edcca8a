"""The optimal control problem of eq. (30) on system (12): maths, parameters, compiled functions.

Prediction state ``x = (q1, q2, xi1, xi2, f1, f2)``, input ``u`` (2), per horizon stage the
unknowns ``(u1, u2, v1, v2, mu1, mu2)``: the input, the dummy inputs of the bounds
``u_i^2 + v_i^2 = umax_i^2`` and their multipliers (Ohtsuka's dummy-input method, with the
dummy cost ``-r_v v_i``).

With ``A(q) = R_wc^T J_b = [[l1 s2, 0], [l1 c2 + l2, l2]]`` (it depends on q2 only),
``eta = A^T f`` and ``dq = xi + alpha eta``, eq. (12) reads::

    q'  = dq
    xi' = M^-1 (u - C(q, dq) xi)
    f'  = -g A dq + w (f2, -f1),        w = dq1 + dq2,  g = s lambda / z_wo

and the costs of eq. (25) and (13)::

    l   = 4 xi^T R xi + 4 kp eta^T dq + u^T R^-1 u      (= 4 x^T Q x + u^T R^-1 u)
    phi = 4 V = 2 xi^T M xi + 2 kp / g f^T f

The Hamiltonian ``H = l - r_v sum(v) + lam^T x' + mu^T (u^2 + v^2 - umax^2)``. Its gradients are
derived by hand with ``dq`` and ``eta`` as intermediates (see :func:`hamiltonian_grad`); the tests
check them against finite differences of :class:`~rt_controller.control.model.NominalModel`.
The gravity term of eq. (1) cancels in eq. (11) and does not appear here.

The compiled functions (``rhs``, ``stage_cost``, ``terminal_cost``, ``terminal_grad``,
``hamiltonian_grad``, ``horizon_at``) live in :mod:`rt_controller.control.rhc.kernel` and are
re-exported here; this module adds the packing of the model and the ``rhc`` settings into their
parameter vectors.
"""

from __future__ import annotations

import math

import numpy as np

from hal.config import RigConfig
from rt_controller.control.model import NominalModel
from rt_controller.control.rhc.kernel import (  # noqa: F401  (re-exported: the compiled OCP functions)
    ALPHA,
    DT,
    GAIN,
    GROWTH,
    HFD,
    I_INIT_ITERS,
    I_INIT_KRYLOV,
    I_KMAX,
    I_N,
    I_SUB,
    INIT_TOL,
    KP,
    L1,
    L2,
    NAUX,
    NIP,
    NP,
    NS,
    NU,
    NX,
    RINV,
    RV,
    RW,
    T1,
    T2,
    T3,
    TF,
    UMAX,
    VMIN,
    ZETA,
    hamiltonian_grad,
    horizon_at,
    rhs,
    stage_adjoint,
    stage_cost,
    stage_forward,
    terminal_cost,
    terminal_grad,
)

DUMMY_FLOOR = 1e-6
"""Dummy inputs are kept at or above ``DUMMY_FLOOR * umax_i``: this selects the minimising branch
(v > 0) and bounds the multiplier ``mu_i = r_v / (2 v_i)`` so a bound never makes it infinite."""

INIT_KRYLOV = 60
"""Largest Krylov dimension of one Newton-GMRES step of the initial solve."""

MAX_SUBSTEP_S = 0.025
"""Longest explicit Euler step of the prediction. The arm's fast modes are about 40 /s, so a step
of T_f / N longer than ~0.05 s is unstable (T = 1 s with N = 10); each stage is then split into
``ceil(T_f / (N MAX_SUBSTEP_S))`` substeps with the input held (same unknowns, finer sweep)."""


def substeps(horizon: float, steps: int) -> int:
    """Euler substeps per horizon stage so that each is at most :data:`MAX_SUBSTEP_S`."""
    return max(1, math.ceil(horizon / steps / MAX_SUBSTEP_S - 1e-9))


def pack_params(model: NominalModel, cfg: RigConfig) -> tuple[np.ndarray, np.ndarray]:
    """Float and integer parameter vectors (P, iP) for the compiled kernels."""
    h = cfg.rhc
    P = np.zeros(NP)
    P[T1], P[T2], P[T3] = model.theta1, model.theta2, model.theta3
    P[L1], P[L2], P[GAIN], P[KP] = model.l1, model.l2, model.gain, model.kp
    P[ALPHA : ALPHA + 4] = np.asarray(model.alpha, dtype=float).ravel()
    P[RW : RW + 4] = np.asarray(model.R, dtype=float).ravel()
    P[RINV : RINV + 4] = np.asarray(model.R_inv, dtype=float).ravel()
    umax = np.asarray(h.u_max, dtype=float)
    P[UMAX : UMAX + 2] = umax
    P[RV] = h.dummy_weight
    P[VMIN : VMIN + 2] = DUMMY_FLOOR * umax
    P[HFD] = h.fd_step
    P[ZETA] = h.zeta
    P[DT] = 1.0 / cfg.rates.control_hz
    P[TF] = h.horizon
    P[GROWTH] = h.horizon_growth
    P[INIT_TOL] = h.init_tol
    iP = np.zeros(NIP, dtype=np.int64)
    iP[I_N] = h.steps
    iP[I_KMAX] = h.kmax
    iP[I_INIT_ITERS] = h.init_iterations
    iP[I_INIT_KRYLOV] = min(NS * h.steps, max(INIT_KRYLOV, h.kmax))
    iP[I_SUB] = substeps(h.horizon, h.steps)
    return P, iP


def horizon_length(P: np.ndarray, t: float) -> float:
    """T(t) = Tf (1 - exp(-a t)), or Tf when a = 0 (plain-Python twin of :func:`horizon_at`)."""
    a = P[GROWTH]
    return float(P[TF]) if a <= 0.0 else float(P[TF] * (1.0 - math.exp(-a * max(t, 0.0))))
