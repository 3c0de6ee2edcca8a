"""Delay compensation: a joint state sampled before the tick, brought up to the tick.

A live loop does not always read the DSP's sample of this period: a DSP process that ran late
sends it after the controller's release, and the tick then runs on the previous period's state.
With one whole period of delay the paper's IOC and RHC gains are unstable (``hil simulate --law
ioc --state-delay 1 --no-predict``). The controller knows what happened since the sample: its
own nominal model (eq. 1) and the torques it sent. It integrates the one under the other over
the state's age, the way a Smith predictor removes a known dead time, so the law sees the
state of now.
"""

from __future__ import annotations

import collections

import numpy as np

from rt_controller.control import model_kernels

STEP_S = 1e-3
"""Longest Runge-Kutta step of the prediction, s."""


class StatePredictor:
    """Torques sent, by release time, and the prediction of a state over its age.

    ``horizon_s`` is the oldest state worth predicting (older ones are not kept in the torque
    history; before the first torque sent, the drive applied none).
    """

    def __init__(self, params: np.ndarray, horizon_s: float) -> None:
        if not horizon_s > 0:
            raise ValueError(f"prediction horizon must be positive, got {horizon_s}")
        self._p = params
        self.horizon_s = float(horizon_s)
        self._sent: collections.deque[tuple[float, np.ndarray]] = collections.deque()

    def reset(self) -> None:
        """Forget the torques sent (a new run)."""
        self._sent.clear()

    def sent(self, t: float, tau: np.ndarray) -> None:
        """Record that ``tau`` was sent at tick time ``t`` (held until the next one)."""
        self._sent.append((float(t), np.array(tau, dtype=float)))
        while len(self._sent) > 1 and self._sent[1][0] <= t - self.horizon_s:
            self._sent.popleft()

    def segments(self, t: float, age_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(torques, durations): what the drive held over [t - age_s, t], in order."""
        start = t - min(age_s, self.horizon_s)
        taus, bounds = [np.zeros(2)], [start]
        for ts, tau in self._sent:
            if ts >= t:
                break
            if ts <= start:
                taus[0] = tau
            else:
                taus.append(tau)
                bounds.append(ts)
        bounds.append(t)
        return np.array(taus), np.diff(np.array(bounds))

    def predict(
        self, t: float, q: np.ndarray, dq: np.ndarray, age_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) at ``t`` from a state measured ``age_s`` seconds before; as is when the age
        is not positive."""
        if not age_s > 0:
            return q, dq
        taus, durations = self.segments(t, age_s)
        return model_kernels.predict(
            self._p, np.asarray(q, float), np.asarray(dq, float), taus, durations, STEP_S
        )
