"""The compiled C/GMRES solver: its state (U, Udot, workspace) around one numba call per tick."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numba
import numpy as np

from hal.config import RigConfig
from rt_controller.control.model import NominalModel
from rt_controller.control.model_kernels import prepare
from rt_controller.control.rhc.kernel import rhc_tick
from rt_controller.control.rhc.problem import pack_params
from rt_controller.control.state import NS, NX, ST, work_length


class SolveReport(NamedTuple):
    """Result of one solver update (a tuple: cheap to build on every tick)."""

    u: np.ndarray
    """Input to apply (clipped to the bounds); meaningless when not ``ok``."""
    residual: float
    """Optimality residual ||F|| of the solution the input comes from."""
    iterations: int
    """GMRES iterations (forward-difference products) spent, all Newton steps when
    ``initialised``."""
    ok: bool
    """Finite and at most ``rhc.residual_bound``; otherwise the solver re-initialises next time."""
    initialised: bool
    """This update solved from scratch (Newton-GMRES)."""


def compiled_entry(dispatcher, *args) -> Callable:
    """The compiled function of ``dispatcher`` for the types of ``args``, called directly.

    The overload's own CPython wrapper skips the dispatcher's per-call type resolution (a few
    microseconds when the interpreter's caches are cold, as at 50 Hz). The arrays passed later
    must have exactly these types; falls back to the dispatcher if there is no such overload.
    """
    sig = tuple(numba.typeof(a) for a in args)
    cres = dispatcher.overloads.get(sig)
    return dispatcher if cres is None else cres.entry_point


def pack_state(q: np.ndarray, xi: np.ndarray, f: np.ndarray, out: np.ndarray | None = None):
    """The prediction state x = (q, xi, f) (6)."""
    x = np.empty(NX) if out is None else out
    x[0:2] = q
    x[2:4] = xi
    x[4:6] = f
    return x


class CGMRESSolver:
    """Continuation/GMRES solver of eq. (30); one compiled call per :meth:`update`.

    All the solver's state lives in one float64 vector ``st`` (the measured state, the flags, the
    outputs, U and Udot; layout :data:`~rt_controller.control.state.ST`) and one work array, so
    a tick is a single compiled call with four array arguments (after :meth:`warm_up`, straight
    to the compiled overload) and nothing is allocated but the report.
    """

    def __init__(self, model: NominalModel, cfg: RigConfig) -> None:
        self.cfg = cfg
        self.P, self.iP = pack_params(model, cfg)
        self.N = cfg.rhc.steps
        n = NS * self.N
        self.st = np.zeros(ST.HEAD + 2 * n)
        self.U = self.st[ST.HEAD : ST.HEAD + n]
        self.Udot = self.st[ST.HEAD + n : ST.HEAD + 2 * n]
        self._x = self.st[ST.X : ST.X + NX]
        self._xdot = self.st[ST.XDOT : ST.XDOT + NX]
        self.work = np.zeros(work_length(self.iP))
        self.st[ST.INIT] = 1.0
        self._tick: Callable = rhc_tick

    @property
    def dispatch_free(self) -> bool:
        """Whether a tick calls the compiled entry directly, skipping numba's dispatcher (after
        :meth:`warm_up`)."""
        return self._tick is not rhc_tick

    @property
    def needs_init(self) -> bool:
        """The next update solves from scratch (kept in the state vector, so the compiled
        per-tick rule that advances this solver's arrays shares it)."""
        return self.st[ST.INIT] != 0.0

    @needs_init.setter
    def needs_init(self, value: bool) -> None:
        self.st[ST.INIT] = float(value)

    def reset(self) -> None:
        """Forget the warm start: the next update solves from scratch."""
        self.U[:] = 0.0
        self.Udot[:] = 0.0
        self.needs_init = True

    @property
    def last_fevals(self) -> int:
        """Evaluations of F (forward and backward sweep pairs) in the last update."""
        return int(self.st[ST.FEVALS])

    def update(self, x: np.ndarray, t: float, xdot: np.ndarray | None = None) -> SolveReport:
        """One tick at state ``x`` (6) and solver time ``t`` (s, for the horizon growth).

        ``xdot`` overrides the predicted state motion (zeros freeze the state); by default it is
        eq. (12) under the warm start's first input (under the applied one after a Newton solve).
        """
        st = self.st
        self._x[:] = x
        init = self.needs_init
        st[ST.T] = t
        if xdot is None:
            st[ST.MODEL_XDOT] = 1.0
        else:
            st[ST.MODEL_XDOT] = 0.0
            self._xdot[:] = xdot
        self._tick(self.P, self.iP, st, self.work)
        u = st[ST.U : ST.U + 2].copy()
        return SolveReport(u, float(st[ST.RES]), int(st[ST.ITERS]), not self.needs_init, init)

    def warm_up(self) -> None:
        """Compile (or load from the numba cache) before the first tick, then reset."""
        s = self.cfg.scenario
        q, dq, f = (np.array(v, dtype=float) for v in (s.q0, s.dq0, s.f0))
        xi, _ = prepare(self.P, q, dq, f)
        x = pack_state(q, xi, f)
        self.update(x, 0.0)
        self.update(x, 1.0 / self.cfg.rates.control_hz)
        self.reset()
        self._tick = compiled_entry(rhc_tick, self.P, self.iP, self.st, self.work)
