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

The Hamiltonian ``H = l - r_v sum(v) + lam^T x' + mu^T (u^2 + v^2 - umax^2)``. Its gradients
are derived by hand with ``dq`` and ``eta`` as intermediates (``dynamics.stage_adjoint``); the
tests check them against finite differences of ``tests/support/nominal_model.py``.
The gravity term of eq. (1) cancels in eq. (11) and does not appear here.

The compiled functions (``rhs``, ``terminal_grad``, ``stage_adjoint``, ``horizon_at``) live
in :mod:`rt_controller.control.rhc.dynamics`; this module packs the model and the ``rhc``
settings into their parameter vectors.
"""

from __future__ import annotations

import math

import numpy as np

from hal.config import RigConfig
from rt_controller.control import state
from rt_controller.control.model import NominalModel
from rt_controller.control.state import IP, NS, PAR, work_offsets

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
    """Float and integer parameter vectors (P, iP) for the compiled kernels (layouts
    :data:`~rt_controller.control.state.PAR` and :data:`~rt_controller.control.state.IP`)."""
    h = cfg.rhc
    P = state.pack_params(model)
    umax = np.asarray(h.u_max, dtype=float)
    P[PAR.U_MAX : PAR.U_MAX + 2] = umax
    P[PAR.RV] = h.dummy_weight
    P[PAR.VMIN : PAR.VMIN + 2] = DUMMY_FLOOR * umax
    P[PAR.HFD] = h.fd_step
    P[PAR.ZETA] = h.zeta
    P[PAR.DT] = 1.0 / cfg.rates.control_hz
    P[PAR.TF] = h.horizon
    P[PAR.GROWTH] = h.horizon_growth
    P[PAR.INIT_TOL] = h.init_tol
    P[PAR.RES_BOUND] = h.residual_bound
    iP = np.zeros(IP.SIZE, dtype=np.int64)
    iP[IP.N] = h.steps
    iP[IP.KMAX] = h.kmax
    iP[IP.INIT_ITERS] = h.init_iterations
    iP[IP.INIT_KRYLOV] = min(NS * h.steps, max(INIT_KRYLOV, h.kmax))
    iP[IP.SUB] = substeps(h.horizon, h.steps)
    krylov = int(max(iP[IP.KMAX], iP[IP.INIT_KRYLOV]))
    cut, _ = work_offsets(h.steps, int(iP[IP.SUB]), krylov)
    iP[IP.WORK : IP.WORK + cut.size] = cut
    return P, iP
