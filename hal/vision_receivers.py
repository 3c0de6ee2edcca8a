"""The receivers of the vision link: :class:`FeatureDecoder` (the controller's, of
``hil/vision/features``) and :class:`PoseDecoder` (the vision process's, of
``hil/emulator/camera_pose``). They authenticate, order and age-check every message of the wire
format of :mod:`hal.vision_codec`, never raise, and count each rejection (:class:`RxCounts`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from hal.secoc import rig_key
from hal.vision_codec import (
    FEATURES_LABEL,
    POSE_LABEL,
    FeatureMsg,
    PoseMsg,
    is_resend,
    parse_features,
    parse_pose,
    verified,
)


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

    def rejections(self) -> dict[str, int]:
        """The rejection counters that are not zero, by reason (``{"bad_mac": 150}``)."""
        return {k: n for k in REJECTION_FIELDS if (n := getattr(self, k))}

    def as_dict(self) -> dict[str, int]:
        d = asdict(self)
        d.update(
            malformed=self.malformed,
            stale=self.stale,
            untrusted=self.untrusted,
            rejected=self.rejected,
        )
        return d


REJECTION_FIELDS = (
    "bad_size",
    "bad_magic",
    "bad_version",
    "bad_flags",
    "bad_value",
    "bad_type",
    "stale_age",
    "stale_order",
    "backwards_stamp",
    "future_stamp",
    "foreign_source",
    "bad_mac",
)
"""The counters of :class:`RxCounts` that each count a rejection (``malformed``, ``stale`` and
``untrusted`` are their sums)."""


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

    def as_dict(self) -> dict[str, int]:
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
        if not verified(bytes(payload), self.key, label):
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
        out = _parse_guarded(parse_features, payload)
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
        out = _parse_guarded(parse_pose, payload)
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
