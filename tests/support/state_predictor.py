"""Delay compensation spelt out in Python: the oracle's history of the torques sent and the
motion of the nominal arm under them, on the compiled kernels of
:mod:`rt_controller.control.model_kernels` (why the rule compensates: docs/concepts/clock-modes.md).
The compiled rule keeps the same history in its own arrays; :func:`predictor_of` views them.
"""

from __future__ import annotations

import numpy as np

from rt_controller.control import model_kernels
from rt_controller.control.controller import Controller
from rt_controller.control.decide_kernel import CAPACITY, STEP_S, record_sent
from rt_controller.control.state import KS


class StatePredictor:
    """Torques sent, by release time, and the motion of the nominal arm under them.

    ``horizon_s`` is the oldest measurement worth compensating (older torques are dropped from
    the history; before the first torque sent, the drive applied none). The work is done by
    compiled kernels (:mod:`~rt_controller.control.model_kernels`) on the history's arrays.
    """

    def __init__(
        self,
        params: np.ndarray,
        horizon_s: float,
        history: tuple[np.ndarray, np.ndarray, int] | None = None,
    ) -> None:
        """``history``: (times, torques, count) arrays to work on (the compiled per-tick
        rule's, :mod:`~rt_controller.control.decide_kernel`) instead of empty ones."""
        if not horizon_s > 0:
            raise ValueError(f"prediction horizon must be positive, got {horizon_s}")
        self._p = params
        self.horizon_s = float(horizon_s)
        if history is None:
            history = (np.zeros(CAPACITY), np.zeros((CAPACITY, 2)), 0)
        self._times, self._taus, n = history
        self._ks = np.zeros(KS.SIZE)  # the compiled rule's count of torques held, KS.N
        self._ks[KS.N] = n

    def __len__(self) -> int:
        """Torques held in the history."""
        return int(self._ks[KS.N])

    def retarget(self, params: np.ndarray, horizon_s: float) -> None:
        """Predict with new model parameters and horizon from now on (the torques sent so far
        are kept)."""
        self._p = params
        self.horizon_s = float(horizon_s)

    def reset(self) -> None:
        """Forget the torques sent (a new run)."""
        self._ks[KS.N] = 0.0

    def sent(self, t: float, tau: np.ndarray) -> None:
        """Record that ``tau`` was sent at tick time ``t`` (held until the next one), as the
        compiled rule records it (:func:`~rt_controller.control.decide_kernel.record_sent`)."""
        record_sent(self._times, self._taus, self._ks, t, tau[0], tau[1], self.horizon_s)

    def segments(self, start: float, end: float) -> tuple[np.ndarray, np.ndarray]:
        """(torques, durations): what the drive held over [start, end], in order."""
        return model_kernels.held_torques(self._times, self._taus, len(self), start, end)

    def advance(
        self, q: np.ndarray, dq: np.ndarray, t_from: float, t_to: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) at ``t_to`` of the state (q, dq) at ``t_from``, forwards or backwards in
        time; neither end further than ``horizon_s`` before the other."""
        q, dq = np.asarray(q, float), np.asarray(dq, float)
        return model_kernels.advance(
            self._p, q, dq, self._times, self._taus, len(self), t_from, t_to, self.horizon_s, STEP_S
        )

    def predict(
        self, t: float, q: np.ndarray, dq: np.ndarray, age_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) at ``t`` from a state measured ``age_s`` seconds before; as is when the age
        is not positive."""
        if not age_s > 0:
            return q, dq
        return self.advance(q, dq, t - min(age_s, self.horizon_s), t)

    def compensate(
        self,
        now: float,
        q: np.ndarray,
        dq: np.ndarray,
        f: np.ndarray,
        state_age_s: float,
        feature_age_s: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, dq, f) at ``now`` of a state measured ``state_age_s`` and features captured
        ``feature_age_s`` before it (0 or less: as measured), in one compiled call."""
        q, dq, f = (np.asarray(v, float) for v in (q, dq, f))
        return model_kernels.compensate(
            self._p,
            q,
            dq,
            f,
            self._times,
            self._taus,
            len(self),
            now,
            state_age_s,
            feature_age_s,
            self.horizon_s,
            STEP_S,
        )


def predictor_of(ctl: Controller) -> StatePredictor:
    """The torques ``ctl`` sent and the motion of the nominal arm under them: a view of its
    compiled rule's history as of now."""
    r = ctl.rule
    return StatePredictor(r.p, r.horizon_s, history=(r.hist_t, r.hist_tau, len(r)))
