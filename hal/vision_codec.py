"""Versioned wire format of the vision link: features (vision -> controller) and camera poses
(emulator -> vision), plus receivers that reject and count bad messages.

Why a fixed little-endian struct and not JSON: a message is 56 bytes, packs/unpacks in about a
microsecond with one precompiled :class:`struct.Struct` (JSON costs 5-10x more and its size
varies), floats travel bit-exact (lockstep runs stay deterministic), and a fixed size per version
makes malformed input trivial to spot. JSON stays where people read it (the MCAP log).

Features v2 — key ``hil/vision/features``, 72 bytes, little-endian (``<2sBBIQqqQdd16s``)::

    off size type  field
      0    2 bytes magic        b"HF"
      2    1 u8    version      2
      3    1 u8    flags        bit0 valid (f holds a measurement), bit1 lockstep; others 0
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

Authentication: the receivers (:class:`FeatureDecoder`, :class:`PoseDecoder`) verify the MAC
with the rig key first (``bad_mac``), so only the rig's own vision process (and emulator) can
speak; their ordering and staleness checks then stop replays of authentic messages.
:func:`decode_features` / :func:`decode_pose` only unpack (logs stay readable after the run's
key is gone). v1 (no MAC) is refused as ``bad_version``, and so is a v2 camera pose (no seed).

Compatibility: a receiver accepts exactly the versions it knows; any change of layout or meaning
bumps the version byte. Reserved flag bits must be zero.
"""

from __future__ import annotations

import functools
import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

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
POSE_FLAG_LOCKSTEP = 0x01
POSE_FLAG_SEED = 0x02
_FEATURE_FLAGS = FLAG_VALID | FLAG_LOCKSTEP
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


def _verified(buf: bytes, key: bytes | None, label: str) -> bool:
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
    flags = (FLAG_VALID if msg.valid else 0) | (FLAG_LOCKSTEP if msg.lockstep else 0)
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


def _parse_features(buf: bytes) -> FeatureMsg | str:
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
    )


def _parse_pose(buf: bytes) -> PoseMsg | str:
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
    out = _parse_features(bytes(buf))
    if isinstance(out, str):
        raise HalCodecError(f"features: malformed message ({out}, {len(buf)} bytes)")
    return out


def decode_pose(buf: bytes) -> PoseMsg:
    """Unpack camera pose v3 (without checking the MAC) or raise :class:`HalCodecError`."""
    out = _parse_pose(bytes(buf))
    if isinstance(out, str):
        raise HalCodecError(f"camera pose: malformed message ({out}, {len(buf)} bytes)")
    return out


def _parse_guarded(parse: Callable[[bytes], object], payload: bytes) -> object:
    """``parse(payload)``, or the rejection kind ``"bad_type"`` for a payload that is not bytes."""
    try:
        return parse(payload)
    except TypeError:
        return "bad_type"


@dataclass
class RxCounts:
    """What a receiver did with each message it was fed (every message lands in one bucket
    besides ``received``: accepted, a ``bad_*`` malformation, or a ``stale_*`` rejection)."""

    received: int = 0
    accepted: int = 0
    bad_size: int = 0
    bad_magic: int = 0
    bad_version: int = 0
    bad_flags: int = 0
    bad_value: int = 0
    bad_type: int = 0
    """Not bytes-like at all (a bug on the caller's side, still never raised)."""
    bad_mac: int = 0
    """Well formed but not authenticated by the rig key (a rogue publisher, another rig)."""
    stale_age: int = 0
    """Older than the age limit when received."""
    stale_order: int = 0
    """Not newer than the last accepted message (replayed, repeated or going backwards)."""
    backwards_stamp: int = 0
    """Realtime: capture stamp older than the last accepted one of the same source."""
    future_stamp: int = 0
    """Realtime: stamped further in the future than the allowed clock skew (its age would be
    negative and pass any stale check)."""
    foreign_source: int = 0
    """From another source id than the locked-in publisher, which was not silent long enough
    for a takeover."""
    invalid: int = 0
    """Accepted messages flagged not valid (no measurement yet); subset of ``accepted``."""
    repeats: int = 0
    """Accepted re-sends of the same frame answering a newer pose; subset of ``accepted``."""
    source_changes: int = 0
    """A new source id took over (the first one, or after the locked source went silent for the
    takeover time); ordering restarts."""
    resyncs: int = 0
    """Ordering restarted after too many consecutive ``stale_order`` rejections."""
    resent: int = 0
    """Lockstep: authenticated re-sends of the last accepted message (the DSP publishes a
    period's pose again while it waits for the command, and the vision process answers it
    again); neither news nor a rejection."""

    @property
    def malformed(self) -> int:
        return (
            self.bad_size
            + self.bad_magic
            + self.bad_version
            + self.bad_flags
            + self.bad_value
            + self.bad_type
        )

    @property
    def stale(self) -> int:
        return self.stale_age + self.stale_order + self.backwards_stamp

    @property
    def untrusted(self) -> int:
        return self.future_stamp + self.foreign_source + self.bad_mac

    @property
    def rejected(self) -> int:
        return self.malformed + self.stale + self.untrusted

    def as_dict(self) -> dict[str, int]:
        d = asdict(self)
        d.update(
            malformed=self.malformed,
            stale=self.stale,
            untrusted=self.untrusted,
            rejected=self.rejected,
        )
        return d


class _Receiver:
    """Shared ordering/locking of the two receivers."""

    def __init__(
        self,
        resync_after: int,
        clock: Callable[[], int],
        source_takeover_ns: int | None = 0,
        key: bytes | None = None,
    ) -> None:
        if resync_after < 1:
            raise ValueError("resync_after must be at least 1")
        if source_takeover_ns is not None and source_takeover_ns < 0:
            raise ValueError("source_takeover_ns must be non-negative or None")
        self.counts = RxCounts()
        self.key = rig_key() if key is None else key
        self.resync_after = resync_after
        self.source_takeover_ns = source_takeover_ns
        self._clock = clock
        self._cond = threading.Condition(threading.Lock())
        self._source: int | None = None
        self._key: tuple[int, int] | None = None
        self._order_rejects = 0
        self._accepted_ns: int | None = None
        """Receive time of the last accepted message (the source lock's silence timer)."""

    @property
    def source(self) -> int | None:
        """The locked-in source id (``None`` before the first accepted message)."""
        return self._source

    def counters(self) -> dict[str, int]:
        """Every counter by name (``accepted``, ``future_stamp``, ``foreign_source``, ...,
        plus the sums ``malformed``, ``stale``, ``untrusted``, ``rejected``)."""
        with self._cond:
            return self.counts.as_dict()

    def _foreign(self, source: int, now: int) -> bool:
        """With the lock held: whether ``source`` must be rejected (counted) as foreign."""
        if self._source is None or source == self._source:
            return False
        takeover = self.source_takeover_ns
        if takeover is not None and (
            self._accepted_ns is None or now - self._accepted_ns >= takeover
        ):
            return False
        self.counts.foreign_source += 1
        return True

    def _count(self, parsed: object, payload: bytes, label: str) -> bool:
        """Count one received payload (caller holds the lock); False for a malformed one,
        whose kind (the string the parser returned) is counted too, or an unauthentic one."""
        c = self.counts
        c.received += 1
        if isinstance(parsed, str):
            setattr(c, parsed, getattr(c, parsed) + 1)
            return False
        if not _verified(bytes(payload), self.key, label):
            c.bad_mac += 1
            return False
        return True

    def _order(self, source: int, key: tuple[int, int]) -> int:
        """With the lock held: 0 = reject (counted), 1 = newer, 2 = accepted as a restart
        (new source or resync). Updates the ordering state unless rejected."""
        c = self.counts
        verdict = 1
        if self._source is not None and source != self._source:
            c.source_changes += 1
            self._key = None
            self._order_rejects = 0
            verdict = 2
        if self._key is not None and key <= self._key:
            self._order_rejects += 1
            if self._order_rejects < self.resync_after:
                c.stale_order += 1
                return 0
            c.resyncs += 1
            verdict = 2
        self._order_rejects = 0
        self._source = source
        self._key = key
        return verdict

    def reset(self) -> None:
        """Forget the source lock, ordering and latest message (counters stay)."""
        with self._cond:
            self._source = None
            self._key = None
            self._order_rejects = 0
            self._accepted_ns = None


def feature_age_ns(now_ns: int, stamp_ns: int, recv_ns: int) -> int:
    """Age of a feature measurement for staleness: the larger of its age by capture stamp and
    by receive time, never negative. A stamp from the future (within the allowed clock skew)
    cannot make a message look fresher than its arrival, and a message that arrived long ago
    stays old whatever its stamp says."""
    return max(now_ns - stamp_ns, now_ns - recv_ns, 0)


class FeatureDecoder(_Receiver):
    """Receiver side of ``hil/vision/features``: :meth:`feed` never raises.

    A message is accepted when, in this order (the first failing check names the counter):

    1. it is well formed (``bad_*``) and authentic: its MAC verifies with ``key``, the rig key
       (default: this process's ephemeral key) (``bad_mac``);
    2. realtime only: its ``stamp_ns`` is at most ``max_clock_skew_ns`` ahead of the receive
       clock (``future_stamp``) and at most ``max_age_ns`` behind it (``stale_age``); lockstep
       messages are judged in simulation time by the controller (see :meth:`sim_age_ns`);
    3. it comes from the locked-in source id (``foreign_source``). The first accepted message
       locks its source; another source takes over only once the locked one sent nothing
       accepted for ``source_takeover_ns`` (a restarted vision process; ``0`` = at once,
       ``None`` = never without :meth:`reset`). A second publisher can never interleave;
    4. realtime only: its stamp is not older than the last accepted one (``backwards_stamp``);
    5. it is newer than the last accepted one by ``(frame, pose_seq)`` (``stale_order``) — a
       lockstep re-send of the same frame answering a newer pose is newer; a replay is not.
       ``resync_after`` consecutive ordering rejections of otherwise fresh messages restart the
       ordering (a corrupted huge counter cannot lock the receiver out forever; checks 2-4
       still hold, so a resync never admits old data).

    Staleness: :meth:`age_ns` uses both the capture stamp and the receive time
    (:func:`feature_age_ns`), so it is never negative. :meth:`counters` returns every counter.

    Thread-safe: zenoh's callback thread feeds, the control loop reads :attr:`latest` or waits
    with :meth:`wait_pose_seq`. Wiring: ``session.subscribe(KEY_FEATURES, decoder.feed)``.
    """

    def __init__(
        self,
        *,
        max_age_ns: int | None = 100_000_000,
        resync_after: int = 10,
        clock: Callable[[], int] = time.monotonic_ns,
        max_clock_skew_ns: int = 5_000_000,
        source_takeover_ns: int | None = 1_000_000_000,
        key: bytes | None = None,
    ) -> None:
        super().__init__(resync_after, clock, source_takeover_ns, key)
        if max_clock_skew_ns < 0:
            raise ValueError("max_clock_skew_ns must be non-negative")
        self.max_age_ns = max_age_ns
        self.max_clock_skew_ns = max_clock_skew_ns
        self.latest: FeatureMsg | None = None
        """Newest accepted *valid* message."""
        self.latest_recv_ns: int | None = None
        """Receive time (``clock``) of :attr:`latest`."""
        self.last: FeatureMsg | None = None
        """Newest accepted message, valid or not."""
        self.pose_seq = -1
        """Highest ``pose_seq`` of an accepted message (-1 before the first)."""

    @classmethod
    def from_config(cls, controller: Any, **kwargs: Any) -> FeatureDecoder:
        """A decoder with the limits of a ``hal.config.ControllerConfig``: ``feature_timeout_s``,
        ``max_clock_skew_s``, ``feature_source_takeover_s``."""
        kwargs.setdefault("max_age_ns", round(controller.feature_timeout_s * 1e9))
        kwargs.setdefault("max_clock_skew_ns", round(controller.max_clock_skew_s * 1e9))
        kwargs.setdefault("source_takeover_ns", round(controller.feature_source_takeover_s * 1e9))
        return cls(**kwargs)

    def feed(self, payload: bytes, recv_ns: int | None = None) -> FeatureMsg | None:
        """Decode one payload; the accepted message, or None when it was rejected (counted)."""
        now = self._clock() if recv_ns is None else recv_ns
        out = _parse_guarded(_parse_features, payload)
        with self._cond:
            c = self.counts
            if not self._count(out, payload, FEATURES_LABEL):
                return None
            msg = out
            if is_resend(msg, self.last):
                c.resent += 1
                return None
            if not msg.lockstep:
                if msg.stamp_ns - now > self.max_clock_skew_ns:
                    c.future_stamp += 1
                    return None
                if self.max_age_ns is not None and now - msg.stamp_ns > self.max_age_ns:
                    c.stale_age += 1
                    return None
            if self._foreign(msg.source, now):
                return None
            last = self.last
            if (
                not msg.lockstep
                and last is not None
                and not last.lockstep
                and msg.source == last.source
                and msg.stamp_ns < last.stamp_ns
            ):
                c.backwards_stamp += 1
                return None
            verdict = self._order(msg.source, (msg.frame, msg.pose_seq))
            if not verdict:
                return None
            self._accepted_ns = now
            c.accepted += 1
            if last is not None and msg.frame == last.frame and msg.source == last.source:
                c.repeats += 1
            self.last = msg
            if msg.valid:
                self.latest = msg
                self.latest_recv_ns = now
            else:
                c.invalid += 1
            if verdict == 2 or msg.pose_seq > self.pose_seq:
                self.pose_seq = msg.pose_seq
            self._cond.notify_all()
            return msg

    def age_ns(self, now_ns: int | None = None) -> int | None:
        """Age of :attr:`latest` for staleness (None before the first valid message): the larger
        of its age by capture stamp and by receive time (:func:`feature_age_ns`), never
        negative. Realtime; lockstep runs judge :meth:`sim_age_ns`."""
        with self._cond:
            latest, recv = self.latest, self.latest_recv_ns
        if latest is None or recv is None:
            return None
        now = self._clock() if now_ns is None else now_ns
        return feature_age_ns(now, latest.stamp_ns, recv)

    def latest_received(self) -> tuple[FeatureMsg | None, int | None]:
        """(:attr:`latest`, :attr:`latest_recv_ns`) read together (one consistent pair)."""
        with self._cond:
            return self.latest, self.latest_recv_ns

    def fresh_latest(self, max_age_ns: int, now_ns: int | None = None) -> FeatureMsg | None:
        """:attr:`latest` if its :meth:`age_ns` is at most ``max_age_ns``, else None."""
        with self._cond:
            latest, recv = self.latest, self.latest_recv_ns
        if latest is None or recv is None:
            return None
        now = self._clock() if now_ns is None else now_ns
        return latest if feature_age_ns(now, latest.stamp_ns, recv) <= max_age_ns else None

    def sim_age_ns(self, sim_now_ns: int) -> int | None:
        """Age of :attr:`latest` in emulator time (lockstep): ``sim_now_ns - sim_time_ns``.

        Negative means the message claims a simulation time after ``sim_now_ns``: treat it as
        stale (``not 0 <= age <= timeout``), never as fresh."""
        latest = self.latest
        return None if latest is None else sim_now_ns - latest.sim_time_ns

    def wait_pose_seq(self, seq: int, timeout_s: float) -> FeatureMsg | None:
        """Block until a message answering pose ``seq`` or newer arrived (lockstep); returns
        :attr:`last`, or None on timeout."""
        with self._cond:
            ok = self._cond.wait_for(lambda: self.pose_seq >= seq, timeout_s)
            return self.last if ok else None

    def reset(self) -> None:
        super().reset()
        with self._cond:
            self.latest = self.last = None
            self.latest_recv_ns = None
            self.pose_seq = -1


def is_resend(msg: FeatureMsg | PoseMsg, last: FeatureMsg | PoseMsg | None) -> bool:
    """``msg`` is a lockstep re-send of ``last``: the same run, period and content (the
    stamps and the authentication may differ)."""
    if last is None or type(msg) is not type(last) or not (msg.lockstep and last.lockstep):
        return False
    return msg._replace(stamp_ns=0) == last._replace(stamp_ns=0)


class PoseDecoder(_Receiver):
    """Receiver side of ``hil/emulator/camera_pose`` (the vision process): :meth:`feed` never
    raises; rejects malformed poses and poses not newer (by ``seq``) than the last one."""

    def __init__(
        self,
        *,
        resync_after: int = 10,
        clock: Callable[[], int] = time.monotonic_ns,
        key: bytes | None = None,
    ) -> None:
        super().__init__(resync_after, clock, 0, key)  # source takeover 0: follow restarts
        self.latest: PoseMsg | None = None
        self.latest_recv_ns: int | None = None

    def feed(self, payload: bytes, recv_ns: int | None = None) -> PoseMsg | None:
        """Decode one payload; the accepted pose, or None when it was rejected (counted). A
        lockstep re-send of the latest pose is returned too (counted ``resent``): the DSP
        waits for its command, and the answer is to be sent again."""
        now = self._clock() if recv_ns is None else recv_ns
        out = _parse_guarded(_parse_pose, payload)
        with self._cond:
            c = self.counts
            if not self._count(out, payload, POSE_LABEL):
                return None
            if is_resend(out, self.latest):
                c.resent += 1
                return out
            if not self._order(out.source, (out.seq, 0)):
                return None
            self._accepted_ns = now
            c.accepted += 1
            self.latest = out
            self.latest_recv_ns = now
            return out
