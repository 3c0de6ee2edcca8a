"""The per-tick rule spelt out in Python on the law objects: the oracle the compiled rule
(:class:`rt_controller.control.controller.Controller`, one call of
:func:`~rt_controller.control.decide_kernel.decide_tick`) is held to.

It takes the same inputs as ``Controller.decide`` and answers the same
:class:`~rt_controller.control.controller.Decision` (written into an io vector of the compiled
rule's layout), but every branch is plain Python: the drive and staleness gates, the delay
compensation (:class:`tests.support.state_predictor.StatePredictor`), the hold, the law object
(any :class:`tests.support.python_laws.ControlLaw`: the laws of :mod:`tests.support.python_laws`,
the C/GMRES law on the NumPy reference solver of :mod:`tests.support.rhc_reference`, a test
double), eq. (11) and the costs. Product code never imports it.
"""

from __future__ import annotations

import math
import time

import numpy as np

from hal.config import RigConfig
from rt_controller.control import model_kernels
from rt_controller.control.controller import Decision
from rt_controller.control.model import NominalModel
from rt_controller.control.state import (
    IO,
    MODE_CONTROL,
    MODE_DRIVE,
    MODE_HOLD,
    MODE_NO_STATE,
    pack_params,
)
from tests.support.python_laws import ControlLaw, Measurement, make_law
from tests.support.state_predictor import StatePredictor


def finite2(v: np.ndarray) -> bool:
    """Whether both entries of a 2-vector are finite."""
    return math.isfinite(v[0]) and math.isfinite(v[1])


class PythonRule:
    """``Controller``'s public face (``decide``, ``reconfigure``, ``reset``, ``warm_up``,
    ``law``: the law's name, ``model``) on a law object (``law_object``, built by name or
    given), plus its ``predictor``."""

    def __init__(self, cfg: RigConfig, law: str | ControlLaw | None = None) -> None:
        self.cfg = cfg
        self.model = NominalModel.from_config(cfg)
        self._p = pack_params(self.model)
        name = cfg.controller.law if law is None else law
        self.law_object: ControlLaw = (
            make_law(name, self.model, cfg) if isinstance(name, str) else name
        )
        self.law = self.law_object.name
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
            self._p = pack_params(self.model)
            self.law_object = make_law(cfg.controller.law, self.model, cfg)
            self.law = self.law_object.name
        self.predictor.retarget(self._p, self._horizon(cfg))

    def reset(self) -> None:
        self.law_object.reset()
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
        io = np.full(IO.SIZE, np.nan)  # the compiled rule's io vector, outputs as it sets them
        io[IO.TAU : IO.TAU + 2] = 0.0
        io[IO.XI : IO.XI + 2] = io[IO.U : IO.U + 2] = 0.0
        io[[IO.TAU_SATURATED, IO.RESIDUAL, IO.ITERATIONS, IO.FALLBACK]] = 0.0
        solve_ns = 0
        if drive_mode != "enabled":
            self._holding = True
            io[IO.MODE] = MODE_DRIVE
        elif state_stale:
            io[IO.MODE] = MODE_NO_STATE
        else:
            solve_ns = self._act(io, t, now, (q, dq, f), f_stale, (state_age_s, feature_age_s))
        self.predictor.sent(now, io[IO.TAU : IO.TAU + 2].copy())
        return Decision(io, drive_mode, solve_ns)

    def _act(self, io, t, now, qdqf, f_stale, ages) -> int:
        """The hold or the law on the state (and features) brought up to the tick; the law's
        own time, ns."""
        q, dq, f = (np.asarray(v, dtype=float) for v in qdqf)
        state_age, f_age = ages
        usable = not f_stale and finite2(f)
        if state_age > 0 or (usable and f_age > 0):
            q, dq, f = self.predictor.compensate(now, q, dq, f, state_age, f_age if usable else 0)
        io[IO.Q_PRED : IO.Q_PRED + 2], io[IO.DQ_PRED : IO.DQ_PRED + 2] = q, dq
        if not usable:  # hold: a joint damper, eq. (27) with eta = 0 and no feedforward
            self._holding = True
            io[IO.MODE] = MODE_HOLD
            hold = np.clip(-2.0 * self.model.R @ dq, -self.tau_max, self.tau_max)
            io[IO.TAU : IO.TAU + 2] = hold
            return 0
        if self._holding:
            self.law_object.reset()
            self._holding = False
        io[IO.MODE] = MODE_CONTROL
        io[IO.F_PRED : IO.F_PRED + 2] = f
        xi, tau_ff = model_kernels.prepare(self._p, q, dq, f)
        start = time.perf_counter_ns()
        out = self.law_object(Measurement(t=t, q=q, dq=dq, f=f, xi=xi))
        solve_ns = time.perf_counter_ns() - start
        u = np.asarray(out.u, dtype=float)
        tau, raw, saturated = model_kernels.torque(tau_ff, u, self.tau_max)  # eq. (11)
        io[IO.XI : IO.XI + 2], io[IO.U : IO.U + 2] = xi, u
        io[IO.TAU_RAW : IO.TAU_RAW + 2] = raw
        io[IO.TAU_SATURATED], io[IO.FALLBACK] = float(saturated), float(out.fallback)
        io[IO.RESIDUAL], io[IO.ITERATIONS] = out.residual, out.iterations
        if finite2(tau):
            io[IO.TAU : IO.TAU + 2] = tau
        io[IO.COST], io[IO.V] = model_kernels.costs(self._p, q, xi, f, u)
        return solve_ns
