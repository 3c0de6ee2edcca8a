"""The emulated world: arm physics, camera and target on one simulation clock.

Used in-process by ``hil simulate`` and by the emulated DSP and vision processes. The clock is
the integer physics step; time is ``step / physics_hz`` seconds.
"""

from __future__ import annotations

import math

import numpy as np

from hal.config import RigConfig, plant_view
from plant_emulator.arm import ArmPhysics, Encoder
from plant_emulator.camera import CameraModel, CameraPose, FeatureFrame, camera_pose, project
from plant_emulator.scenario import TargetMotion, paper_target


class World:
    """Arm + camera + target. Torque is held between calls of :meth:`hold`.

    Built from the plant's numbers (:func:`hal.config.plant_view`: ``[robot]`` and ``[camera]``
    times the ``[plant]`` factors, the model mismatch), which ``cfg`` then holds."""

    def __init__(self, cfg: RigConfig, *, seed: int | None = None) -> None:
        self.cfg = cfg = plant_view(cfg)
        self.arm = ArmPhysics(cfg.robot)
        self.dt = 1.0 / cfg.rates.physics_hz
        self.target: TargetMotion = paper_target(cfg)
        self.seed = seed
        self.reset()

    def reset(self) -> None:
        """Back to the scenario's initial state."""
        self.step_index = 0
        self.q = np.array(self.cfg.scenario.q0, dtype=float)
        self.dq = np.array(self.cfg.scenario.dq0, dtype=float)
        self.tau_applied = np.zeros(2)
        self.camera = CameraModel(self.cfg.camera, self.seed)
        self.camera.capture(0.0, self.true_features())

    @property
    def t(self) -> float:
        return self.step_index * self.dt

    def pose(self) -> CameraPose:
        return camera_pose(self.cfg.robot, self.q)

    def true_features(self) -> np.ndarray:
        """Noise-free features of the target as the camera sees it now."""
        return project(self.cfg.camera, self.pose(), self.target.position(self.t))

    def step(self, tau: np.ndarray) -> None:
        """Advance one physics step with ``tau`` held (saturated by the amplifier)."""
        self.hold(tau, 1)

    def hold(self, tau: np.ndarray, steps: int, encoder: Encoder | None = None) -> None:
        """Advance ``steps`` physics steps with ``tau`` held, stopping at camera frame times;
        ``encoder`` (the DSP's sensors) is sampled after every step."""
        self.tau_applied = self.arm.saturate(np.asarray(tau, dtype=float))
        end = self.step_index + steps
        while self.step_index < end:
            n = end - self.step_index
            if not self.camera.on_demand:
                due = math.ceil(self.camera.next_capture_time() / self.dt - 1e-9)
                n = min(n, max(1, due - self.step_index))
            if encoder is None:
                self.q, self.dq = self.arm.integrate(self.q, self.dq, self.tau_applied, self.dt, n)
            else:
                self.q, self.dq = self.arm.integrate_encoded(
                    self.q, self.dq, self.tau_applied, self.dt, n, encoder
                )
            self.step_index += n
            if not self.camera.on_demand:
                self.camera.capture(self.t, self.true_features())

    def features(self) -> FeatureFrame | None:
        """Newest camera frame delivered by now (taken now when the camera is on demand)."""
        if self.camera.on_demand and self.camera.frame_time != self.t:
            self.camera.capture(self.t, self.true_features())
        return self.camera.latest(self.t)

    def measure(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, dq, f) as ideal sensors report them now (f from the newest delivered frame)."""
        frame = self.features()
        f = frame.f if frame is not None else np.full(2, np.nan)
        return self.q.copy(), self.dq.copy(), f.copy()
