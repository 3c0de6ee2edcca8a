"""One frame in, the paper's features out: check the frame, detect the target, undistort,
convert to f. Frames that give no measurement are counted by reason, never raised.

Tracking window (standard in visual servoing): the detector looks first in a window around where
the target is expected, the last detection moved on by the motion between the last two
(constant image velocity), and in the whole frame when it is not there whole. The window is a
hint, never a result: on the rig's plain plane the window's f is the whole frame's to the bit;
on a textured plane its threshold can take another edge pixel. It cuts the detection's time
by about a third (``hil bench vision``: ``detect_us`` against ``detect_tracked_us``;
docs/benchmarks.md, "Design choices, measured").

Region of interest: the window (with the detector's sub-pixel margin) is also what the grabber
asks the camera to send of the next frame (:meth:`Pipeline.roi`). A region whose window holds
the target gives the measurement the whole frame would (the same pixels, the same window
search); otherwise (:meth:`Pipeline.process_region` returns None) the whole frame is needed
and the tracker is left as it was, so the whole frame's measurement is today's.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from vision.detector import REASONS, Detection, DetectorParams, Window, detect
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


REJECTED = (*REASONS, "bad_mac")
"""The reasons counted in ``rejected``: the detector's, and ``bad_mac`` (a camera frame whose MAC
does not verify: signed with another rig key)."""


@dataclass
class PipelineCounts:
    """Frames processed, measurements made, and frames without one by reason."""

    frames: int = 0
    measured: int = 0
    tracked: int = 0
    """Measurements found in the tracking window (the others searched the whole frame)."""
    rejected: Counter[str] = field(default_factory=Counter)

    def as_dict(self) -> dict[str, object]:
        return {
            "frames": self.frames,
            "measured": self.measured,
            "tracked": self.tracked,
            "rejected": {r: self.rejected.get(r, 0) for r in REJECTED},
        }


WINDOW_PAD_DIAMETERS = 1.0
"""The tracking window reaches this many target diameters beyond the expected disc..."""
WINDOW_PAD_MIN_PX = 16.0
"""...and at least this far (px): room for the image motion the prediction misses."""


class Tracker:
    """Where the next frame's target is expected: the window around the last detection moved on
    by the last frame-to-frame motion found in the window; no window before a detection or
    after a frame without one (the whole frame is searched)."""

    def __init__(self) -> None:
        self._last: Detection | None = None
        self._velocity = (0.0, 0.0)

    def window(self) -> Window | None:
        d = self._last
        if d is None:
            return None
        u, v = d.u + self._velocity[0], d.v + self._velocity[1]
        diameter = 2.0 * math.sqrt(d.area / math.pi)
        reach = diameter / 2 + max(WINDOW_PAD_DIAMETERS * diameter, WINDOW_PAD_MIN_PX)
        return (
            math.floor(u - reach),
            math.floor(v - reach),
            math.ceil(u + reach) + 1,
            math.ceil(v + reach) + 1,
        )

    def update(self, d: Detection | None, tracked: bool) -> None:
        """The frame's detection (None: none) and whether the window found it: a target found
        only in the whole frame jumped (or was lost), its motion is no velocity."""
        last = self._last
        moving = tracked and d is not None and last is not None
        self._velocity = (d.u - last.u, d.v - last.v) if moving else (0.0, 0.0)  # type: ignore[union-attr]
        self._last = d


class Pipeline:
    """The image processing of the vision process, for frames of ``intrinsics``' size
    (``track``: search a tracking window first, see the module docstring)."""

    def __init__(
        self,
        intrinsics: Intrinsics,
        params: DetectorParams | None = None,
        *,
        track: bool = True,
        notice: Callable[[str], None] | None = None,
    ) -> None:
        self.intrinsics = intrinsics
        self.params = params or DetectorParams()
        self.counts = PipelineCounts()
        self.tracker = Tracker() if track else None
        self.notice = notice
        """Told once, at the first frame of another size than the camera's (a real camera or
        clip of another resolution: every frame would be rejected)."""
        self.wrong_size: tuple[int, int] | None = None
        """(width, height) of the first frame of another size than the camera's."""

    def reject(self, reason: str, detect_ns: int = 0) -> Measurement:
        """Count a frame that gave no measurement (also for frames that never decoded);
        ``detect_ns``: the time of a detection that found nothing (0: none ran)."""
        self.counts.frames += 1
        self.counts.rejected[reason] += 1
        return Measurement(None, reason, None, detect_ns)

    def process(self, pixels: np.ndarray) -> Measurement:
        """Measure f in one 8-bit grey frame (height x width)."""
        t0 = time.perf_counter_ns()
        k = self.intrinsics
        if not isinstance(pixels, np.ndarray) or pixels.dtype != np.uint8 or pixels.ndim != 2:
            return self.reject("malformed")
        if pixels.shape != (k.height, k.width):
            if self.wrong_size is None:
                self.wrong_size = (w, h) = (pixels.shape[1], pixels.shape[0])
                if self.notice is not None:
                    self.notice(
                        f"frames are {w}x{h}, camera.width_px x height_px {k.width}x{k.height}: "
                        "every such frame is rejected (wrong_size); set [camera] width_px, "
                        "height_px to the camera's (and calibrate it)"
                    )
            return self.reject("wrong_size")
        window = self.tracker.window() if self.tracker is not None else None
        det, reason = detect(pixels, self.params, window) if window else (None, None)
        tracked = det is not None
        if det is None:
            det, reason = detect(pixels, self.params)
        if self.tracker is not None:
            self.tracker.update(det, tracked)
        if det is None:
            return self.reject(reason or "not_found", max(time.perf_counter_ns() - t0, 1))
        return self._measured(det, tracked, t0)

    def process_region(self, pixels: np.ndarray, x0: int, y0: int) -> Measurement | None:
        """Measure f in a region of interest (the frame's pixels at ``(x0, y0)``): the
        measurement the whole frame would give, or None when only the whole frame can tell
        (no tracking window, or the target not whole in it; nothing is counted)."""
        t0 = time.perf_counter_ns()
        k = self.intrinsics
        window = self.tracker.window() if self.tracker is not None else None
        if window is None or not isinstance(pixels, np.ndarray) or pixels.dtype != np.uint8:
            return None
        if pixels.ndim != 2:
            return None
        det, _ = detect(pixels, self.params, window, region=(x0, y0, k.width, k.height))
        if det is None:
            return None
        self.tracker.update(det, True)  # type: ignore[union-attr]
        return self._measured(det, True, t0)

    def roi(self) -> tuple[int, int, int, int] | None:
        """The region of the next frame :meth:`process_region` needs, ``(x0, y0, x1, y1)``
        inside the frame: the tracking window and the sub-pixel margin; None: the whole
        frame."""
        window = self.tracker.window() if self.tracker is not None else None
        if window is None:
            return None
        k, m = self.intrinsics, self.params.margin
        x0, y0 = max(window[0] - m, 0), max(window[1] - m, 0)
        x1, y1 = min(window[2] + m, k.width), min(window[3] + m, k.height)
        if x1 - x0 < 8 or y1 - y0 < 8:
            return None
        return (x0, y0, x1, y1)

    def _measured(self, det: Detection, tracked: bool, t0: int) -> Measurement:
        f = self.intrinsics.features((det.u, det.v))
        self.counts.frames += 1
        self.counts.measured += 1
        self.counts.tracked += tracked
        return Measurement(f, None, det, time.perf_counter_ns() - t0)
