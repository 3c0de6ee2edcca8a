"""Fakes of the control loop's seams for tests that drive ``ControlLoop`` on a fake clock: the
recorder as the loop uses it, and a joint state at rest as a hardware profile reads it."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hal.hardware_interface import Observation


def at_rest(now_ns: int, *, new: bool = True) -> Observation:
    """The arm at rest at the paper's start pose, f at (-120, -160), enabled, fresh inputs
    (``new`` False: no new joint state since the last read)."""
    return Observation(
        q=np.array([math.pi / 6, -math.pi / 6]),
        dq=np.zeros(2),
        f=np.array([-120.0, -160.0]),
        state_ns=now_ns,
        state_age_ms=0.0,
        state_stale=False,
        f_age_ms=0.0,
        f_stale=False,
        f_valid=True,
        drive_mode="enabled",
        state_new=new,
    )


class ListRecorder:
    """The recorder's seam as the loop uses it, keeping the cycles and parameter records."""

    error = None
    """The log never fails here (the loop ends a lockstep run whose log failed)."""

    def __init__(self) -> None:
        self.cycles: list[dict[str, Any]] = []
        self.parameters: list[dict[str, Any]] = []

    def record_cycle(self, cycle: dict[str, Any]) -> None:
        self.cycles.append(cycle)

    def record_diagnostics(self, diag: dict[str, Any], final: bool = False) -> None:
        pass

    def record_parameters(self, record: dict[str, Any]) -> None:
        self.parameters.append(record)

    def record_event(self, record: dict[str, Any]) -> None:
        pass

    def as_dict(self) -> dict[str, Any]:
        return {}
