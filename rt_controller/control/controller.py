"""One control step: measurement -> law -> torque (eq. 11), independent of any I/O.

:meth:`Controller.decide` (the per-tick rule of the daemon, replay and simulation) runs as one
compiled call (:mod:`~rt_controller.control.decide_kernel`) for the configured law;
:meth:`Controller.step` is the same rule spelt out in Python on the law object, the readable
reference the tests hold the compiled call to, and the path for a law given as an object (the
NumPy reference solver, a test double).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from hal.config import RigConfig
from rt_controller.control import decide_kernel as dk
from rt_controller.control import model_kernels
from rt_controller.control.law_table import make_law
from rt_controller.control.laws import ControlLaw, LawOutput, Measurement
from rt_controller.control.model import NominalModel
from rt_controller.control.state_predictor import StatePredictor

_isfinite = math.isfinite
_MODE_NAMES = ("control", "hold", "no_state")
"""The names of the compiled rule's modes ``MODE_CONTROL``, ``MODE_HOLD``, ``MODE_NO_STATE``
(``MODE_DRIVE`` is named by the drive's mode)."""


def finite2(v: np.ndarray) -> bool:
    """Whether both entries of a 2-vector are finite (a scalar test: no array temporaries)."""
    return _isfinite(v[0]) and _isfinite(v[1])


def _floats(v: np.ndarray) -> np.ndarray:
    """``v`` as a float64 array, without a copy when it is one already."""
    return v if type(v) is np.ndarray and v.dtype == np.float64 else np.asarray(v, dtype=float)


@dataclass(frozen=True)
class Command:
    """What one tick decided: the law's output, the torque of eq. (11) and its saturated value."""

    measurement: Measurement
    law: LawOutput
    tau_raw: np.ndarray
    tau: np.ndarray
    saturated: bool


class Decision:
    """One tick of the daemon: the torque to send and how it was obtained.

    Built from the compiled rule's outputs (:meth:`from_outputs`), the fields beyond ``tau``
    and ``mode`` are made when first read: the loop reads only the record's numbers
    (:meth:`record_fields`).
    """

    __slots__ = ("_V", "_command", "_cost", "_features", "_out", "_state", "_tau", "mode", "torque")

    def __init__(
        self,
        tau: np.ndarray,
        mode: str,
        command: Command | None = None,
        state: tuple[np.ndarray, np.ndarray] | None = None,
        features: np.ndarray | None = None,
        cost: float = math.nan,
        V: float = math.nan,
    ) -> None:
        self._tau = tau
        self.torque = (float(tau[0]), float(tau[1]))
        """The torque to send, as the pair of floats the write takes."""
        self.mode = mode
        """``control`` (the law ran), ``hold`` (stale features: joint damper), ``no_state``, or
        the drive's mode when it is not enabled (``disarmed``, ``fault``, ...)."""
        self._command, self._state, self._features = command, state, features
        self._cost, self._V = cost, V
        self._out: tuple[list[float], float, int] | None = None

    @classmethod
    def from_outputs(cls, io: np.ndarray, drive_mode: str, t: float, solve_ns: int) -> Decision:
        """The decision in the outputs of the compiled rule's io vector
        (:mod:`~rt_controller.control.decide_kernel`), copied; ``solve_ns`` is the call's
        duration. Only the torque pair and the mode are made now (the write needs them)."""
        v = io.tolist()
        d = cls.__new__(cls)
        d._tau, d.torque = None, (v[dk.OUT_TAU], v[dk.OUT_TAU + 1])
        mode = int(v[dk.OUT_MODE])
        d.mode = _MODE_NAMES[mode] if mode < len(_MODE_NAMES) else drive_mode
        d._command = d._state = d._features = None
        d._out = (v, t, solve_ns)
        d._cost, d._V = v[dk.OUT_COST], v[dk.OUT_V]
        return d

    @property
    def tau(self) -> np.ndarray:
        """The torque to send (2,), as an array (:attr:`torque` is the same pair of floats)."""
        if self._tau is None:
            self._tau = np.array(self.torque)
        return self._tau

    def _vec(self, k: int) -> np.ndarray:
        assert self._out is not None
        return np.array(self._out[0][k : k + 2])

    @property
    def command(self) -> Command | None:
        """The law's step when ``mode == "control"``."""
        if self._command is None and self._out is not None and self.mode == "control":
            v, t, solve_ns = self._out
            q, dq = self.state  # type: ignore[misc]
            m = Measurement(t=t, q=q, dq=dq, f=self.features, xi=self._vec(dk.OUT_XI))
            law = LawOutput(
                u=self._vec(dk.OUT_U),
                residual=v[dk.OUT_RES],
                iterations=int(v[dk.OUT_ITERS]),
                fallback=bool(v[dk.OUT_FALLBACK]),
                solve_ns=solve_ns,
            )
            self._command = Command(m, law, self._vec(dk.OUT_RAW), self.tau, bool(v[dk.OUT_SAT]))
        return self._command

    @property
    def state(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(q, dq) the hold or the law acted on: the joint state brought up to the tick (as
        measured when its age was not given); ``None`` when neither ran."""
        if self._state is None and self._out is not None and self.mode in ("control", "hold"):
            self._state = (self._vec(dk.OUT_Q), self._vec(dk.OUT_DQ))
        return self._state

    @property
    def features(self) -> np.ndarray | None:
        """f the law acted on: the features brought up to the tick (as measured when their age
        was not given); ``None`` when the law did not run."""
        if self._features is None and self._out is not None and self.mode == "control":
            self._features = self._vec(dk.OUT_F)
        return self._features

    @property
    def cost(self) -> float:
        """l(x_k, u_k) of eq. (25) for this tick; NaN when the law did not run."""
        return self._cost

    @property
    def V(self) -> float:
        """V(x_k) of eq. (13) for this tick; NaN when the law did not run."""
        return self._V

    @property
    def solve_ns(self) -> int:
        """The law's (or the compiled rule's) own time, ns; 0 when no law ran."""
        if self._out is not None:
            return self._out[2] if self.mode == "control" else 0
        return 0 if self._command is None else self._command.law.solve_ns

    def record_fields(self, law_name: str) -> dict[str, Any]:
        """The cycle record's output fields (see :func:`rt_controller.runtime.cycle_record.
        decision_fields`)."""
        nan2 = [math.nan, math.nan]
        if self._out is not None:
            v = self._out[0]
            ran, acted = self.mode == "control", self.mode in ("control", "hold")
            return {
                "q_pred": v[dk.OUT_Q : dk.OUT_Q + 2] if acted else nan2,
                "dq_pred": v[dk.OUT_DQ : dk.OUT_DQ + 2] if acted else nan2,
                "f_pred": v[dk.OUT_F : dk.OUT_F + 2] if ran else nan2,
                "xi": v[dk.OUT_XI : dk.OUT_XI + 2],
                "u": v[dk.OUT_U : dk.OUT_U + 2],
                "tau": v[dk.OUT_TAU : dk.OUT_TAU + 2],
                "tau_saturated": v[dk.OUT_SAT] != 0.0,
                "law": law_name if ran else self.mode,
                "residual": v[dk.OUT_RES],
                "iterations": int(v[dk.OUT_ITERS]),
                "fallback": v[dk.OUT_FALLBACK] != 0.0,
                "cost": v[dk.OUT_COST],
                "V": v[dk.OUT_V],
            }
        cmd, state = self._command, self._state
        law = None if cmd is None else cmd.law
        return {
            "q_pred": nan2 if state is None else [float(state[0][0]), float(state[0][1])],
            "dq_pred": nan2 if state is None else [float(state[1][0]), float(state[1][1])],
            "f_pred": nan2 if self._features is None else [float(x) for x in self._features],
            "xi": [0.0, 0.0] if cmd is None else [float(x) for x in cmd.measurement.xi],
            "u": [0.0, 0.0] if law is None else [float(x) for x in law.u],
            "tau": [float(self.tau[0]), float(self.tau[1])],
            "tau_saturated": False if cmd is None else bool(cmd.saturated),
            "law": self.mode if cmd is None else law_name,
            "residual": 0.0 if law is None else float(law.residual),
            "iterations": 0 if law is None else int(law.iterations),
            "fallback": False if law is None else bool(law.fallback),
            "cost": float(self._cost),
            "V": float(self._V),
        }


class Controller:
    """Pure step function around a control law; the caller owns clocks and transports."""

    def __init__(self, cfg: RigConfig, law: str | ControlLaw | None = None) -> None:
        self.cfg = cfg
        self.model = NominalModel.from_config(cfg)
        self._p = model_kernels.pack(self.model)
        name = cfg.controller.law if law is None else law
        self.law: ControlLaw = make_law(name, self.model, cfg) if isinstance(name, str) else name
        self.tau_max = np.array(cfg.robot.tau_max, dtype=float)
        self._holding = False
        c = cfg.controller
        self._predictor = StatePredictor(self._p, max(c.state_timeout_s, c.feature_timeout_s))
        self.rule: dk.CompiledRule | None = None
        """The compiled per-tick rule of a built-in law (``None`` for a law given as object)."""
        if isinstance(name, str):
            self.rule = dk.CompiledRule(cfg, name, self._p, getattr(self.law, "solver", None))

    @property
    def predictor(self) -> StatePredictor:
        """The torques sent and the motion of the nominal arm under them (for the compiled
        rule: a view of its history as of now)."""
        if self.rule is None:
            return self._predictor
        r = self.rule
        return StatePredictor(self._p, r.horizon_s, history=(r.hist_t, r.hist_tau, len(r)))

    def reconfigure(self, cfg: RigConfig, *, law_changed: bool = True) -> None:
        """Run from now on with ``cfg``, which differs from the current configuration only in
        online-tunable keys (:data:`rt_controller.calibration.parameters.TUNABLE`); called between
        two ticks, by the loop and by ``hil replay`` at the same tick.

        The model's gains and the law are rebuilt when ``law_changed`` (a new law starts as at
        the run's start: C/GMRES solves its first tick from scratch, and falls back to eq. 27
        when that solve diverges); the state predictor keeps the torques it sent."""
        self.cfg = cfg
        c = cfg.controller
        if law_changed:
            self.model = NominalModel.from_config(cfg)
            self._p = model_kernels.pack(self.model)
            self.law = make_law(c.law, self.model, cfg)
            if self.rule is not None:
                self.rule.retarget(cfg, c.law, self._p, getattr(self.law, "solver", None))
        if self.rule is not None:
            self.rule.limits(cfg)
        self._predictor.retarget(self._p, max(c.state_timeout_s, c.feature_timeout_s))

    def reset(self) -> None:
        """As new: the law starts again, no torque sent, not holding."""
        self.law.reset()
        self._predictor.reset()
        self._holding = False
        if self.rule is not None:
            self.rule.reset()

    def measurement(self, t: float, q: np.ndarray, dq: np.ndarray, f: np.ndarray) -> Measurement:
        q, dq, f = (np.asarray(v, dtype=float) for v in (q, dq, f))
        return Measurement(t=t, q=q, dq=dq, f=f, xi=model_kernels.prepare(self._p, q, dq, f)[0])

    def hold_torque(self, dq: np.ndarray) -> np.ndarray:
        """Safe torque without image features: tau = -2 R dq (a joint damper, eq. 27 with
        eta = 0 and no feedforward), clipped to the amplifier limits."""
        return np.clip(-2.0 * self.model.R @ dq, -self.tau_max, self.tau_max)

    def step(self, t: float, q: np.ndarray, dq: np.ndarray, f: np.ndarray) -> Command:
        """u from the law, tau by eq. (11), clipped to the amplifier limits.

        Without valid features (``f`` not finite) the tick holds: u = 0, tau = :meth:`hold_torque`.
        """
        if not finite2(f):
            m = Measurement(
                t=t,
                q=np.asarray(q, float),
                dq=np.asarray(dq, float),
                f=np.asarray(f, float),
                xi=np.full(2, np.nan),
            )
            tau = self.hold_torque(m.dq)
            return Command(m, LawOutput(u=np.zeros(2)), tau, tau, False)
        q, dq, f = _floats(q), _floats(dq), _floats(f)
        xi, tau_ff = model_kernels.prepare(self._p, q, dq, f)
        m = Measurement(t=t, q=q, dq=dq, f=f, xi=xi)
        out = self.law(m)
        u = out.u if type(out.u) is np.ndarray else np.asarray(out.u, dtype=float)
        tau, tau_raw, saturated = model_kernels.torque(tau_ff, u, self.tau_max)  # eq. (11)
        return Command(m, out, tau_raw, tau, saturated)

    def costs(self, cmd: Command) -> tuple[float, float]:
        """(l(x_k, u_k) of eq. 25, V(x_k) of eq. 13) for this tick."""
        m = cmd.measurement
        u = np.asarray(cmd.law.u, dtype=float)
        return model_kernels.costs(self._p, m.q, m.xi, m.f, u)

    def stage_cost(self, cmd: Command) -> float:
        """l(x_k, u_k) of eq. (25) for this tick."""
        return self.costs(cmd)[0]

    def energy(self, cmd: Command) -> float:
        """V(x_k) of eq. (13) for this tick."""
        return self.costs(cmd)[1]

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
        """The daemon's per-tick rule, shared with ``hil replay`` so a log replays exactly.

        A DSP not in *operation enabled* (``drive_mode`` is ``disarmed``, ``fault``,
        ``dsp_restarted`` or ``no_status``, see :mod:`hal.drive_state`): zero torque, the law does
        not run and restarts when the drive is enabled again. No joint state: zero torque. Stale
        features: hold (:meth:`hold_torque`) and re-initialise the law when features return.
        Otherwise the law and eq. (11). Never returns NaN torque.

        ``state_age_s``: how long before ``now_s`` the joint state was sampled; a positive age
        is compensated (:class:`~rt_controller.control.state_predictor.StatePredictor`: the
        nominal model under the torques this method returned meanwhile) before the hold or the
        law sees the state. ``feature_age_s``: how long before ``now_s`` the features were
        captured; a positive age is compensated by seeing the (static) target from the
        predicted pose of now instead of the pose at capture. ``now_s`` is when the tick
        actually runs on the time axis of ``t`` (the release plus the tick's lateness; default
        ``t``); every returned torque is taken as sent then.
        """
        now = t if now_s is None else now_s
        rule = self.rule
        if rule is not None:  # one compiled call; the inputs in one slice assignment
            io = rule.io
            io[dk.IN_T : dk.IN_ENABLED + 1] = (
                t, now, q[0], q[1], dq[0], dq[1], f[0], f[1], state_age_s, feature_age_s,
                f_stale, state_stale, drive_mode == "enabled",
            )  # fmt: skip
            start = time.perf_counter_ns()
            rule.call()
            solve_ns = time.perf_counter_ns() - start
            return Decision.from_outputs(io, drive_mode, t, solve_ns)
        flags, ages = (f_stale, state_stale, drive_mode), (state_age_s, feature_age_s)
        d = self._decide(t, q, dq, f, flags, ages, now)
        self._predictor.sent(now, d.tau)
        if d.command is None:
            return d
        cost, V = self.costs(d.command)
        return Decision(d.tau, d.mode, d.command, d.state, d.features, cost, V)

    def _decide(
        self,
        t: float,
        q: np.ndarray,
        dq: np.ndarray,
        f: np.ndarray,
        flags: tuple[bool, bool, str],
        ages: tuple[float, float],
        now_s: float,
    ) -> Decision:
        f_stale, state_stale, drive_mode = flags
        if drive_mode != "enabled":
            self._holding = True
            return Decision(np.zeros(2), drive_mode, None)
        if state_stale:
            return Decision(np.zeros(2), "no_state", None)
        state_age, feature_age = ages
        usable = not f_stale and finite2(f)
        if state_age > 0 or (usable and feature_age > 0):
            q, dq, f = self._predictor.compensate(
                now_s, q, dq, f, state_age, feature_age if usable else 0.0
            )
        if not usable:
            self._holding = True
            dq = np.asarray(dq, dtype=float)
            return Decision(self.hold_torque(dq), "hold", None, (np.asarray(q, float), dq))
        if self._holding:
            self.law.reset()
            self._holding = False
        cmd = self.step(t, q, dq, f)
        tau = cmd.tau if finite2(cmd.tau) else np.zeros(2)
        m = cmd.measurement
        return Decision(tau, "control", cmd, (m.q, m.dq), m.f)


def warm_up(ctl: Controller, cfg: RigConfig) -> None:
    """Run every branch of the per-tick rule once (law, eq. 11, costs, hold, no state) so that
    nothing is compiled or imported on first use inside a real-time loop, then forget it all.

    The law is exercised at the scenario's initial state; the controller is left as new (law
    re-initialised, not holding).
    """
    sc = cfg.scenario
    q, dq, f = np.array(sc.q0, float), np.array(sc.dq0, float), np.array(sc.f0, float)
    cases = ((False, False, "enabled"), (True, False, "enabled"), (False, True, "enabled"))
    cases += ((False, False, "disarmed"), (False, False, "enabled"))
    for i, (f_stale, state_stale, mode) in enumerate(cases):
        d = ctl.decide(
            0.001 * i,
            q,
            dq,
            f,
            f_stale=f_stale,
            state_stale=state_stale,
            drive_mode=mode,
            state_age_s=0.0005 * i,  # the prediction too
            feature_age_s=0.0007 * i,
        )
        if d.command is not None:
            ctl.costs(d.command)
    ctl.step(0.0, q, dq, np.full(2, np.nan))  # the no-features branch of step
    ctl.reset()
