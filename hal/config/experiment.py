"""The experiment's sections: ``[scenario]`` (initial pose, target, the target jump) and
``[rates]`` (control, physics, state and status rates)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from hal.config.values import Vec2


@dataclass(frozen=True)
class ScenarioConfig:
    """Initial pose, target placement and the target jump ("paper": the paper's Section V)."""

    name: str = "paper"
    q0: Vec2 = (math.pi / 6, -math.pi / 6)
    dq0: Vec2 = (0.0, 0.0)
    f0: Vec2 = (-120.0, -160.0)
    """Features at t = 0 (px); the target is placed so that the camera sees this."""
    disturbance: bool = True
    """Whether the target jumps at ``jump_time``."""
    jump_time: float = 3.0
    f_jump: Vec2 = (-50.0, -64.0)
    """Features the jumped target would have, seen from the camera's initial pose (px)."""


@dataclass(frozen=True)
class RatesConfig:
    """Loop rates in Hz."""

    control_hz: float = 50.0
    physics_hz: float = 1000.0
    state_hz: float = 1000.0
    """Rate of the camera poses the emulator publishes for vision, and of the DSP's joint-state
    frames with ``dsp.state_sync = free`` (``command``, the default, sends one state per control
    period, in step with the controller)."""
    status_hz: float = 10.0
    """Rate of the DSP's status frames."""

    @property
    def control_period_ns(self) -> int:
        return round(1e9 / self.control_hz)

    @property
    def substeps(self) -> int:
        """Physics steps per control period."""
        return round(self.physics_hz / self.control_hz)
