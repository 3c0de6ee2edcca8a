"""Offline closed loop: a plant object plus the controller, no transports, faster than real time.

The plant is passed in (the ``hil`` CLI hands over the emulator's
:class:`plant_emulator.world.World`), so this module never imports the emulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from hal.config import RigConfig
from rt_controller.control.controller import Controller


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

    def summary(self) -> dict[str, Any]:
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
        }
        if self.law == "rhc":
            res = tr.array("residual")
            solve_us = tr.array("solve_ns") / 1e3
            out.update(
                residual_median=float(np.median(res)),
                residual_max=float(np.max(res)),
                fallbacks=int(np.sum(tr.fallback)),
                solve_us_median=float(np.median(solve_us)),
                solve_us_p99=float(np.percentile(solve_us, 99)),
            )
        return out


def run_closed_loop(
    plant: Plant, controller: Controller, cfg: RigConfig, duration: float
) -> SimResult:
    """Sample, decide and hold the torque for one control period, ``duration * rate`` times."""
    rate = cfg.rates.control_hz
    substeps = cfg.rates.substeps
    ticks = math.floor(duration * rate + 1e-9)
    tr = Trace()
    for _ in range(ticks):
        q, dq, f = plant.measure()
        cmd = controller.step(plant.t, q, dq, f)
        m, out = cmd.measurement, cmd.law
        tr.t.append(m.t)
        tr.q.append(m.q)
        tr.dq.append(m.dq)
        tr.f.append(m.f)
        tr.xi.append(m.xi)
        tr.u.append(out.u)
        tr.tau.append(cmd.tau)
        held = not np.all(np.isfinite(m.f))
        tr.cost.append(0.0 if held else controller.stage_cost(cmd))
        tr.V.append(np.nan if held else controller.energy(cmd))
        tr.residual.append(out.residual)
        tr.iterations.append(out.iterations)
        tr.fallback.append(out.fallback)
        tr.solve_ns.append(out.solve_ns)
        plant.hold(cmd.tau, substeps)
    return SimResult(controller.law.name, rate, duration, tr)
