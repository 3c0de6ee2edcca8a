"""The per-tick rule as one compiled call: observation numbers in, decision numbers out.

:func:`decide_tick` does in one numba call what the test oracle ``tests/support/python_rule.py``
spells out in Python with the law objects: the drive-state and staleness branches, the delay
compensation (:func:`~rt_controller.control.model_kernels.compensate`), xi and the feedforward
of eq. (11), the law (eq. 15, eq. 27, or the C/GMRES update of eq. 30 with its residual check
and its fallback to eq. 27), the torque and its saturation, l and V, and the torque history the next
compensation needs. It calls the same compiled kernels in the same order, so it decides what
the Python rule decides. All its state lives in preallocated arrays (:class:`CompiledRule`);
nothing is allocated per tick but the kernels' own 2-vectors.

The call goes straight to the compiled overload (:func:`~rt_controller.control.rhc.solver.
compiled_entry`), past numba's dispatcher.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np
from numba import njit

from hal.config import RigConfig
from rt_controller.control import model_kernels as mk
from rt_controller.control import numba_cache  # noqa: F401  (before any cached kernel)
from rt_controller.control.rhc import kernel as rk
from rt_controller.control.rhc.solver import CGMRESSolver, compiled_entry
from rt_controller.control.state import (
    IO,
    KS,
    LIM,
    MODE_CONTROL,
    MODE_DRIVE,
    MODE_HOLD,
    MODE_NO_STATE,
    PAR,
    ST,
    XS,
)

LAW_CODES = {"pbc": 0.0, "ioc": 1.0, "rhc": 2.0}
"""The law's code in ``LIM.LAW``."""

CAPACITY = 1024
"""Torques the history holds before it drops those older than the horizon (amortised)."""
STEP_S = 1e-3
"""Longest Runge-Kutta step of the prediction, s."""


@njit(cache=True, fastmath=False)
def record_sent(hist_t, hist_tau, ks, t, tau0, tau1, horizon):
    """Append the torque sent at ``t``; a full history first keeps only the one held at
    ``t - horizon`` and those after it (the oldest goes if that is still all of them)."""
    n = int(ks[KS.N])
    cap = hist_t.shape[0]
    if n == cap:
        first = 1  # the oldest goes in any case
        for i in range(1, n):
            if hist_t[i] <= t - horizon:
                first = i
        n -= first
        for i in range(n):
            hist_t[i] = hist_t[first + i]
            hist_tau[i, 0], hist_tau[i, 1] = hist_tau[first + i, 0], hist_tau[first + i, 1]
    hist_t[n] = t
    hist_tau[n, 0], hist_tau[n, 1] = tau0, tau1
    ks[KS.N] = n + 1


@njit(cache=True, fastmath=False)
def law_input(io, p, lim, ks, xi, P, st, work, iP):
    """u of the configured law at the io's tick (the C/GMRES update for rhc, falling back to
    eq. 27 clipped to the bounds when its solution is not finite or its residual too large)."""
    law = lim[LIM.LAW]
    r00, r01, r10, r11 = p[PAR.R], p[PAR.R + 1], p[PAR.R + 2], p[PAR.R + 3]
    if law == 0.0:  # eq. (15)
        return -r00 * xi[0] + -r01 * xi[1], -r10 * xi[0] + -r11 * xi[1], False
    u0 = -2.0 * r00 * xi[0] + -2.0 * r01 * xi[1]  # eq. (27)
    u1 = -2.0 * r10 * xi[0] + -2.0 * r11 * xi[1]
    if law == 1.0:
        return u0, u1, False
    t = io[IO.T]
    if math.isnan(ks[KS.T0]):
        ks[KS.T0] = t
    x = st[ST.X : ST.X + XS.SIZE]
    x[XS.Q], x[XS.Q + 1] = io[IO.Q_PRED], io[IO.Q_PRED + 1]
    x[XS.XI], x[XS.XI + 1] = xi[0], xi[1]
    x[XS.F], x[XS.F + 1] = io[IO.F_PRED], io[IO.F_PRED + 1]
    st[ST.T] = t - ks[KS.T0]
    st[ST.MODEL_XDOT] = 1.0
    rk.rhc_tick(P, iP, st, work)  # a solve it does not accept starts from scratch next tick
    if st[ST.INIT] == 0.0:
        return st[ST.U], st[ST.U + 1], False
    ks[KS.FALLBACKS] += 1.0
    if not (math.isfinite(u0) and math.isfinite(u1)):
        return 0.0, 0.0, True
    um0, um1 = lim[LIM.U_MAX], lim[LIM.U_MAX + 1]
    return min(max(u0, -um0), um0), min(max(u1, -um1), um1), True


@njit(cache=True, fastmath=False)
def reset_law(ks, st):
    """Forget the law's warm start (U and Udot, all after the solver state's head; nothing for
    pbc and ioc) and its horizon-growth clock: the next solve starts from scratch."""
    ks[KS.T0] = np.nan
    ks[KS.FALLBACKS] = 0.0
    for i in range(ST.HEAD, st.shape[0]):
        st[i] = 0.0
    st[ST.INIT] = 1.0


@njit(cache=True, fastmath=False)
def decide_tick(io, p, lim, hist_t, hist_tau, ks, P, iP, st, work):
    """One tick of the per-tick rule (see the module docstring); writes the io's outputs."""
    for k in range(IO.OUTPUTS, IO.SIZE):
        io[k] = np.nan
    io[IO.TAU], io[IO.TAU + 1] = 0.0, 0.0
    io[IO.XI], io[IO.XI + 1], io[IO.U], io[IO.U + 1] = 0.0, 0.0, 0.0, 0.0
    io[IO.TAU_SATURATED], io[IO.RESIDUAL], io[IO.ITERATIONS], io[IO.FALLBACK] = 0.0, 0.0, 0.0, 0.0
    now, horizon = io[IO.NOW], lim[LIM.HORIZON]
    if io[IO.ENABLED] == 0.0:
        ks[KS.HOLDING] = 1.0
        io[IO.MODE] = MODE_DRIVE
    elif io[IO.STATE_STALE] != 0.0:
        io[IO.MODE] = MODE_NO_STATE
    else:
        _act(io, p, lim, hist_t, hist_tau, ks, P, iP, st, work)
    record_sent(hist_t, hist_tau, ks, now, io[IO.TAU], io[IO.TAU + 1], horizon)


@njit(cache=True, fastmath=False)
def _act(io, p, lim, hist_t, hist_tau, ks, P, iP, st, work):
    """The hold or the law on the state (and features) brought up to the tick."""
    q, dq, f = io[IO.Q : IO.Q + 2], io[IO.DQ : IO.DQ + 2], io[IO.F : IO.F + 2]
    state_age, f_age = io[IO.STATE_AGE], io[IO.F_AGE]
    usable = io[IO.F_STALE] == 0.0 and math.isfinite(f[0]) and math.isfinite(f[1])
    if state_age > 0 or (usable and f_age > 0):
        q, dq, f = mk.compensate(
            p, q, dq, f, hist_t, hist_tau, int(ks[KS.N]), io[IO.NOW], state_age,
            f_age if usable else 0.0, lim[LIM.HORIZON], lim[LIM.STEP],
        )  # fmt: skip
    io[IO.Q_PRED], io[IO.Q_PRED + 1], io[IO.DQ_PRED], io[IO.DQ_PRED + 1] = q[0], q[1], dq[0], dq[1]
    tm0, tm1 = lim[LIM.TAU_MAX], lim[LIM.TAU_MAX + 1]
    if not usable:  # hold: tau = -2 R dq, clipped (eq. 27 with eta = 0, no feedforward)
        ks[KS.HOLDING] = 1.0
        io[IO.MODE] = MODE_HOLD
        r = p[PAR.R : PAR.R + 4]
        h0 = -2.0 * r[0] * dq[0] + -2.0 * r[1] * dq[1]
        h1 = -2.0 * r[2] * dq[0] + -2.0 * r[3] * dq[1]
        io[IO.TAU], io[IO.TAU + 1] = min(max(h0, -tm0), tm0), min(max(h1, -tm1), tm1)
        return
    if ks[KS.HOLDING] != 0.0:  # features are back: the law starts again
        reset_law(ks, st)
        ks[KS.HOLDING] = 0.0
    io[IO.MODE] = MODE_CONTROL
    io[IO.F_PRED], io[IO.F_PRED + 1] = f[0], f[1]
    xi, tau_ff = mk.prepare(p, q, dq, f)
    io[IO.XI], io[IO.XI + 1] = xi[0], xi[1]
    u0, u1, fallback = law_input(io, p, lim, ks, xi, P, st, work, iP)
    u = np.empty(2)
    u[0], u[1] = u0, u1
    tau, raw, saturated = mk.torque(tau_ff, u, lim[LIM.TAU_MAX : LIM.TAU_MAX + 2])
    io[IO.U], io[IO.U + 1] = u0, u1
    io[IO.TAU_RAW], io[IO.TAU_RAW + 1] = raw[0], raw[1]
    io[IO.TAU_SATURATED] = 1.0 if saturated else 0.0
    io[IO.FALLBACK] = 1.0 if fallback else 0.0
    if lim[LIM.LAW] == 2.0:
        io[IO.RESIDUAL], io[IO.ITERATIONS] = st[ST.RES], st[ST.ITERS]
    if math.isfinite(tau[0]) and math.isfinite(tau[1]):
        io[IO.TAU], io[IO.TAU + 1] = tau[0], tau[1]
    io[IO.COST], io[IO.V] = mk.costs(p, q, xi, f, u)


class CompiledRule:
    """The arrays :func:`decide_tick` works on, and the call itself.

    ``law`` is the law's name (:data:`LAW_CODES`), ``params`` the model's parameter vector
    (:func:`~rt_controller.control.state.pack_params`), ``solver`` the law's C/GMRES solver
    (``None`` for pbc and ioc), whose state vector and work array the call advances in place.
    """

    def __init__(
        self, cfg: RigConfig, law: str, params: np.ndarray, solver: CGMRESSolver | None
    ) -> None:
        self.io = np.zeros(IO.SIZE)
        self.ks = np.zeros(KS.SIZE)
        self.ks[KS.T0] = np.nan
        self.hist_t = np.zeros(CAPACITY)
        self.hist_tau = np.zeros((CAPACITY, 2))
        self.lim = np.zeros(LIM.SIZE)
        self.retarget(cfg, law, params, solver)

    def retarget(
        self, cfg: RigConfig, law: str, params: np.ndarray, solver: CGMRESSolver | None
    ) -> None:
        """Decide with this configuration, model and solver from now on; the torque history
        is kept and the law starts again."""
        self.p = params
        lim = self.lim
        lim[LIM.TAU_MAX : LIM.TAU_MAX + 2] = cfg.robot.tau_max
        lim[LIM.U_MAX : LIM.U_MAX + 2] = cfg.rhc.u_max
        lim[LIM.LAW] = LAW_CODES[law]
        self.limits(cfg)
        lim[LIM.STEP] = STEP_S
        if solver is None:
            self.P, self.iP = np.zeros(1), np.zeros(1, dtype=np.int64)
            self.st, self.work = np.zeros(ST.HEAD), np.zeros(1)
        else:
            self.P, self.iP, self.st, self.work = solver.P, solver.iP, solver.st, solver.work
        self.call: Callable[[], None] = self._first_call
        """Decide on the inputs in :attr:`io` (filling its outputs): after the first call, the
        compiled overload itself with the arrays bound (:meth:`bind`)."""
        reset_law(self.ks, self.st)  # a new law starts; holding stays as it was

    @property
    def horizon_s(self) -> float:
        """The oldest measurement worth compensating, s."""
        return float(self.lim[LIM.HORIZON])

    def __len__(self) -> int:
        """Torques held in the history."""
        return int(self.ks[KS.N])

    def reset(self) -> None:
        """As new: the law starts again, not holding, and the torque history is empty."""
        reset_law(self.ks, self.st)
        self.ks[KS.HOLDING] = 0.0
        self.ks[KS.N] = 0.0

    def limits(self, cfg: RigConfig) -> None:
        """The timeouts (the prediction horizon) of ``cfg`` from now on; the law goes on."""
        c = cfg.controller
        self.lim[LIM.HORIZON] = max(c.state_timeout_s, c.feature_timeout_s)

    @property
    def arguments(self) -> tuple:
        """What :func:`decide_tick` is called with: this rule's arrays."""
        return (
            self.io, self.p, self.lim, self.hist_t, self.hist_tau, self.ks,
            self.P, self.iP, self.st, self.work,
        )  # fmt: skip

    def _first_call(self) -> None:
        decide_tick(*self.arguments)
        self.bind()  # compiled (or loaded from numba's cache) now

    def bind(self) -> None:
        """From now on, :attr:`call` is the compiled overload with this rule's arrays bound:
        one C-level call, past the dispatcher and the attribute loads."""
        args = self.arguments
        self.call = functools.partial(compiled_entry(decide_tick, *args), *args)
