"""Wire format of one camera frame over zenoh (camera -> frame grabber), like a network camera's.

Camera frame v2 — key ``hil/camera/frame``, 64-byte little-endian header
(``<2sBBIQqqqQHHB3xHHHH``), then ``width * height`` bytes of 8-bit grey pixels (row-major, top
row first) of the region ``(x0, y0)``-``(x0 + width, y0 + height)`` of the sensor's
``sensor_width`` x ``sensor_height`` frame (the whole frame, or a region of interest the frame
grabber asked for: :class:`RoiRequest`), then the MAC::

    off size type  field
      0    2 bytes magic        b"HC"
      2    1 u8    version      2
      3    1 u8    flags        bit0 lockstep (exactly one frame per control period); others 0
      4    4 u32   source       random id of the publishing camera (restart detection)
      8    8 u64   seq          frame counter of the camera (0, 1, ...)
     16    8 i64   stamp_ns     CLOCK_MONOTONIC at the middle of the exposure (the capture stamp)
     24    8 i64   sim_time_ns  emulator physics time at the middle of the exposure (a real
                                camera: the capture stamp again)
     32    8 i64   exposure_ns  exposure time (>= 0; 0: an instant, no motion blur)
     40    8 u64   period       lockstep: the control period k (camera pose seq) the frame
                                answers; realtime: seq of the newest camera pose when captured
     48    2 u16   width        pixels per row (> 0)
     50    2 u16   height       rows (> 0)
     52    1 u8    encoding     1 = mono8 (the only one)
     53    3       reserved     zero
     56    2 u16   x0           the region's first column in the sensor's frame
     58    2 u16   y0           the region's first row
     60    2 u16   sensor_width the sensor's frame (x0 + width <= sensor_width)
     62    2 u16   sensor_height                    (y0 + height <= sensor_height)
     64  w*h bytes pixels
    end   16 bytes mac          HMAC-SHA256 of header and pixels, truncated to 128 bits, with the
                                rig key derived for "hil/zenoh/camera_frame" (hal/secoc.py)

Region of interest (GenICam's OffsetX/OffsetY/Width/Height): the grabber's tracking window
reads about 130x130 px of a 640x480 frame, so it names that region for the camera's next frame
on ``hil/camera/roi`` (:class:`RoiRequest`, 24 bytes and a MAC) and the camera sends only it;
its offset and the sensor's size are in the authenticated header. Request v1::

    off size type  field
      0    2 bytes magic        b"HW"
      2    1 u8    version      1
      3    1 u8    flags        0
      4    4 u32   source       the camera (frame source id) the request is for
      8    8 u64   seq          the camera frame it is for
     16    2 u16   x0, y0, width, height: the region; all 0: the whole frame
     24   16 bytes mac          HMAC-SHA256 truncated to 128 bits, key for "hil/zenoh/camera_roi"

A request for the frame just sent, naming the whole frame, asks for that frame again whole (the
target was not in its region).

Why raw pixels and not PNG/JPEG: a 640x480 frame is 300 kB, encoding costs milliseconds and a
lossy codec changes what the detector sees; raw mono8 is what a GigE Vision camera streams. The
MAC (as on the other zenoh links) costs about 0.2 ms per 640x480 frame and keeps a rogue or
another rig's camera out. :func:`decode_frame` gives a zero-copy numpy view of the pixels.

Zenoh's shared memory carries the frames already: the rig's sessions keep zenoh's default
``transport.shared_memory``, under which a put over 3 kB goes through a shared-memory pool
between processes of one host by itself; it halves a frame's transport, and an explicit
``zenoh.shm.ShmProvider`` buys nothing more. A config that turns it off doubles the frame's
transport. Figures: ``python scripts/bench_frame_shm.py`` (docs/benchmarks.md, "Design
choices, measured").
"""

from __future__ import annotations

import functools
import struct
import threading
from dataclasses import dataclass

import numpy as np

from hal.errors import HalCodecError
from hal.secoc import VISION_MAC_BYTES, Mac, derive, rig_key
from hal.vision_receivers import RxCounts

FRAME_MAGIC = b"HC"
FRAME_VERSION = 2
FRAME_LABEL = "hil/zenoh/camera_frame"
FLAG_LOCKSTEP = 0x01
ENCODING_MONO8 = 1
ENCODINGS = {ENCODING_MONO8: "mono8"}
"""Encoding byte -> the name (ROS/Foxglove spelling)."""
MAC_SIZE = VISION_MAC_BYTES
_HEADER = struct.Struct("<2sBBIQqqqQHHB3xHHHH")
HEADER_SIZE = _HEADER.size
MAX_SIDE = 65535


@dataclass(frozen=True)
class CameraFrame:
    """One decoded frame; ``pixels`` is a read-only (height, width) uint8 view of the payload."""

    seq: int
    stamp_ns: int
    sim_time_ns: int
    exposure_ns: int
    period: int
    pixels: np.ndarray
    lockstep: bool = False
    source: int = 0
    encoding: str = "mono8"
    x0: int = 0
    """The pixels' first column in the sensor's frame (a region of interest: > 0 or smaller)."""
    y0: int = 0
    sensor_size: tuple[int, int] | None = None
    """The sensor's frame (width, height); None: the pixels' own (a whole frame)."""

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])

    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def is_roi(self) -> bool:
        """Whether the pixels are a region of the sensor's frame, not all of it."""
        return self.sensor_size is not None and self.sensor_size != (self.width, self.height)


def frame_size(width: int, height: int) -> int:
    """Bytes of an encoded ``width`` x ``height`` mono8 frame (header, pixels, MAC)."""
    return HEADER_SIZE + width * height + MAC_SIZE


@functools.lru_cache(maxsize=8)
def _mac_of(key: bytes) -> Mac:
    return Mac(derive(key, FRAME_LABEL), MAC_SIZE)


def _mac(key: bytes | None) -> Mac:
    return _mac_of(rig_key() if key is None else key)


def encode_frame(
    pixels: np.ndarray,
    *,
    seq: int,
    stamp_ns: int,
    sim_time_ns: int,
    exposure_ns: int,
    period: int,
    lockstep: bool = False,
    source: int = 0,
    key: bytes | None = None,
    x0: int = 0,
    y0: int = 0,
    sensor_size: tuple[int, int] | None = None,
) -> bytes:
    """Pack one mono8 frame (``pixels``: a 2-D uint8 array; a region of interest at ``(x0,
    y0)`` of a ``sensor_size`` frame, default: the whole frame), authenticated with the rig
    ``key`` (default: this process's ephemeral key); :class:`HalCodecError` for what a receiver
    would reject."""
    if not isinstance(pixels, np.ndarray) or pixels.ndim != 2 or pixels.dtype != np.uint8:
        raise HalCodecError(
            f"camera frame: pixels must be a 2-D uint8 array, got "
            f"{getattr(pixels, 'dtype', type(pixels).__name__)} {getattr(pixels, 'shape', '')}"
        )
    height, width = pixels.shape
    if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
        raise HalCodecError(f"camera frame: size {width}x{height} out of range 1..{MAX_SIDE}")
    if exposure_ns < 0:
        raise HalCodecError(f"camera frame: exposure_ns must be non-negative, got {exposure_ns}")
    sw, sh = (width, height) if sensor_size is None else sensor_size
    inside = x0 + width <= sw <= MAX_SIDE and y0 + height <= sh <= MAX_SIDE
    if x0 < 0 or y0 < 0 or not inside:
        raise HalCodecError(
            f"camera frame: region {width}x{height} at ({x0}, {y0}) is not inside {sw}x{sh}"
        )
    try:
        header = _HEADER.pack(
            FRAME_MAGIC,
            FRAME_VERSION,
            FLAG_LOCKSTEP if lockstep else 0,
            source,
            seq,
            stamp_ns,
            sim_time_ns,
            exposure_ns,
            period,
            width,
            height,
            ENCODING_MONO8,
            x0,
            y0,
            sw,
            sh,
        )
    except struct.error as exc:
        raise HalCodecError(f"camera frame: field out of range: {exc}") from exc
    body = np.ascontiguousarray(pixels).data
    return b"".join((header, body, _mac(key).tag(header, body)))


def _parse(buf: bytes | bytearray | memoryview) -> CameraFrame | str:
    """The frame, or the name of the malformation counter."""
    n = len(buf)
    if n < HEADER_SIZE + MAC_SIZE:
        return "bad_size"
    magic, version, flags, source, seq, stamp, sim, exposure, period, w, h, enc, x0, y0, sw, sh = (
        _HEADER.unpack_from(buf)
    )
    if magic != FRAME_MAGIC:
        return "bad_magic"
    if version != FRAME_VERSION:
        return "bad_version"
    if flags & ~FLAG_LOCKSTEP:
        return "bad_flags"
    if enc not in ENCODINGS or w == 0 or h == 0 or exposure < 0:
        return "bad_value"
    if x0 + w > sw or y0 + h > sh:  # a region outside the sensor's frame
        return "bad_value"
    if n != frame_size(w, h):
        return "bad_size"
    pixels = np.frombuffer(buf, dtype=np.uint8, count=w * h, offset=HEADER_SIZE).reshape(h, w)
    if pixels.flags.writeable:
        pixels = pixels.view()
        pixels.flags.writeable = False
    return CameraFrame(
        seq,
        stamp,
        sim,
        exposure,
        period,
        pixels,
        bool(flags & FLAG_LOCKSTEP),
        source,
        ENCODINGS[enc],
        x0,
        y0,
        (sw, sh),
    )


def decode_frame(buf: bytes | bytearray | memoryview) -> CameraFrame:
    """Unpack camera frame v2 (without checking the MAC: logs, tools) or raise
    :class:`HalCodecError` naming the problem (a mis-sized payload is ``bad_size``)."""
    try:
        out = _parse(buf)
    except TypeError:
        out = "bad_type"
    if isinstance(out, str):
        n = len(buf) if hasattr(buf, "__len__") else "?"
        raise HalCodecError(f"camera frame: malformed frame ({out}, {n} bytes)")
    return out


class FrameDecoder:
    """Receiver side of ``hil/camera/frame`` (the frame grabber): :meth:`feed` never raises.

    Counters (:class:`hal.vision_codec.RxCounts`, the features link's): a frame is accepted when
    it is well formed (``bad_*``: ``bad_size`` for a payload that is not exactly header, width x
    height pixels and MAC; ``bad_value`` for an unknown encoding, a zero side or a negative
    exposure), authentic (``bad_mac``) and newer than the last accepted frame of the same camera
    by ``(seq, period)`` (``stale_order``; the same frame again whole after its region of
    interest is newer: the grabber asked for it, see :class:`RoiRequest`). A new
    source id (a restarted camera) takes over at once (``source_changes``). In lockstep, the
    same frame again (same source, seq and period) is returned too and counted ``resent``: the
    camera answers a re-sent pose with it, and the grabber answers it again.

    Thread-safe: zenoh's callback thread feeds, anyone reads :meth:`counters`.
    """

    def __init__(self, *, key: bytes | None = None) -> None:
        self.counts = RxCounts()
        self.key = rig_key() if key is None else key
        self._lock = threading.Lock()
        self.last: CameraFrame | None = None
        """Newest accepted frame."""

    def feed(self, payload: bytes | bytearray | memoryview) -> CameraFrame | None:
        """Decode one payload: the accepted (or re-sent) frame, or None when it was rejected."""
        try:
            out = _parse(payload)
        except TypeError:
            out = "bad_type"
        with self._lock:
            c = self.counts
            c.received += 1
            if isinstance(out, str):
                setattr(c, out, getattr(c, out) + 1)
                return None
            view = memoryview(payload)
            body = len(view) - MAC_SIZE
            if not _mac(self.key).verify(view[body:], view[:body]):
                c.bad_mac += 1
                return None
            last = self.last
            if last is not None and last.source == out.source:
                same = (out.seq, out.period) == (last.seq, last.period)
                if same and last.is_roi and not out.is_roi:
                    pass  # the frame again whole, asked for: accepted
                elif out.lockstep and same:
                    c.resent += 1
                    return out
                elif (out.seq, out.period) <= (last.seq, last.period):
                    c.stale_order += 1
                    return None
            elif last is not None:
                c.source_changes += 1
            c.accepted += 1
            self.last = out
            return out

    def as_dict(self) -> dict[str, int]:
        """Every counter by name, plus the sums ``malformed``, ``stale``, ``untrusted`` and
        ``rejected``."""
        with self._lock:
            return self.counts.as_dict()


ROI_MAGIC = b"HW"
ROI_VERSION = 1
ROI_LABEL = "hil/zenoh/camera_roi"
_ROI = struct.Struct("<2sBBIQHHHH")
ROI_SIZE = _ROI.size + MAC_SIZE


@dataclass(frozen=True)
class RoiRequest:
    """The region of interest a frame grabber wants in camera frame ``seq`` of camera
    ``source``: ``window = (x0, y0, x1, y1)`` px, end exclusive, or None for the whole frame."""

    source: int
    seq: int
    window: tuple[int, int, int, int] | None

    def clamped(self, width: int, height: int) -> tuple[int, int, int, int] | None:
        """The window inside a ``width`` x ``height`` frame; None: the whole frame (no window,
        or nothing of it inside the frame)."""
        if self.window is None:
            return None
        x0, y0, x1, y1 = self.window
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
        if x0 >= x1 or y0 >= y1:
            return None
        return (x0, y0, x1, y1)


@functools.lru_cache(maxsize=8)
def _roi_mac_of(key: bytes) -> Mac:
    return Mac(derive(key, ROI_LABEL), MAC_SIZE)


def _roi_mac(key: bytes | None) -> Mac:
    return _roi_mac_of(rig_key() if key is None else key)


def encode_roi_request(req: RoiRequest, key: bytes | None = None) -> bytes:
    """Pack a request (a window must lie in 0..65535 and not be empty), authenticated with the
    rig ``key``; :class:`HalCodecError` otherwise."""
    x0, y0, x1, y1 = (0, 0, 0, 0) if req.window is None else req.window
    if req.window is not None and not (0 <= x0 < x1 <= MAX_SIDE and 0 <= y0 < y1 <= MAX_SIDE):
        raise HalCodecError(f"roi request: window {req.window} is empty or out of range")
    try:
        body = _ROI.pack(ROI_MAGIC, ROI_VERSION, 0, req.source, req.seq, x0, y0, x1 - x0, y1 - y0)
    except struct.error as exc:
        raise HalCodecError(f"roi request: field out of range: {exc}") from exc
    return body + _roi_mac(key).tag(body)


def decode_roi_request(buf: bytes | bytearray | memoryview, key: bytes | None = None) -> RoiRequest:
    """Unpack and authenticate a request, or raise :class:`HalCodecError` naming the problem
    (``malformed`` or ``bad_mac``)."""
    try:
        view = memoryview(buf)
    except TypeError:
        raise HalCodecError("roi request: malformed (not bytes)") from None
    if len(view) != ROI_SIZE:
        raise HalCodecError(f"roi request: malformed ({len(view)} bytes, want {ROI_SIZE})")
    magic, version, flags, source, seq, x0, y0, w, h = _ROI.unpack_from(view)
    if magic != ROI_MAGIC or version != ROI_VERSION or flags or (w == 0) != (h == 0):
        raise HalCodecError("roi request: malformed (magic, version, flags or size)")
    body = _ROI.size
    if not _roi_mac(key).verify(view[body:], view[:body]):
        raise HalCodecError("roi request: bad_mac")
    return RoiRequest(source, seq, None if w == 0 else (x0, y0, x0 + w, y0 + h))
