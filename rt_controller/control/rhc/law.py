"""Receding-horizon control (eq. 30) as a :class:`~rt_controller.control.laws.ControlLaw`."""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from hal.config import RigConfig
from rt_controller.control.laws import LawOutput, Measurement, inverse_optimal
from rt_controller.control.model import NominalModel
from rt_controller.control.rhc.solver import CGMRESSolver, SolveReport, pack_state
from rt_controller.control.state import NX


class Solver(Protocol):
    """What the law needs from a solver (the compiled one or the NumPy reference)."""

    needs_init: bool

    def update(self, x: np.ndarray, t: float, xdot: np.ndarray | None = None) -> SolveReport: ...

    def reset(self) -> None: ...


class RecedingHorizonLaw:
    """u from the C/GMRES solution of eq. (30), warm-started every tick.

    The call is a pure function of the measurement and the solver state (U, Udot, the time the
    law started). A non-finite solution or one whose residual exceeds ``rhc.residual_bound``
    is never applied: that tick gets the inverse-optimal law u = -2 R xi (eq. 27) clipped to the
    bounds ``rhc.u_max`` (zeros if xi itself is not finite), and the solver solves from scratch
    (Newton-GMRES) at the next tick. The applied u always satisfies |u_i| <= umax_i.
    The product decides with the compiled rule on this solver's arrays (warmed up by
    :meth:`~rt_controller.control.controller.Controller.warm_up`); this call is the test
    oracle's spelling.
    """

    name = "rhc"

    def __init__(
        self, model: NominalModel, cfg: RigConfig, *, solver: Solver | None = None
    ) -> None:
        self.model = model
        self.cfg = cfg
        self.solver: Solver = CGMRESSolver(model, cfg) if solver is None else solver
        self._x = np.zeros(NX)
        self._umax = np.asarray(cfg.rhc.u_max, dtype=float)
        self._t0: float | None = None
        self.fallbacks = 0
        """Ticks that fell back to the inverse-optimal law since construction or :meth:`reset`."""

    def reset(self) -> None:
        """Forget the warm start and the horizon-growth clock."""
        self.solver.reset()
        self._t0 = None
        self.fallbacks = 0

    def fallback_input(self, m: Measurement) -> np.ndarray:
        """Eq. (27) clipped to the bounds |u_i| <= umax_i (zeros if xi is not finite)."""
        u = inverse_optimal(self.model, np.asarray(m.xi, dtype=float))
        if not np.all(np.isfinite(u)):
            return np.zeros(2)
        return np.clip(u, -self._umax, self._umax)

    def __call__(self, m: Measurement) -> LawOutput:
        start = time.perf_counter_ns()
        if self._t0 is None:
            self._t0 = m.t
        x = pack_state(m.q, m.xi, m.f, out=self._x)
        rep = self.solver.update(x, m.t - self._t0)
        solve_ns = time.perf_counter_ns() - start
        if rep.ok:
            return LawOutput(
                u=rep.u, residual=rep.residual, iterations=rep.iterations, solve_ns=solve_ns
            )
        self.fallbacks += 1
        u = self.fallback_input(m)
        return LawOutput(
            u=u,
            residual=rep.residual,
            iterations=rep.iterations,
            fallback=True,
            solve_ns=solve_ns,
        )
