"""The camera's recent poses (from the emulator's world) with their capture stamps: a frame's
exposure is rendered from the poses interpolated over it."""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

from plant_emulator.camera import CameraPose


@dataclass(frozen=True)
class PoseSample:
    seq: int
    sim_ns: int
    stamp_ns: int
    pose: CameraPose


class PoseHistory:
    """Recent camera poses of one run; :meth:`pose_at` interpolates linearly in sim time."""

    def __init__(self, keep_ns: int) -> None:
        self.keep_ns = keep_ns
        self.samples: list[PoseSample] = []
        self._times: list[int] = []

    def add(self, s: PoseSample) -> None:
        if self.samples and s.sim_ns <= self._times[-1]:
            self.samples[-1] = s  # a holding world re-publishes time 0: keep the newest pose
            self._times[-1] = s.sim_ns
        else:
            self.samples.append(s)
            self._times.append(s.sim_ns)
        old = bisect.bisect_left(self._times, s.sim_ns - self.keep_ns) - 1
        if old > 0:
            del self.samples[:old], self._times[:old]

    def clear(self) -> None:
        self.samples.clear()
        self._times.clear()

    @property
    def newest(self) -> PoseSample | None:
        return self.samples[-1] if self.samples else None

    def _bracket(self, t_ns: float) -> tuple[PoseSample, PoseSample, float]:
        s = self.samples
        i = bisect.bisect_left(self._times, t_ns)
        if i == 0:
            return s[0], s[0], 0.0
        if i == len(s):
            return s[-1], s[-1], 0.0
        a, b = s[i - 1], s[i]
        return a, b, (t_ns - a.sim_ns) / (b.sim_ns - a.sim_ns)

    def pose_at(self, t_s: float) -> CameraPose:
        a, b, w = self._bracket(t_s * 1e9)
        pa, pb = a.pose, b.pose
        dphi = math.remainder(pb.phi - pa.phi, 2 * math.pi)
        return CameraPose(pa.x + w * (pb.x - pa.x), pa.y + w * (pb.y - pa.y), pa.phi + w * dphi)

    def stamp_at(self, t_s: float) -> int:
        """The monotonic time at sim time ``t_s`` (interpolated between the poses' stamps)."""
        a, b, w = self._bracket(t_s * 1e9)
        return round(a.stamp_ns + w * (b.stamp_ns - a.stamp_ns))
