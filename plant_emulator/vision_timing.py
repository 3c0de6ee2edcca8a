"""The vision process's timing: its frame rate (:func:`resolve_fps`) and the frame slots
(:class:`FrameClock`). The injected publisher dropouts (``--dropout``) are
:class:`hal.dropout.Dropout`, the image pipeline's too."""

from __future__ import annotations

import math

from hal.config import RigConfig
from hal.dropout import Dropout, in_dropout
from hal.errors import HalConfigError

DEFAULT_FPS = 60.0
"""Frame rate of the vision process when neither ``--fps`` nor ``camera.frame_rate_hz`` set one."""


def resolve_fps(cfg: RigConfig, fps: float | None) -> float:
    """``fps`` if given (0 = every pose), else ``camera.frame_rate_hz`` if set, else 60 Hz."""
    if fps is None:
        return cfg.camera.frame_rate_hz if cfg.camera.frame_rate_hz > 0 else DEFAULT_FPS
    if not math.isfinite(fps) or fps < 0:
        raise HalConfigError(f"--fps must be a non-negative number (0 = every pose), got {fps}")
    return float(fps)


class FrameClock:
    """Frame slots at ``origin + round(k * 1e9 / fps)`` ns; missed slots are skipped, never burst.

    ``origin_ns=None`` starts the clock at the first :meth:`due` call; ``fps == 0`` makes every
    call a frame.
    """

    def __init__(self, fps: float, origin_ns: int | None = None) -> None:
        self.fps = fps
        self._origin0 = origin_ns
        self.reset()

    def reset(self) -> None:
        self.origin_ns = self._origin0
        self.k = 0

    def _slot(self, k: int) -> int:
        return (self.origin_ns or 0) + round(k * 1e9 / self.fps)

    @property
    def next_ns(self) -> int | None:
        """Time of the next frame slot (None when not started or ``fps == 0``)."""
        if self.fps <= 0 or self.origin_ns is None:
            return None
        return self._slot(self.k)

    def due(self, t_ns: int) -> bool:
        """Whether a frame is taken at ``t_ns``; if so the clock moves past ``t_ns``."""
        if self.fps <= 0:
            return True
        if self.origin_ns is None:
            self.origin_ns = t_ns
        if t_ns < self._slot(self.k):
            return False
        k = max(self.k, int((t_ns - self.origin_ns) * self.fps // 1e9))
        while self._slot(k) <= t_ns:
            k += 1
        self.k = k
        return True


__all__ = ["DEFAULT_FPS", "Dropout", "FrameClock", "in_dropout", "resolve_fps"]
