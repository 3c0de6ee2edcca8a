"""Versioned wire format of the vision link: features (vision -> controller) and camera poses
(emulator -> vision); the receivers that reject and count bad messages are
:mod:`hal.vision_receivers`.

Why a fixed little-endian struct and not JSON: a message is 56 bytes, packs/unpacks in about a
microsecond with one precompiled :class:`struct.Struct` (JSON costs 5-10x more and its size
varies), floats travel bit-exact (lockstep runs stay deterministic), and a fixed size per version
makes malformed input trivial to spot. JSON stays where people read it (the MCAP log).

Features v2 — key ``hil/vision/features``, 72 bytes, little-endian (``<2sBBIQqqQdd16s``)::

    off size type  field
      0    2 bytes magic        b"HF"
      2    1 u8    version      2
      3    1 u8    flags        bit0 valid (f holds a measurement), bit1 lockstep, bit2 image
                                (this frame's camera image follows on hil/vision/image, for
                                the log); others 0
      4    4 u32   source       random id of the publishing vision process (restart detection)
      8    8 u64   frame        frame counter of the image (0, 1, ...)
     16    8 i64   stamp_ns     CLOCK_MONOTONIC at capture on the vision host (on one host this
                                is the emulator's clock too)
     24    8 i64   sim_time_ns  emulator physics time of the camera pose the image was taken at
     32    8 u64   pose_seq     seq of the newest camera pose seen when published; in lockstep,
                                the pose this message answers
     40    8 f64   fx           feature x, px
     48    8 f64   fy           feature y, px (f must be finite; (0, 0) when not valid)
     56   16 bytes mac          HMAC-SHA256 of bytes 0..55, truncated to 128 bits, with the
                                rig key derived for "hil/zenoh/features" (hal/secoc.py)

Camera pose v3 — key ``hil/emulator/camera_pose``, 80 bytes (``<2sBBIQqqdddQ16s``)::

      0    2 bytes magic        b"HP"
      2    1 u8    version      3
      3    1 u8    flags        bit0 lockstep (one pose per control period, answer each);
                                bit1 seed (the run's camera noise seed is ``seed``); others 0
      4    4 u32   source       random id of the publishing emulator (restart detection)
      8    8 u64   seq          pose sequence number (the control tick in lockstep)
     16    8 i64   sim_time_ns  emulator physics time of the pose
     24    8 i64   stamp_ns     CLOCK_MONOTONIC of the emulator when the pose was sampled
     32    8 f64   x            camera position, m
     40    8 f64   y            camera position, m
     48    8 f64   phi          camera heading q1 + q2, rad
     56    8 u64   seed         with flag bit1: the camera noise seed of the emulator's run (a
                                scenario reset named it); else 0 (the vision process's own)
     64   16 bytes mac          as for features, key derived for "hil/zenoh/camera_pose"

Authentication: the receivers (:class:`~hal.vision_receivers.FeatureDecoder`,
:class:`~hal.vision_receivers.PoseDecoder`) verify the MAC
with the rig key first (``bad_mac``), so only the rig's own vision process (and emulator) can
speak; their ordering and staleness checks then stop replays of authentic messages.
:func:`decode_features` / :func:`decode_pose` only unpack (logs stay readable after the run's
key is gone). v1 (no MAC) is refused as ``bad_version``, and so is a v2 camera pose (no seed).

Compatibility: a receiver accepts exactly the versions it knows; any change of layout or meaning
bumps the version byte. Reserved flag bits must be zero, so a receiver that predates a flag
refuses a message that sets it (``bad_flags``) rather than misread it.
"""

from __future__ import annotations

import functools
import math
import struct
from typing import NamedTuple

from hal.errors import HalCodecError
from hal.secoc import VISION_MAC_BYTES, Mac, derive, rig_key

FEATURES_MAGIC = b"HF"
POSE_MAGIC = b"HP"
VERSION = 2
"""Version of the features message."""
POSE_VERSION = 3
"""Version of the camera pose message (v3 added the run's noise seed)."""
MAC_SIZE = VISION_MAC_BYTES
FEATURES_LABEL = "hil/zenoh/features"
POSE_LABEL = "hil/zenoh/camera_pose"
FLAG_VALID = 0x01
FLAG_LOCKSTEP = 0x02
FLAG_IMAGE = 0x04
POSE_FLAG_LOCKSTEP = 0x01
POSE_FLAG_SEED = 0x02
_FEATURE_FLAGS = FLAG_VALID | FLAG_LOCKSTEP | FLAG_IMAGE
_POSE_FLAGS = POSE_FLAG_LOCKSTEP | POSE_FLAG_SEED
_FEAT = struct.Struct("<2sBBIQqqQdd")
_POSE = struct.Struct("<2sBBIQqqdddQ")
FEATURES_SIZE = _FEAT.size + MAC_SIZE
POSE_SIZE = _POSE.size + MAC_SIZE


@functools.lru_cache(maxsize=16)
def _mac_of(key: bytes, label: str) -> Mac:
    return Mac(derive(key, label), MAC_SIZE)


def _mac(key: bytes | None, label: str) -> Mac:
    """The MAC of ``label`` with ``key`` (default: :func:`hal.secoc.rig_key`)."""
    return _mac_of(rig_key() if key is None else key, label)


def verified(buf: bytes, key: bytes | None, label: str) -> bool:
    body = len(buf) - MAC_SIZE
    return _mac(key, label).verify(buf[body:], buf[:body])


_isfinite = math.isfinite


class FeatureMsg(NamedTuple):
    """One features message (see the module docstring for the meaning of each field)."""

    frame: int
    stamp_ns: int
    sim_time_ns: int
    pose_seq: int
    f: tuple[float, float]
    valid: bool = True
    lockstep: bool = False
    source: int = 0
    image: bool = False
    """The camera image of this frame follows for the log (the receiver can count it lost)."""

    def as_dict(self) -> dict[str, object]:
        """Plain dict for JSON logs (``f`` as a list)."""
        d: dict[str, object] = self._asdict()
        d["f"] = list(self.f)
        return d


class PoseMsg(NamedTuple):
    """One camera-pose message (see the module docstring)."""

    seq: int
    sim_time_ns: int
    stamp_ns: int
    x: float
    y: float
    phi: float
    lockstep: bool = False
    source: int = 0
    seed: int | None = None
    """The camera noise seed of the emulator's run, when a scenario reset named one."""


def encode_features(msg: FeatureMsg, key: bytes | None = None) -> bytes:
    """Pack ``msg`` as features v2, authenticated with the rig ``key`` (default: this process's
    ephemeral key); :class:`HalCodecError` for values the receiver would reject."""
    fx, fy = msg.f
    if not (_isfinite(fx) and _isfinite(fy)):
        raise HalCodecError(f"features: f must be finite, got {msg.f}")
    flags = (
        (FLAG_VALID if msg.valid else 0)
        | (FLAG_LOCKSTEP if msg.lockstep else 0)
        | (FLAG_IMAGE if msg.image else 0)
    )
    try:
        body = _FEAT.pack(
            FEATURES_MAGIC,
            VERSION,
            flags,
            msg.source,
            msg.frame,
            msg.stamp_ns,
            msg.sim_time_ns,
            msg.pose_seq,
            fx,
            fy,
        )
    except struct.error as exc:
        raise HalCodecError(f"features: field out of range: {exc}") from exc
    return body + _mac(key, FEATURES_LABEL).tag(body)


def encode_pose(msg: PoseMsg, key: bytes | None = None) -> bytes:
    """Pack ``msg`` as camera pose v3, authenticated with the rig ``key`` (as features)."""
    if not (_isfinite(msg.x) and _isfinite(msg.y) and _isfinite(msg.phi)):
        raise HalCodecError(f"camera pose: x, y, phi must be finite, got {msg}")
    if msg.seed is not None and (isinstance(msg.seed, bool) or not isinstance(msg.seed, int)):
        raise HalCodecError(f"camera pose: seed must be an integer or None, got {msg.seed!r}")
    flags = (POSE_FLAG_LOCKSTEP if msg.lockstep else 0) | (
        0 if msg.seed is None else POSE_FLAG_SEED
    )
    try:
        body = _POSE.pack(
            POSE_MAGIC,
            POSE_VERSION,
            flags,
            msg.source,
            msg.seq,
            msg.sim_time_ns,
            msg.stamp_ns,
            msg.x,
            msg.y,
            msg.phi,
            0 if msg.seed is None else msg.seed,
        )
    except struct.error as exc:
        raise HalCodecError(f"camera pose: field out of range: {exc}") from exc
    return body + _mac(key, POSE_LABEL).tag(body)


def parse_features(buf: bytes) -> FeatureMsg | str:
    """The message, or the name of the malformation counter."""
    if len(buf) != FEATURES_SIZE:
        return "bad_size"
    magic, version, flags, source, frame, stamp, sim, seq, fx, fy = _FEAT.unpack_from(buf)
    if magic != FEATURES_MAGIC:
        return "bad_magic"
    if version != VERSION:
        return "bad_version"
    if flags & ~_FEATURE_FLAGS:
        return "bad_flags"
    if not (_isfinite(fx) and _isfinite(fy)):
        return "bad_value"
    return FeatureMsg(
        frame,
        stamp,
        sim,
        seq,
        (fx, fy),
        bool(flags & FLAG_VALID),
        bool(flags & FLAG_LOCKSTEP),
        source,
        bool(flags & FLAG_IMAGE),
    )


def parse_pose(buf: bytes) -> PoseMsg | str:
    if len(buf) != POSE_SIZE:
        return "bad_size"
    magic, version, flags, source, seq, sim, stamp, x, y, phi, seed = _POSE.unpack_from(buf)
    if magic != POSE_MAGIC:
        return "bad_magic"
    if version != POSE_VERSION:
        return "bad_version"
    if flags & ~_POSE_FLAGS:
        return "bad_flags"
    if not (_isfinite(x) and _isfinite(y) and _isfinite(phi)):
        return "bad_value"
    if seed and not flags & POSE_FLAG_SEED:
        return "bad_value"
    return PoseMsg(
        seq,
        sim,
        stamp,
        x,
        y,
        phi,
        bool(flags & POSE_FLAG_LOCKSTEP),
        source,
        seed if flags & POSE_FLAG_SEED else None,
    )


def decode_features(buf: bytes) -> FeatureMsg:
    """Unpack features v2 (without checking the MAC: logs, tools) or raise
    :class:`HalCodecError` naming the problem."""
    out = parse_features(bytes(buf))
    if isinstance(out, str):
        raise HalCodecError(f"features: malformed message ({out}, {len(buf)} bytes)")
    return out


def decode_pose(buf: bytes) -> PoseMsg:
    """Unpack camera pose v3 (without checking the MAC) or raise :class:`HalCodecError`."""
    out = parse_pose(bytes(buf))
    if isinstance(out, str):
        raise HalCodecError(f"camera pose: malformed message ({out}, {len(buf)} bytes)")
    return out


def is_resend(msg: FeatureMsg | PoseMsg, last: FeatureMsg | PoseMsg | None) -> bool:
    """``msg`` is a lockstep re-send of ``last``: the same run, period and content (the
    stamps and the authentication may differ)."""
    if last is None or type(msg) is not type(last) or not (msg.lockstep and last.lockstep):
        return False
    return msg._replace(stamp_ns=0) == last._replace(stamp_ns=0)
