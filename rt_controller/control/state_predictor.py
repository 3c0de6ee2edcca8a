"""Delay compensation: a joint state and image features measured before the tick, brought up
to the tick.

A live loop does not always read the DSP's sample of this period: a DSP process that ran late
sends it after the controller's release, and the tick then runs on the previous period's state.
With one whole period of delay the paper's IOC and RHC gains are unstable (``hil simulate --law
ioc --state-delay 1 --no-predict``). The controller knows what happened since the sample: its
own nominal model (eq. 1) and the torques it sent. It integrates the one under the other over
the state's age, the way a Smith predictor removes a known dead time, so the law sees the
state of now. Image features are older still (capture, vision, zenoh); the camera's pose at
capture follows from the same trajectory, and a static target seen from there is seen from the
pose of now by eq. (6).
"""

from __future__ import annotations

import collections

import numpy as np

from rt_controller.control import model_kernels

STEP_S = 1e-3
"""Longest Runge-Kutta step of the prediction, s."""


class StatePredictor:
    """Torques sent, by release time, and the motion of the nominal arm under them.

    ``horizon_s`` is the oldest measurement worth compensating (older torques are not kept in
    the history; before the first torque sent, the drive applied none).
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

    def segments(self, start: float, end: float) -> tuple[np.ndarray, np.ndarray]:
        """(torques, durations): what the drive held over [start, end], in order."""
        taus, bounds = [np.zeros(2)], [start]
        for ts, tau in self._sent:
            if ts >= end:
                break
            if ts <= start:
                taus[0] = tau
            else:
                taus.append(tau)
                bounds.append(ts)
        bounds.append(end)
        return np.array(taus), np.diff(np.array(bounds))

    def advance(
        self, q: np.ndarray, dq: np.ndarray, t_from: float, t_to: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) at ``t_to`` of the state (q, dq) at ``t_from``, forwards or backwards in
        time; neither end further than ``horizon_s`` before the other."""
        lo, hi = min(t_from, t_to), max(t_from, t_to)
        taus, durations = self.segments(max(lo, hi - self.horizon_s), hi)
        if t_to < t_from:
            taus, durations = taus[::-1].copy(), -durations[::-1]
        q, dq = np.asarray(q, float), np.asarray(dq, float)
        return model_kernels.predict(self._p, q, dq, taus, durations, STEP_S)

    def predict(
        self, t: float, q: np.ndarray, dq: np.ndarray, age_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) at ``t`` from a state measured ``age_s`` seconds before; as is when the age
        is not positive."""
        if not age_s > 0:
            return q, dq
        return self.advance(q, dq, t - min(age_s, self.horizon_s), t)

    def features(self, f: np.ndarray, q_then: np.ndarray, q_now: np.ndarray) -> np.ndarray:
        """The features ``f`` captured at joint angles ``q_then``, as seen from ``q_now``."""
        return model_kernels.reproject(self._p, np.asarray(q_then, float), q_now, f)
