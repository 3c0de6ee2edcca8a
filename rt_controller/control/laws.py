"""Control laws for the input u of eq. (11): each maps a measurement to u.

``pbc`` and ``ioc`` are pure functions of the state (eq. 15 and 27). ``rhc`` (eq. 30) carries the
C/GMRES warm start between ticks; it lives in :mod:`rt_controller.control.rhc`. Laws are looked
up by name in :mod:`rt_controller.control.law_table`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hal.config import RigConfig
from rt_controller.control.model import NominalModel


@dataclass(frozen=True)
class Measurement:
    """What a law sees at one tick: time (s) and the state of the visual feedback system."""

    t: float
    q: np.ndarray
    dq: np.ndarray
    f: np.ndarray
    xi: np.ndarray


@dataclass(frozen=True)
class LawOutput:
    """The input u of eq. (11) with the solver's report (zeros for the closed-form laws)."""

    u: np.ndarray
    residual: float = 0.0
    iterations: int = 0
    fallback: bool = False
    solve_ns: int = 0


class ControlLaw(Protocol):
    """A law computes u from a measurement; ``reset`` forgets any warm start."""

    name: str

    def __call__(self, m: Measurement) -> LawOutput: ...

    def reset(self) -> None: ...


def passivity_based(model: NominalModel, xi: np.ndarray) -> np.ndarray:
    """u_p = -R xi, eq. (15)."""
    return -model.R @ xi


def inverse_optimal(model: NominalModel, xi: np.ndarray) -> np.ndarray:
    """u_inv = -2 R xi, eq. (27)."""
    return -2.0 * model.R @ xi


class PassivityBasedLaw:
    """Eq. (15) as a :class:`ControlLaw`."""

    name = "pbc"

    def __init__(self, model: NominalModel, cfg: RigConfig | None = None) -> None:
        self.model = model

    def __call__(self, m: Measurement) -> LawOutput:
        return LawOutput(u=passivity_based(self.model, m.xi))

    def reset(self) -> None:
        """Stateless: nothing to forget."""


class InverseOptimalLaw(PassivityBasedLaw):
    """Eq. (27) as a :class:`ControlLaw`."""

    name = "ioc"

    def __call__(self, m: Measurement) -> LawOutput:
        return LawOutput(u=inverse_optimal(self.model, m.xi))
