"""One control step: measurement -> law -> torque (eq. 11), independent of any I/O.

:meth:`Controller.decide` is the per-tick rule of the daemon, replay and simulation: one
compiled call (:mod:`~rt_controller.control.decide_kernel`) for the configured law. The same
rule spelt out in Python on the law objects is a test oracle (``tests/support/python_rule.py``)
that the compiled call is held to; the product has this one implementation.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from hal.config import LAW_NAMES, RigConfig
from rt_controller.control import decide_kernel as dk
from rt_controller.control.model import NominalModel
from rt_controller.control.rhc.solver import CGMRESSolver
from rt_controller.control.state import IO, MODE_NAMES, OUTPUTS, pack_params
from rt_controller.errors import ControllerConfigError

_RECORD = tuple(
    ("law" if f.record == "law" else f.name, IO.offset(f.name), f.record)
    for f in OUTPUTS
    if f.record
)
"""(record name, io offset, JSON type) of each output the cycle record holds, in order."""
_OUTPUT = {f.name: (IO.offset(f.name), f.size) for f in OUTPUTS}


class Decision:
    """One tick of the per-tick rule: the torque to send and how it was obtained.

    Made from the outputs of the compiled rule's io vector (:data:`~rt_controller.control.
    state.IO`), copied. Every output is an attribute by its declared name (``d.xi``,
    ``d.residual``, ``d.cost``: a 2-vector as an array, a number as a float); only the torque
    pair and the mode are made at once (the write needs them), the rest when read: the loop
    reads only the record's numbers (:meth:`record_fields`).
    """

    __slots__ = ("_out", "_solve_ns", "_tau", "mode", "torque")

    def __init__(self, io: np.ndarray, drive_mode: str, solve_ns: int) -> None:
        """``io``: the rule's io vector after the call; ``drive_mode`` names the mode when the
        drive was not enabled; ``solve_ns`` the call's duration."""
        v = io.tolist()
        self._out = v
        self._solve_ns = solve_ns
        self._tau: np.ndarray | None = None
        self.torque = (v[IO.TAU], v[IO.TAU + 1])
        """The torque to send, as the pair of floats the write takes."""
        mode = int(v[IO.MODE])
        self.mode = MODE_NAMES[mode] if mode < len(MODE_NAMES) else drive_mode
        """``control`` (the law ran), ``hold`` (stale features: joint damper), ``no_state``, or
        the drive's mode when it is not enabled (``disarmed``, ``fault``, ...)."""

    def __getattr__(self, name: str) -> Any:
        """An output of the rule by its declared name (:data:`~rt_controller.control.state.
        OUTPUTS`): a float, or an array for a vector."""
        try:
            k, size = _OUTPUT[name]
        except KeyError:
            raise AttributeError(name) from None
        return self._out[k] if size == 1 else np.array(self._out[k : k + size])

    @property
    def tau(self) -> np.ndarray:
        """The torque to send (2,), as an array (:attr:`torque` is the same pair of floats)."""
        if self._tau is None:
            self._tau = np.array(self.torque)
        return self._tau

    @property
    def solve_ns(self) -> int:
        """The compiled rule's own time, ns; 0 when no law ran."""
        return self._solve_ns if self.mode == "control" else 0

    def record_fields(self, law_name: str) -> dict[str, Any]:
        """The cycle record's decision fields, as declared (:data:`~rt_controller.control.
        state.OUTPUTS`; see :func:`rt_controller.runtime.cycle_record.decision_fields`); the
        rule leaves NaN in what it did not act on, recorded as null whatever the type."""
        v, out = self._out, {}
        for name, k, kind in _RECORD:
            if kind == "vector":
                out[name] = v[k : k + 2]
            elif kind == "boolean":
                out[name] = None if v[k] != v[k] else v[k] != 0.0  # NaN: not acted on, null
            elif kind == "integer":
                out[name] = None if v[k] != v[k] else int(v[k])
            elif kind == "law":
                out[name] = law_name if self.mode == "control" else self.mode
            else:
                out[name] = v[k]
        return out


class Controller:
    """The per-tick rule of the configured law around its compiled call (:meth:`decide`); the
    caller owns clocks and transports."""

    def __init__(self, cfg: RigConfig, law: str | None = None) -> None:
        self.cfg = cfg
        self.model = NominalModel.from_config(cfg)
        self._p = pack_params(self.model)
        self.law = cfg.controller.law if law is None else law
        """The law's name (one of :data:`hal.config.LAW_NAMES`)."""
        self.rule = dk.CompiledRule(cfg, self.law, self._p, self._solver())
        """The compiled per-tick rule: its arrays and the call."""

    def _solver(self) -> CGMRESSolver | None:
        """The C/GMRES solver whose arrays the compiled rule advances (rhc), else None."""
        if self.law not in dk.LAW_CODES:
            raise ControllerConfigError(
                f"unknown law {self.law!r} (choose from {', '.join(LAW_NAMES)})"
            )
        return CGMRESSolver(self.model, self.cfg) if self.law == "rhc" else None

    def reconfigure(self, cfg: RigConfig, *, law_changed: bool = True) -> None:
        """Run from now on with ``cfg``, which differs from the current configuration only in
        online-tunable keys (:data:`rt_controller.calibration.parameters.TUNABLE`); called between
        two ticks, by the loop and by ``hil replay`` at the same tick.

        The model's gains and the law are rebuilt when ``law_changed`` (a new law starts as at
        the run's start: C/GMRES solves its first tick from scratch, and falls back to eq. 27
        when that solve diverges); the torque history is kept."""
        self.cfg = cfg
        if law_changed:
            self.model = NominalModel.from_config(cfg)
            self._p = pack_params(self.model)
            self.law = cfg.controller.law
            self.rule.retarget(cfg, self.law, self._p, self._solver())
        self.rule.limits(cfg)

    def reset(self) -> None:
        """As new: the law starts again, no torque sent, not holding."""
        self.rule.reset()

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
        """The per-tick rule of the daemon, ``hil replay`` and ``hil simulate`` (so a log
        replays exactly): one compiled call (:func:`~rt_controller.control.decide_kernel.
        decide_tick`).

        A DSP not in *operation enabled* (``drive_mode`` is ``disarmed``, ``fault``,
        ``dsp_restarted`` or ``no_status``, see :mod:`hal.drive_state`): zero torque, the law does
        not run and restarts when the drive is enabled again. No joint state: zero torque. Stale
        features: hold (tau = -2 R dq, clipped) and re-initialise the law when features return.
        Otherwise the law and eq. (11). Never returns NaN torque.

        ``state_age_s``: how long before ``now_s`` the joint state was sampled; a positive age
        is compensated (:func:`~rt_controller.control.model_kernels.compensate`: the
        nominal model under the torques this method returned meanwhile) before the hold or the
        law sees the state. ``feature_age_s``: how long before ``now_s`` the features were
        captured; a positive age is compensated by seeing the (static) target from the
        predicted pose of now instead of the pose at capture. ``now_s`` is when the tick
        actually runs on the time axis of ``t`` (the release plus the tick's lateness; default
        ``t``); every returned torque is taken as sent then.
        """
        now = t if now_s is None else now_s
        rule = self.rule
        io = rule.io  # the inputs in one slice assignment
        io[: IO.OUTPUTS] = (
            t, now, q[0], q[1], dq[0], dq[1], f[0], f[1], state_age_s, feature_age_s,
            f_stale, state_stale, drive_mode == "enabled",
        )  # fmt: skip
        start = time.perf_counter_ns()
        rule.call()
        solve_ns = time.perf_counter_ns() - start
        return Decision(io, drive_mode, solve_ns)

    def warm_up(self) -> None:
        """Run every branch of the per-tick rule once (law, eq. 11, costs, hold, no state, a
        drive not enabled, the delay compensation) so that nothing is compiled or imported on
        first use inside a real-time loop, then forget it all: the one warm-up of the daemon,
        ``hil replay`` and ``hil simulate``.

        The law is exercised at the scenario's initial state; the controller is left as new (law
        re-initialised, no torque sent, not holding).
        """
        sc = self.cfg.scenario
        q, dq, f = np.array(sc.q0, float), np.array(sc.dq0, float), np.array(sc.f0, float)
        cases = ((False, False, "enabled"), (True, False, "enabled"), (False, True, "enabled"))
        cases += ((False, False, "disarmed"), (False, False, "enabled"))
        for i, (f_stale, state_stale, mode) in enumerate(cases):
            d = self.decide(
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
            d.record_fields(self.law)
        self.reset()
