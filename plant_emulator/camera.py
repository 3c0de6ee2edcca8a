"""Eye-in-hand pinhole camera (eq. 6) with optional pixel noise, frame rate and latency."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from hal.config import CameraConfig, RobotConfig


@dataclass(frozen=True)
class CameraPose:
    """Camera position (m) in the X_w-Y_w plane and its heading q1 + q2 (rad)."""

    x: float
    y: float
    phi: float


@dataclass(frozen=True)
class FeatureFrame:
    """One image's features as delivered: capture time (s), frame counter, f (px), validity."""

    t_capture: float
    frame: int
    f: np.ndarray
    valid: bool = True


def camera_pose(robot: RobotConfig, q: np.ndarray) -> CameraPose:
    """Forward kinematics of the hand (the camera sits at the tip of link 2)."""
    a12 = q[0] + q[1]
    x = robot.l1 * math.cos(q[0]) + robot.l2 * math.cos(a12)
    y = robot.l1 * math.sin(q[0]) + robot.l2 * math.sin(a12)
    return CameraPose(x, y, a12)


def project(camera: CameraConfig, pose: CameraPose, target: np.ndarray) -> np.ndarray:
    """Ideal perspective projection of a target point in the plane z = z_wo, eq. (6)."""
    dx, dy = target[0] - pose.x, target[1] - pose.y
    c, s = math.cos(pose.phi), math.sin(pose.phi)
    return camera.gain * np.array([c * dx + s * dy, -s * dx + c * dy])


def unproject(camera: CameraConfig, pose: CameraPose, f: np.ndarray) -> np.ndarray:
    """The target point that a camera at ``pose`` sees at features ``f`` (inverse of eq. 6)."""
    c, s = math.cos(pose.phi), math.sin(pose.phi)
    fx, fy = f[0] / camera.gain, f[1] / camera.gain
    return np.array([pose.x + c * fx - s * fy, pose.y + s * fx + c * fy])


class CameraModel:
    """Captures frames on its own clock and delivers them after the configured latency.

    ``frame_rate_hz == 0`` captures on every call of :meth:`capture`: on demand when there is no
    latency, else at every physics step.
    """

    def __init__(self, camera: CameraConfig, seed: int | None = None) -> None:
        self.cfg = camera
        self.period = 1.0 / camera.frame_rate_hz if camera.frame_rate_hz > 0 else 0.0
        self.rng = np.random.default_rng(camera.seed if seed is None else seed)
        self.frame = 0
        self.frame_time = -math.inf
        """Capture time of the newest frame taken."""
        self._next_capture = 0.0
        self._pending: deque[FeatureFrame] = deque()
        self._delivered: FeatureFrame | None = None

    def capture(self, t: float, f_true: np.ndarray) -> None:
        """Offer the true features at time ``t``; a frame is taken when one is due."""
        if t + 1e-12 < self._next_capture:
            return
        f = np.array(f_true, dtype=float)
        if self.cfg.noise_px > 0:
            f = f + self.rng.normal(0.0, self.cfg.noise_px, size=2)
        self._pending.append(FeatureFrame(t, self.frame, f))
        self.frame_time = t
        self.frame += 1
        if self.period > 0:
            self._next_capture += self.period * max(
                1, math.floor((t - self._next_capture) / self.period) + 1
            )
        self._deliver(t)

    @property
    def on_demand(self) -> bool:
        """True when frames are taken only when asked for (no frame clock, no latency)."""
        return self.period == 0.0 and self.cfg.latency_s == 0.0

    def next_capture_time(self) -> float:
        """Time of the next frame on the camera's own clock (0 period: every offer)."""
        return self._next_capture

    def _deliver(self, t: float) -> None:
        while self._pending and self._pending[0].t_capture + self.cfg.latency_s <= t + 1e-12:
            self._delivered = self._pending.popleft()

    def latest(self, t: float) -> FeatureFrame | None:
        """The newest frame delivered by time ``t`` (None before the first one arrives)."""
        self._deliver(t)
        return self._delivered
