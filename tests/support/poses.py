"""Camera poses as the emulator publishes them to the vision process, for its tests."""

from __future__ import annotations

from typing import Any

import numpy as np

from hal.config import RigConfig
from hal.vision_codec import PoseMsg
from plant_emulator.camera import CameraPose, camera_pose

MS = 1_000_000
PERIOD = 20 * MS
"""The paper's 50 Hz control period, ns."""


def q0_pose(cfg: RigConfig) -> CameraPose:
    """The camera pose at the scenario's initial joint angles."""
    return camera_pose(cfg.robot, np.array(cfg.scenario.q0))


def pose_msg(
    cfg: RigConfig,
    seq: int,
    sim_ns: int,
    *,
    lockstep: bool,
    q: Any = None,
    source: int = 1,
    seed: int | None = None,
) -> PoseMsg:
    """Pose message ``seq`` at simulation time ``sim_ns`` (joint angles ``q``, default q0)."""
    p = q0_pose(cfg) if q is None else camera_pose(cfg.robot, np.array(q))
    return PoseMsg(seq, sim_ns, 0, p.x, p.y, p.phi, lockstep, source, seed)


def camera_cfg(cfg: RigConfig, **kw: Any) -> RigConfig:
    """``cfg`` with these ``camera.*`` keys overridden."""
    return cfg.with_overrides({f"camera.{k}": v for k, v in kw.items()})
