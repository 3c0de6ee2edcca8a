"""One frame in, the paper's features out: check the frame, detect the target, undistort,
convert to f. Frames that give no measurement are counted by reason, never raised."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from vision.detector import REASONS, Detection, DetectorParams, detect
from vision.intrinsics import Intrinsics


@dataclass(frozen=True)
class Measurement:
    """What one frame gave: f (px, the paper's axes) or the reason there is none, the detection
    in the distorted image (for the overlay) and the processing time."""

    f: tuple[float, float] | None
    reason: str | None
    detection: Detection | None
    detect_ns: int

    @property
    def valid(self) -> bool:
        return self.f is not None


@dataclass
class PipelineCounts:
    """Frames processed, measurements made, and frames without one by reason."""

    frames: int = 0
    measured: int = 0
    rejected: Counter[str] = field(default_factory=Counter)

    def as_dict(self) -> dict[str, object]:
        return {
            "frames": self.frames,
            "measured": self.measured,
            "rejected": {r: self.rejected.get(r, 0) for r in REASONS},
        }


class Pipeline:
    """The image processing of the vision process, for frames of ``intrinsics``' size."""

    def __init__(self, intrinsics: Intrinsics, params: DetectorParams | None = None) -> None:
        self.intrinsics = intrinsics
        self.params = params or DetectorParams()
        self.counts = PipelineCounts()

    def reject(self, reason: str) -> Measurement:
        """Count a frame that gave no measurement (also for frames that never decoded)."""
        self.counts.frames += 1
        self.counts.rejected[reason] += 1
        return Measurement(None, reason, None, 0)

    def process(self, pixels: np.ndarray) -> Measurement:
        """Measure f in one 8-bit grey frame (height x width)."""
        t0 = time.perf_counter_ns()
        k = self.intrinsics
        if not isinstance(pixels, np.ndarray) or pixels.dtype != np.uint8 or pixels.ndim != 2:
            return self.reject("malformed")
        if pixels.shape != (k.height, k.width):
            return self.reject("wrong_size")
        det, reason = detect(pixels, self.params)
        if det is None:
            return self.reject(reason or "not_found")
        f = k.features((det.u, det.v))
        self.counts.frames += 1
        self.counts.measured += 1
        return Measurement(f, None, det, time.perf_counter_ns() - t0)
