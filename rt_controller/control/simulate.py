"""Offline closed loop: a plant object plus the controller, no transports, faster than real time.

The plant is passed in (the ``hil`` CLI hands over the emulator's
:class:`plant_emulator.world.World`), so this module never imports the emulator.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from hal.config import RigConfig
from rt_controller.control.controller import Controller
from rt_controller.errors import ControllerConfigError
from rt_controller.sample_stats import percentile


class Plant(Protocol):
    """What the closed loop needs from a plant."""

    @property
    def t(self) -> float: ...

    def measure(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def hold(self, tau: np.ndarray, steps: int) -> None: ...


@dataclass
class Trace:
    """Per-tick record of a closed-loop run (arrays with one row per tick)."""

    t: list[float] = field(default_factory=list)
    q: list[np.ndarray] = field(default_factory=list)
    dq: list[np.ndarray] = field(default_factory=list)
    f: list[np.ndarray] = field(default_factory=list)
    xi: list[np.ndarray] = field(default_factory=list)
    u: list[np.ndarray] = field(default_factory=list)
    tau: list[np.ndarray] = field(default_factory=list)
    cost: list[float] = field(default_factory=list)
    V: list[float] = field(default_factory=list)
    residual: list[float] = field(default_factory=list)
    iterations: list[int] = field(default_factory=list)
    fallback: list[bool] = field(default_factory=list)
    solve_ns: list[int] = field(default_factory=list)

    def array(self, name: str) -> np.ndarray:
        return np.asarray(getattr(self, name))


@dataclass
class SimResult:
    law: str
    rate: float
    duration: float
    trace: Trace

    @property
    def J(self) -> float:
        """Eq. (25) integrated over the run: sum over ticks of l(x_k, u_k) / rate."""
        return float(np.sum(self.trace.cost) / self.rate)

    def as_dict(self) -> dict[str, Any]:
        tr = self.trace
        tau = np.abs(tr.array("tau"))
        f_final = tr.f[-1]
        out: dict[str, Any] = {
            "law": self.law,
            "rate": self.rate,
            "duration": self.duration,
            "ticks": len(tr.t),
            "J": self.J,
            "V0": tr.V[0],
            "f_final": [float(v) for v in f_final],
            "f_final_norm": float(np.linalg.norm(f_final)),
            "max_abs_tau": [float(v) for v in tau.max(axis=0)],
            "max_abs_dq": [float(v) for v in np.abs(tr.array("dq")).max(axis=0)],
        }
        if self.law == "rhc":
            res = tr.array("residual")
            solve_us = tr.array("solve_ns") / 1e3
            out.update(
                residual_median=float(np.median(res)),
                residual_max=float(np.max(res)),
                fallbacks=int(np.sum(tr.fallback)),
                solve_us_median=float(np.median(solve_us)),
                solve_us_p99=percentile(solve_us, 99),
            )
        return out


def tick_count(duration: float, rate: float) -> int:
    """Control periods in ``duration`` s at ``rate`` Hz (a partial last period is not run)."""
    return math.floor(duration * rate + 1e-9)


def too_short(duration: float, rate: float) -> str:
    """Why a run of ``duration`` s at ``rate`` Hz is refused: not one control period."""
    return (
        f"--duration {duration:g} s is shorter than one control period ({1 / rate:g} s at "
        f"{rate:g} Hz): no tick would run"
    )


def run_closed_loop(
    plant: Plant,
    controller: Controller,
    cfg: RigConfig,
    duration: float,
    state_delay: int = 0,
    predict: bool = True,
    feature_delay: int = 0,
) -> SimResult:
    """Sample, decide and hold the torque for one control period, ``duration * rate`` times.

    ``state_delay``: the controller sees the joint state (q, dq) of that many periods ago (the
    first one until then) with the current features, what a live loop gets when the DSP's
    sample misses the tick; 0 = none. ``feature_delay``: likewise for the image features (the
    camera, vision and zenoh in between). ``predict``: the controller is told the ages and
    compensates them (the daemon's ``controller.predict_state`` and ``predict_features``);
    false hides them.
    """
    controller.warm_up()  # what the daemon and ``hil replay`` do before their first tick
    rate = cfg.rates.control_hz
    substeps = cfg.rates.substeps
    ticks = tick_count(duration, rate)
    if ticks < 1:
        raise ControllerConfigError(too_short(duration, rate))
    tr = Trace()
    states: collections.deque[tuple[np.ndarray, np.ndarray]] = collections.deque(
        maxlen=state_delay + 1
    )
    features: collections.deque[np.ndarray] = collections.deque(maxlen=feature_delay + 1)
    for _ in range(ticks):
        t = plant.t
        q, dq, f = (np.asarray(v, dtype=float) for v in plant.measure())
        states.append((q, dq))
        features.append(f)
        q, dq = states[0]
        f = features[0]
        age = (len(states) - 1) / rate if predict else 0.0
        f_age = (len(features) - 1) / rate if predict else 0.0
        # The daemon's per-tick rule; in process the features are stale exactly when missing.
        d = controller.decide(
            t,
            q,
            dq,
            f,
            f_stale=not np.all(np.isfinite(f)),
            state_stale=False,
            state_age_s=age,
            feature_age_s=f_age,
        )
        held = d.mode != "control"
        tr.t.append(t)
        tr.q.append(q)
        tr.dq.append(dq)
        tr.f.append(f)
        tr.xi.append(np.full(2, np.nan) if held else d.xi)
        tr.u.append(d.u)
        tr.tau.append(d.tau)
        tr.cost.append(0.0 if held else d.cost)
        tr.V.append(d.V)
        tr.residual.append(d.residual)
        tr.iterations.append(int(d.iterations))
        tr.fallback.append(d.fallback != 0.0)
        tr.solve_ns.append(d.solve_ns)
        plant.hold(d.tau, substeps)
    return SimResult(controller.law, rate, duration, tr)
