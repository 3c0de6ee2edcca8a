"""Wire format of the vision process's decimated image stream: what the camera saw, for the log
and live views (``hil/vision/image``, ``camera.image_log_fps`` frames per second).

Vision image v1, little-endian (``<2sBBIQqqBxxxxxxxdddd``), then the encoded image, then the MAC::

    off size type  field
      0    2 bytes magic        b"HV"
      2    1 u8    version      1
      3    1 u8    flags        bit0 valid (the pipeline measured f); others 0
      4    4 u32   source       random id of the publishing vision process
      8    8 u64   frame        the camera's frame counter
     16    8 i64   stamp_ns     capture stamp (CLOCK_MONOTONIC, middle of the exposure)
     24    8 i64   sim_time_ns  emulator time at capture
     32    1 u8    reason       0 valid, else 1 + index in ``REASONS`` (why there is no f)
     33    7       reserved     zero
     40    8 f64   u            detected centre in the (distorted) image, px (0 if not valid)
     48    8 f64   v
     56    8 f64   fx           the features f published, px (0 if not valid)
     64    8 f64   fy
     72    n bytes image        PNG (lossless: a log's frames re-run the pipeline exactly)
    end   16 bytes mac          HMAC-SHA256 of everything before, truncated to 128 bits, rig key
                                derived for "hil/zenoh/vision_image" (hal/secoc.py)

Why a stream of its own and not the frames: a raw frame is 300 kB at up to 60 fps; the log and
Foxglove need a few compressed frames a second with what the detector made of each.
"""

from __future__ import annotations

import functools
import math
import struct
from typing import NamedTuple

from hal.errors import HalCodecError
from hal.secoc import VISION_MAC_BYTES, Mac, derive, rig_key

MAGIC = b"HV"
VERSION = 1
LABEL = "hil/zenoh/vision_image"
FLAG_VALID = 0x01
REASONS = ("not_found", "out_of_view", "blurred", "malformed", "wrong_size", "dropout")
"""The reasons a frame gave no f (``vision.detector.REASONS`` and the grabber's dropout)."""
_HEADER = struct.Struct("<2sBBIQqqB7xdddd")
HEADER_SIZE = _HEADER.size
MAC_SIZE = VISION_MAC_BYTES


class VisionImage(NamedTuple):
    """One decimated frame with its detection (see the module docstring)."""

    frame: int
    stamp_ns: int
    sim_time_ns: int
    valid: bool
    reason: str | None
    uv: tuple[float, float]
    f: tuple[float, float]
    png: bytes
    source: int = 0


@functools.lru_cache(maxsize=8)
def _mac(key: bytes) -> Mac:
    return Mac(derive(key, LABEL), MAC_SIZE)


def encode_vision_image(msg: VisionImage, key: bytes | None = None) -> bytes:
    """Pack ``msg`` (authenticated with the rig ``key``, default this process's)."""
    if not all(math.isfinite(x) for x in (*msg.uv, *msg.f)):
        raise HalCodecError(f"vision image: u, v, f must be finite, got {msg.uv} {msg.f}")
    if msg.reason is not None and msg.reason not in REASONS:
        raise HalCodecError(f"vision image: unknown reason {msg.reason!r}")
    code = 0 if msg.reason is None else 1 + REASONS.index(msg.reason)
    try:
        head = _HEADER.pack(
            MAGIC, VERSION, FLAG_VALID if msg.valid else 0, msg.source, msg.frame,
            msg.stamp_ns, msg.sim_time_ns, code, *msg.uv, *msg.f,
        )  # fmt: skip
    except struct.error as exc:
        raise HalCodecError(f"vision image: field out of range: {exc}") from exc
    body = head + bytes(msg.png)
    return body + _mac(rig_key() if key is None else key).tag(body)


def decode_vision_image(buf: bytes, key: bytes | None = None) -> VisionImage:
    """Unpack a vision image; with ``key``, also check its MAC. :class:`HalCodecError` names
    what is wrong."""
    if len(buf) < HEADER_SIZE + MAC_SIZE:
        raise HalCodecError(f"vision image: {len(buf)} bytes, shorter than a header")
    magic, version, flags, source, frame, stamp, sim, code, u, v, fx, fy = _HEADER.unpack_from(buf)
    if magic != MAGIC or version != VERSION or flags & ~FLAG_VALID or code > len(REASONS):
        raise HalCodecError("vision image: bad magic, version, flags or reason")
    body = len(buf) - MAC_SIZE
    if key is not None and not _mac(key).verify(buf[body:], buf[:body]):
        raise HalCodecError("vision image: bad MAC")
    reason = None if code == 0 else REASONS[code - 1]
    png = bytes(buf[HEADER_SIZE:body])
    return VisionImage(frame, stamp, sim, bool(flags & FLAG_VALID), reason, (u, v), (fx, fy), png,
                       source)  # fmt: skip


class ImageSlots:
    """Which frames the decimated image stream takes: the first frame at or after each slot of
    ``1 / fps`` of simulation time (so a lockstep run takes the same frames every time); a
    frame earlier than the last one seen starts a new run. One rule for both ends: the image
    log takes those frames, and the emulated camera sends them whole (the others may be a
    region of interest). ``fps <= 0``: no frame."""

    def __init__(self, fps: float) -> None:
        self.period_ns = round(1e9 / fps) if fps > 0 else 0
        self._next_ns: int | None = None
        self._last_ns: int | None = None

    def take(self, sim_time_ns: int) -> bool:
        """Whether the frame of ``sim_time_ns`` is taken (then the next slot is awaited)."""
        if self.period_ns <= 0:
            return False
        t = sim_time_ns
        if self._last_ns is not None and t < self._last_ns:
            self._next_ns = None  # a new run (the emulator's time went back)
        self._last_ns = t
        if self._next_ns is not None and t < self._next_ns:
            return False
        self._next_ns = (t // self.period_ns + 1) * self.period_ns
        return True

    def due(self, sim_time_ns: int) -> bool:
        """Whether :meth:`take` would take a frame of ``sim_time_ns`` (nothing changes)."""
        if self.period_ns <= 0:
            return False
        if self._last_ns is not None and sim_time_ns < self._last_ns:
            return True
        return self._next_ns is None or sim_time_ns >= self._next_ns

    def reset(self) -> None:
        """A new run: the next frame is taken."""
        self._next_ns = self._last_ns = None
