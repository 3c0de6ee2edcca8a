"""The per-tick rule spelt out in Python on the law objects: the oracle the compiled rule
(:class:`rt_controller.control.controller.Controller`, one call of
:func:`~rt_controller.control.decide_kernel.decide_tick`) is held to.

It takes the same inputs as ``Controller.decide`` and answers the same
:class:`~rt_controller.control.controller.Decision` (written into an io vector of the compiled
rule's layout), but every branch is plain Python: the drive and staleness gates, the delay
compensation (:class:`~rt_controller.control.state_predictor.StatePredictor`), the hold, the
law object (any :class:`~rt_controller.control.laws.ControlLaw`: the built-in laws, the C/GMRES
law on the NumPy reference solver of :mod:`tests.support.rhc_reference`, a test double), eq. (11)
and the costs. Product code never imports it.
"""

from __future__ import annotations

import math
import time

import numpy as np

from hal.config import RigConfig
from rt_controller.control import decide_kernel as dk
from rt_controller.control import model_kernels
from rt_controller.control.controller import Decision
from rt_controller.control.law_table import make_law
from rt_controller.control.laws import ControlLaw, Measurement
from rt_controller.control.model import NominalModel
from rt_controller.control.state_predictor import StatePredictor


def finite2(v: np.ndarray) -> bool:
    """Whether both entries of a 2-vector are finite."""
    return math.isfinite(v[0]) and math.isfinite(v[1])


class PythonRule:
    """``Controller``'s public face (``decide``, ``reconfigure``, ``reset``, ``warm_up``,
    ``law``, ``model``, ``predictor``) on a law object; ``law`` is a name or an object."""

    def __init__(self, cfg: RigConfig, law: str | ControlLaw | None = None) -> None:
        self.cfg = cfg
        self.model = NominalModel.from_config(cfg)
        self._p = model_kernels.pack(self.model)
        name = cfg.controller.law if law is None else law
        self.law: ControlLaw = make_law(name, self.model, cfg) if isinstance(name, str) else name
        self.tau_max = np.array(cfg.robot.tau_max, dtype=float)
        self._holding = False
        self.predictor = StatePredictor(self._p, self._horizon(cfg))

    @staticmethod
    def _horizon(cfg: RigConfig) -> float:
        return max(cfg.controller.state_timeout_s, cfg.controller.feature_timeout_s)

    def reconfigure(self, cfg: RigConfig, *, law_changed: bool = True) -> None:
        """As ``Controller.reconfigure``: a new model and law object when ``law_changed``."""
        self.cfg = cfg
        if law_changed:
            self.model = NominalModel.from_config(cfg)
            self._p = model_kernels.pack(self.model)
            self.law = make_law(cfg.controller.law, self.model, cfg)
        self.predictor.retarget(self._p, self._horizon(cfg))

    def reset(self) -> None:
        self.law.reset()
        self.predictor.reset()
        self._holding = False

    def warm_up(self) -> None:
        """Nothing to compile beyond the law object's own; as new."""
        self.reset()

    def decide(
        self,
        t: float,
        q: np.ndarray,
        dq: np.ndarray,
        f: np.ndarray,
        *,
        f_stale: bool,
        state_stale: bool,
        drive_mode: str = "enabled",
        state_age_s: float = 0.0,
        feature_age_s: float = 0.0,
        now_s: float | None = None,
    ) -> Decision:
        now = t if now_s is None else now_s
        io = np.full(dk.N_IO, np.nan)
        io[dk.OUT_TAU : dk.OUT_TAU + 2] = 0.0
        io[dk.OUT_XI : dk.OUT_XI + 2] = io[dk.OUT_U : dk.OUT_U + 2] = 0.0
        io[[dk.OUT_SAT, dk.OUT_RES, dk.OUT_ITERS, dk.OUT_FALLBACK]] = 0.0
        solve_ns = 0
        if drive_mode != "enabled":
            self._holding = True
            io[dk.OUT_MODE] = dk.MODE_DRIVE
        elif state_stale:
            io[dk.OUT_MODE] = dk.MODE_NO_STATE
        else:
            solve_ns = self._act(io, t, now, (q, dq, f), f_stale, (state_age_s, feature_age_s))
        self.predictor.sent(now, io[dk.OUT_TAU : dk.OUT_TAU + 2].copy())
        return Decision(io, drive_mode, t, solve_ns)

    def _act(self, io, t, now, qdqf, f_stale, ages) -> int:
        """The hold or the law on the state (and features) brought up to the tick; the law's
        own time, ns."""
        q, dq, f = (np.asarray(v, dtype=float) for v in qdqf)
        state_age, f_age = ages
        usable = not f_stale and finite2(f)
        if state_age > 0 or (usable and f_age > 0):
            q, dq, f = self.predictor.compensate(now, q, dq, f, state_age, f_age if usable else 0)
        io[dk.OUT_Q : dk.OUT_Q + 2], io[dk.OUT_DQ : dk.OUT_DQ + 2] = q, dq
        if not usable:  # hold: a joint damper, eq. (27) with eta = 0 and no feedforward
            self._holding = True
            io[dk.OUT_MODE] = dk.MODE_HOLD
            hold = np.clip(-2.0 * self.model.R @ dq, -self.tau_max, self.tau_max)
            io[dk.OUT_TAU : dk.OUT_TAU + 2] = hold
            return 0
        if self._holding:
            self.law.reset()
            self._holding = False
        io[dk.OUT_MODE] = dk.MODE_CONTROL
        io[dk.OUT_F : dk.OUT_F + 2] = f
        xi, tau_ff = model_kernels.prepare(self._p, q, dq, f)
        start = time.perf_counter_ns()
        out = self.law(Measurement(t=t, q=q, dq=dq, f=f, xi=xi))
        solve_ns = time.perf_counter_ns() - start
        u = np.asarray(out.u, dtype=float)
        tau, raw, saturated = model_kernels.torque(tau_ff, u, self.tau_max)  # eq. (11)
        io[dk.OUT_XI : dk.OUT_XI + 2], io[dk.OUT_U : dk.OUT_U + 2] = xi, u
        io[dk.OUT_RAW : dk.OUT_RAW + 2] = raw
        io[dk.OUT_SAT], io[dk.OUT_FALLBACK] = float(saturated), float(out.fallback)
        io[dk.OUT_RES], io[dk.OUT_ITERS] = out.residual, out.iterations
        if finite2(tau):
            io[dk.OUT_TAU : dk.OUT_TAU + 2] = tau
        io[dk.OUT_COST], io[dk.OUT_V] = model_kernels.costs(self._p, q, xi, f, u)
        return solve_ns
