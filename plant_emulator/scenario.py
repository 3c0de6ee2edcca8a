"""Scenarios: initial pose and target motion. "paper" is the experiment of the paper's Section V."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hal.config import RigConfig
from plant_emulator.camera import camera_pose, unproject


@dataclass(frozen=True)
class TargetMotion:
    """A static target that optionally jumps once (the paper's disturbance)."""

    start: np.ndarray
    jumped: np.ndarray
    jump_time: float | None

    def position(self, t: float) -> np.ndarray:
        """Target position (x_wo, y_wo) in m at time t (s)."""
        if self.jump_time is not None and t >= self.jump_time:
            return self.jumped
        return self.start


def paper_target(cfg: RigConfig) -> TargetMotion:
    """Target placed so that f(0) = scenario.f0; it jumps to where the camera's initial pose
    would see scenario.f_jump, at scenario.jump_time when the disturbance is on."""
    sc = cfg.scenario
    pose0 = camera_pose(cfg.robot, np.array(sc.q0))
    start = unproject(cfg.camera, pose0, np.array(sc.f0))
    jumped = unproject(cfg.camera, pose0, np.array(sc.f_jump))
    return TargetMotion(start, jumped, sc.jump_time if sc.disturbance else None)
