"""One control step: measurement -> law -> torque (eq. 11), independent of any I/O."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hal.config import RigConfig
from rt_controller.control import model_kernels
from rt_controller.control.law_table import make_law
from rt_controller.control.laws import ControlLaw, LawOutput, Measurement
from rt_controller.control.model import NominalModel
from rt_controller.control.state_predictor import StatePredictor

_isfinite = math.isfinite


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


@dataclass(frozen=True)
class Decision:
    """One tick of the daemon: the torque to send and how it was obtained."""

    tau: np.ndarray
    mode: str
    """``control`` (the law ran), ``hold`` (stale features: joint damper) or ``no_state``."""
    command: Command | None
    """The law's step when ``mode == "control"``."""
    state: tuple[np.ndarray, np.ndarray] | None = None
    """(q, dq) the hold or the law acted on: the joint state brought up to the tick (as
    measured when its age was not given); ``None`` when neither ran."""
    features: np.ndarray | None = None
    """f the law acted on: the features brought up to the tick (as measured when their age was
    not given); ``None`` when the law did not run."""


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
        self.predictor = StatePredictor(self._p, max(c.state_timeout_s, c.feature_timeout_s))

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
        self.predictor.retarget(self._p, max(c.state_timeout_s, c.feature_timeout_s))

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
        ages = (state_age_s, feature_age_s)
        d = self._decide(t, q, dq, f, f_stale, state_stale, drive_mode, ages, now)
        self.predictor.sent(now, d.tau)
        return d

    def _decide(
        self,
        t: float,
        q: np.ndarray,
        dq: np.ndarray,
        f: np.ndarray,
        f_stale: bool,
        state_stale: bool,
        drive_mode: str,
        ages: tuple[float, float],
        now_s: float,
    ) -> Decision:
        if drive_mode != "enabled":
            self._holding = True
            return Decision(np.zeros(2), drive_mode, None)
        if state_stale:
            return Decision(np.zeros(2), "no_state", None)
        state_age, feature_age = ages
        usable = not f_stale and finite2(f)
        if state_age > 0 or (usable and feature_age > 0):
            q, dq, f = self.predictor.compensate(
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
    ctl.law.reset()
    ctl.predictor.reset()
    ctl._holding = False
