"""The compiled C/GMRES solver: its state (U, Udot, workspace) around one numba call per tick."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hal.config import RigConfig
from rt_controller.control.model import NominalModel
from rt_controller.control.rhc.kernel import OK, new_workspace, rhc_tick
from rt_controller.control.rhc.problem import I_INIT_KRYLOV, NS, NX, pack_params


@dataclass(frozen=True)
class SolveReport:
    """Result of one solver update."""

    u: np.ndarray
    """Input to apply (clipped to the bounds); meaningless when not ``ok``."""
    residual: float
    """Optimality residual ||F|| of the solution the input comes from."""
    iterations: int
    """GMRES iterations spent (all Newton steps when ``initialised``)."""
    ok: bool
    """Finite and below ``rhc.residual_bound``; otherwise the solver re-initialises next time."""
    initialised: bool
    """This update solved from scratch (Newton-GMRES)."""


def pack_state(q: np.ndarray, xi: np.ndarray, f: np.ndarray, out: np.ndarray | None = None):
    """The prediction state x = (q, xi, f) (6)."""
    x = np.empty(NX) if out is None else out
    x[0:2] = q
    x[2:4] = xi
    x[4:6] = f
    return x


class CGMRESSolver:
    """Continuation/GMRES solver of eq. (30); one compiled call per :meth:`update`."""

    def __init__(self, model: NominalModel, cfg: RigConfig) -> None:
        self.model = model
        self.cfg = cfg
        self.P, self.iP = pack_params(model, cfg)
        self.N = cfg.rhc.steps
        self.kmax = cfg.rhc.kmax
        self.residual_bound = cfg.rhc.residual_bound
        n = NS * self.N
        self.U = np.zeros(n)
        self.Udot = np.zeros(n)
        self.work = new_workspace(self.N, self.kmax, int(self.iP[I_INIT_KRYLOV]))
        self._xdot = np.zeros(NX)
        self._u = np.zeros(2)
        self.needs_init = True

    def reset(self) -> None:
        """Forget the warm start: the next update solves from scratch."""
        self.U[:] = 0.0
        self.Udot[:] = 0.0
        self.needs_init = True

    @property
    def stages(self) -> np.ndarray:
        """View of U as (N, 6) rows (u1, u2, v1, v2, mu1, mu2)."""
        return self.U.reshape(self.N, NS)

    def update(self, x: np.ndarray, t: float, xdot: np.ndarray | None = None) -> SolveReport:
        """One tick at state ``x`` (6) and solver time ``t`` (s, for the horizon growth).

        ``xdot`` overrides the predicted state motion (zeros freeze the state); by default it is
        eq. (12) under the applied input.
        """
        x = np.ascontiguousarray(x, dtype=np.float64)  # one compiled signature only
        init = self.needs_init
        model_xdot = xdot is None
        if not model_xdot:
            self._xdot[:] = xdot
        residual, iterations, status = rhc_tick(
            self.P,
            self.iP,
            self.U,
            self.Udot,
            x,
            self._xdot,
            float(t),
            init,
            model_xdot,
            self._u,
            self.work,
        )
        ok = status == OK and residual <= self.residual_bound
        self.needs_init = not ok
        return SolveReport(self._u.copy(), float(residual), int(iterations), bool(ok), init)

    def warm_up(self) -> None:
        """Compile (or load from the numba cache) before the first tick, then reset."""
        m, s = self.model, self.cfg.scenario
        q = np.array(s.q0, dtype=float)
        f = np.array(s.f0, dtype=float)
        xi = m.xi(q, np.array(s.dq0, dtype=float), f)
        x = pack_state(q, xi, f)
        self.update(x, 0.0)
        self.update(x, 1.0 / self.cfg.rates.control_hz)
        self.reset()
