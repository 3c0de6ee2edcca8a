"""The control laws as Python objects: the oracle's spelling of what the compiled rule's
``decide_kernel.law_input`` does (eq. 15, eq. 27, and the C/GMRES update of eq. 30 with its
fallback). :class:`tests.support.python_rule.PythonRule` calls them once per tick; product code
never imports them.

A law maps a :class:`Measurement` to a :class:`LawOutput`; ``reset`` forgets any warm start.
:func:`make_law` builds one by name as ``cls(model, cfg)``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hal.config import LAW_NAMES, RigConfig
from rt_controller.control.model import NominalModel
from rt_controller.control.rhc.solver import CGMRESSolver, SolveReport, pack_state
from rt_controller.control.state import NX


@dataclass(frozen=True)
class Measurement:
    """What a law sees at one tick: time (s) and the state of the visual feedback system."""

    t: float
    q: np.ndarray
    dq: np.ndarray
    f: np.ndarray
    xi: np.ndarray


@dataclass(frozen=True)
class LawOutput:
    """The input u of eq. (11) with the solver's report (zeros for the closed-form laws)."""

    u: np.ndarray
    residual: float = 0.0
    iterations: int = 0
    fallback: bool = False
    solve_ns: int = 0


class ControlLaw(Protocol):
    """A law computes u from a measurement; ``reset`` forgets any warm start."""

    name: str

    def __call__(self, m: Measurement) -> LawOutput: ...

    def reset(self) -> None: ...


def passivity_based(model: NominalModel, xi: np.ndarray) -> np.ndarray:
    """u_p = -R xi, eq. (15)."""
    return -model.R @ xi


def inverse_optimal(model: NominalModel, xi: np.ndarray) -> np.ndarray:
    """u_inv = -2 R xi, eq. (27)."""
    return -2.0 * model.R @ xi


class PassivityBasedLaw:
    """Eq. (15)."""

    name = "pbc"

    def __init__(self, model: NominalModel, cfg: RigConfig | None = None) -> None:
        self.model = model

    def __call__(self, m: Measurement) -> LawOutput:
        return LawOutput(u=passivity_based(self.model, m.xi))

    def reset(self) -> None:
        """Stateless: nothing to forget."""


class InverseOptimalLaw(PassivityBasedLaw):
    """Eq. (27)."""

    name = "ioc"

    def __call__(self, m: Measurement) -> LawOutput:
        return LawOutput(u=inverse_optimal(self.model, m.xi))


class Solver(Protocol):
    """What the law needs from a solver (the compiled one or the NumPy reference)."""

    needs_init: bool

    def update(self, x: np.ndarray, t: float, xdot: np.ndarray | None = None) -> SolveReport: ...

    def reset(self) -> None: ...


class RecedingHorizonLaw:
    """u from the C/GMRES solution of eq. (30), warm-started every tick.

    A non-finite solution or one whose residual exceeds ``rhc.residual_bound`` is never applied:
    that tick gets eq. (27) clipped to ``rhc.u_max`` (zeros if xi is not finite), and the solver
    solves from scratch at the next tick.
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
        return LawOutput(
            u=self.fallback_input(m),
            residual=rep.residual,
            iterations=rep.iterations,
            fallback=True,
            solve_ns=solve_ns,
        )


LAWS: dict[str, type] = {
    "pbc": PassivityBasedLaw,
    "ioc": InverseOptimalLaw,
    "rhc": RecedingHorizonLaw,
}
"""Law name -> class, built as ``cls(model, cfg)``; the names are :data:`hal.config.LAW_NAMES`."""


def make_law(name: str, model: NominalModel, cfg: RigConfig) -> ControlLaw:
    """The law called ``name`` (one of :data:`hal.config.LAW_NAMES`) for this model and config."""
    if name not in LAWS:
        raise ValueError(f"unknown law {name!r} (choose from {', '.join(LAW_NAMES)})")
    return LAWS[name](model, cfg)
