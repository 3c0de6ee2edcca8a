"""The simulator-control channel: harness commands to the emulated plant on ``hil/sim/control``.

What only an emulated rig can do (rewind the world to the scenario's start, name the camera
noise seed of the next run) is no part of the CAN database a real DSP implements: the harness
(``hil controller --plan``, used by ``hil experiment``) sends it here, on zenoh, and ``hil
emulator`` subscribes. A real rig has no subscriber, so such a command changes nothing there.

Wire format v1 — 40 bytes, little-endian (``<2sBBBxxxQQ``, then the MAC)::

    off size type  field
      0    2 bytes magic        b"HS"
      2    1 u8    version      1
      3    1 u8    command      1 = RESET_SCENARIO; any other value is malformed
      4    1 u8    flags        bit0 seed given (``seed`` is the new run's camera noise seed)
      5    3 bytes reserved     zero
      8    8 u64   freshness    the sender's wall clock in microseconds, strictly increasing
     16    8 u64   seed         with flag bit0: the camera noise seed (0 .. 2^32 - 1); else 0
     24   16 bytes mac          HMAC-SHA256 of bytes 0..23 truncated to 128 bits, with the rig
                                key derived for "hil/zenoh/sim_control" (hal/secoc.py)

:class:`SimControlReceiver` accepts a message only if its MAC verifies with the rig key
(else ``bad_mac``), its freshness is newer than the last accepted one (else ``replayed``) and
within :data:`FRESHNESS_WINDOW_US` of the receiver's clock (else ``stale``); every rejection is
counted, none raises.
"""

from __future__ import annotations

import contextlib
import enum
import struct
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import zenoh

from hal.errors import HalCodecError, HalTransportError
from hal.secoc import VISION_MAC_BYTES, Mac, derive, now_us, rig_key
from hal.zenoh_session import KEY_SIM_CONTROL

MAGIC = b"HS"
VERSION = 1
LABEL = "hil/zenoh/sim_control"
FLAG_SEED = 0x01
SEED_MAX = 0xFFFF_FFFF
"""The largest camera noise seed a scenario reset names (``camera.seed`` up to 2^32 - 1)."""
FRESHNESS_WINDOW_US = 30_000_000
"""How far a message's freshness may be from the receiver's wall clock (same host: any delay
of the link; across hosts: the clocks' disagreement too)."""
_BODY = struct.Struct("<2sBBBxxxQQ")
SIZE = _BODY.size + VISION_MAC_BYTES


class SimCommand(enum.IntEnum):
    """What the harness asks of the emulated plant."""

    RESET_SCENARIO = 1
    """Lockstep emulator only: the world back to the scenario's start (simulation time 0, the
    configured initial state) under a new DSP session, drive switch-on disabled, as a freshly
    started emulator; the camera noise restarts from the named seed (else the one at start)."""


@dataclass(frozen=True, slots=True)
class SimControl:
    """One simulator-control command; ``seed`` only with RESET_SCENARIO (None: unchanged)."""

    command: SimCommand
    seed: int | None = None


def _mac(key: bytes | None) -> Mac:
    return Mac(derive(rig_key() if key is None else key, LABEL), VISION_MAC_BYTES)


def encode(msg: SimControl, freshness_us: int, key: bytes | None = None) -> bytes:
    """The signed payload of ``msg``; :class:`HalCodecError` for a seed out of range."""
    seed = msg.seed
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise HalCodecError(f"sim control: seed must be an integer or None, got {seed!r}")
    if seed is not None and not 0 <= seed <= SEED_MAX:
        raise HalCodecError(f"sim control: seed must be in [0, {SEED_MAX}], got {seed}")
    flags = 0 if seed is None else FLAG_SEED
    body = _BODY.pack(MAGIC, VERSION, int(msg.command), flags, freshness_us, seed or 0)
    return body + _mac(key).tag1(body)


def parse(payload: bytes) -> tuple[SimControl, int] | str:
    """The command and its freshness, or the name of what is malformed (no MAC check)."""
    if len(payload) != SIZE:
        return "malformed"
    magic, version, command, flags, fv, seed = _BODY.unpack_from(payload)
    if magic != MAGIC or version != VERSION:
        return "bad_version"
    if payload[5:8] != b"\0\0\0" or flags & ~FLAG_SEED or (not flags and seed) or seed > SEED_MAX:
        return "malformed"
    try:
        cmd = SimCommand(command)
    except ValueError:
        return "malformed"
    return SimControl(cmd, seed if flags else None), fv


@dataclass
class SimControlCounts:
    """What the receiver did with each message."""

    accepted: int = 0
    bad_mac: int = 0
    malformed: int = 0
    bad_version: int = 0
    replayed: int = 0
    """Authentic, but not newer than the last accepted one (a replay or a repeat)."""
    stale: int = 0
    """Authentic, but its freshness is more than the window away from this clock."""

    @property
    def rejected(self) -> int:
        return self.bad_mac + self.malformed + self.bad_version + self.replayed + self.stale

    def as_dict(self) -> dict[str, int]:
        return {**asdict(self), "rejected": self.rejected}


class SimControlReceiver:
    """The emulator's side: :meth:`feed` one payload (zenoh's thread); ``on_command`` gets
    each accepted command. Wiring: ``session.subscribe(KEY_SIM_CONTROL, receiver.feed)``."""

    def __init__(
        self,
        on_command: Callable[[SimControl], None],
        *,
        key: bytes | None = None,
        clock_us: Callable[[], int] = now_us,
    ) -> None:
        self._on_command = on_command
        self._mac = _mac(key)
        self._clock = clock_us
        self._last_fv = 0
        self._lock = threading.Lock()
        self.counts = SimControlCounts()

    def feed(self, payload: bytes) -> SimControl | None:
        """Verify and apply one message; the command, or None when it was rejected (counted)."""
        payload = bytes(payload)
        with self._lock:
            parsed = parse(payload)
            if isinstance(parsed, str):
                setattr(self.counts, parsed, getattr(self.counts, parsed) + 1)
                return None
            body = len(payload) - VISION_MAC_BYTES
            if not self._mac.verify(payload[body:], payload[:body]):
                self.counts.bad_mac += 1
                return None
            msg, fv = parsed
            if fv <= self._last_fv:
                self.counts.replayed += 1
                return None
            if abs(fv - self._clock()) > FRESHNESS_WINDOW_US:
                self.counts.stale += 1
                return None
            self._last_fv = fv
            self.counts.accepted += 1
        self._on_command(msg)
        return msg


class SimControlSender:
    """The harness's side: publishes signed commands on ``hil/sim/control``."""

    def __init__(self, session: Any, *, key: bytes | None = None) -> None:
        self.key = key
        self._last_fv = 0
        self._session = session
        self._pub = session.publisher(KEY_SIM_CONTROL)

    def send(self, msg: SimControl) -> None:
        """Publish ``msg`` once; :class:`HalTransportError` if the session is broken."""
        self._last_fv = max(self._last_fv + 1, now_us())
        payload = encode(msg, self._last_fv, self.key)
        try:
            self._pub.put(payload)
        except zenoh.ZError as exc:
            raise HalTransportError(f"zenoh: cannot publish a sim control command: {exc}") from exc

    def has_subscribers(self) -> bool:
        """Whether an emulator listens on ``hil/sim/control`` (a real rig has none)."""
        return bool(self._session.has_subscriber(self._pub))

    def reset_scenario(self, seed: int | None = None) -> None:
        """Ask the emulator to restart the scenario (camera noise ``seed``; None: unchanged)."""
        self.send(SimControl(SimCommand.RESET_SCENARIO, seed))

    def close(self) -> None:
        """Undeclare the publisher (the session stays open). Idempotent."""
        with contextlib.suppress(zenoh.ZError):
            self._pub.undeclare()
