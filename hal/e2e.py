"""End-to-end protection of CAN frames (AUTOSAR E2E Profile 1 style).

Layout shared by every message of ``hal/hil.dbc`` (checked when the database is loaded):

* byte 0: CRC-8 SAE J1850 (poly 0x1D, init 0xFF, xor-out 0xFF) over the message's 16-bit data
  id (low byte, then high byte) followed by payload bytes 1..7;
* bits 8..11 (low nibble of byte 1): rolling counter 0..15, incremented by one per frame sent.

The receiver checks, in this order: known id, length, authentication (optional, SecOC trailer
of :mod:`hal.secoc` after these 8 bytes), CRC, counter. A counter equal to the last
accepted one is a repeated frame; a forward step of 1..``max_delta`` is accepted (steps above 1
are counted as ``lost`` frames); anything else is a counter jump: the frame is rejected and the
receiver resynchronises on it, so the next consecutive frame is accepted again. The first frame of
an id, and the first one after ``reinit_after_ns`` of silence on that id, is accepted as is.

Nothing in the receive path raises for a bad frame: every verdict is counted in
:class:`E2EStats`.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import can

from hal.errors import HalCodecError

FRAME_LENGTH = 8
"""The E2E-protected part of every frame: bytes 0..7 (the SecOC trailer of :mod:`hal.secoc`
follows it in the 16-byte CAN FD frame)."""
COUNTER_MODULO = 16
DEFAULT_MAX_DELTA = 3
"""Largest accepted counter step: up to two frames in a row may be lost."""
DEFAULT_REINIT_AFTER_NS = 500_000_000
"""After this much silence on an id the next frame re-initialises its counter (peer restart)."""


def _make_table(poly: int) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_CRC8_TABLE = _make_table(0x1D)


def crc8_sae_j1850(data: bytes | bytearray | memoryview | Iterable[int]) -> int:
    """CRC-8 SAE J1850 (AUTOSAR ``Crc_CalculateCRC8``): check value of ``b"123456789"`` is 0x4B."""
    crc = 0xFF
    table = _CRC8_TABLE
    for byte in data:
        crc = table[crc ^ byte]
    return crc ^ 0xFF


def e2e_crc(data_id: int, payload: bytes | bytearray | memoryview) -> int:
    """CRC of one frame: data id (low, high byte) then ``payload[1:8]`` (byte 0 holds the CRC)."""
    table = _CRC8_TABLE
    crc = table[0xFF ^ (data_id & 0xFF)]
    crc = table[crc ^ (data_id >> 8)]
    for i in range(1, FRAME_LENGTH):
        crc = table[crc ^ payload[i]]
    return crc ^ 0xFF


class Verdict(enum.StrEnum):
    """Outcome of :meth:`E2EReceiver.check`; the value is the :class:`E2EStats` field name."""

    OK = "accepted"
    IGNORED = "ignored"
    """A valid database id sent by this node's own role (echo or a second controller)."""
    BAD_CRC = "bad_crc"
    REPEATED_COUNTER = "repeated_counter"
    COUNTER_JUMP = "counter_jump"
    WRONG_LENGTH = "wrong_length"
    UNKNOWN_ID = "unknown_id"
    DECODE_ERROR = "decode_error"
    ERROR_FRAME = "error_frame"
    BAD_MAC = "bad_mac"
    """SecOC: the MAC does not verify (forged, another rig's key, corrupted)."""
    STALE_FRESHNESS = "stale_freshness"
    """SecOC: authentic but not fresh (a replayed or repeated frame)."""
    FUTURE_FRESHNESS = "future_freshness"
    """SecOC: authentic but its freshness value runs ahead of the receiver's clock."""


REJECTIONS: tuple[Verdict, ...] = (
    Verdict.BAD_CRC,
    Verdict.REPEATED_COUNTER,
    Verdict.COUNTER_JUMP,
    Verdict.WRONG_LENGTH,
    Verdict.UNKNOWN_ID,
    Verdict.DECODE_ERROR,
    Verdict.ERROR_FRAME,
    Verdict.BAD_MAC,
    Verdict.STALE_FRESHNESS,
    Verdict.FUTURE_FRESHNESS,
)
"""The verdicts that count as a rejected (bad) frame."""
AUTH_REJECTIONS: tuple[Verdict, ...] = (
    Verdict.BAD_MAC,
    Verdict.STALE_FRESHNESS,
    Verdict.FUTURE_FRESHNESS,
)
"""The rejections by authentication (:mod:`hal.secoc`): a frame not from this rig's members."""


@dataclass
class E2EStats:
    """Counters of every receive verdict (one field per :class:`Verdict` value) plus lost frames."""

    accepted: int = 0
    ignored: int = 0
    lost: int = 0
    """Frames missing in counter gaps that were still within ``max_delta`` (not rejections)."""
    bad_crc: int = 0
    repeated_counter: int = 0
    counter_jump: int = 0
    wrong_length: int = 0
    unknown_id: int = 0
    decode_error: int = 0
    error_frame: int = 0
    bad_mac: int = 0
    stale_freshness: int = 0
    future_freshness: int = 0

    def record(self, verdict: Verdict) -> None:
        """Count one frame under ``verdict``."""
        setattr(self, verdict.value, getattr(self, verdict.value) + 1)

    @property
    def rejected(self) -> int:
        """Total of rejected (bad) frames."""
        return sum(getattr(self, v.value) for v in REJECTIONS)

    @property
    def auth_rejected(self) -> int:
        """Frames rejected by authentication (bad MAC or freshness)."""
        return self.bad_mac + self.stale_freshness + self.future_freshness

    def rejections(self) -> dict[str, int]:
        """The rejection counters that are not zero, by verdict (``{"bad_mac": 312}``)."""
        return {v.value: n for v in REJECTIONS if (n := getattr(self, v.value))}

    def copy(self) -> E2EStats:
        return dataclasses.replace(self)

    def as_dict(self) -> dict[str, int]:
        """All counters plus ``rejected``, for logs and ``--json`` summaries."""
        out = dataclasses.asdict(self)
        out["rejected"] = self.rejected
        return out


class E2ESender:
    """Writes the rolling counter and the CRC into outgoing payloads, one counter per data id."""

    def __init__(self) -> None:
        self._counters: dict[int, int] = {}

    def next_counter(self, data_id: int) -> int:
        """The counter the next frame of ``data_id`` gets (0 for the first one)."""
        return self._counters.get(data_id, 0)

    def protect(self, data_id: int, payload: bytearray) -> bytearray:
        """Set counter and CRC of an 8-byte ``payload`` in place and advance the counter."""
        if len(payload) != FRAME_LENGTH:
            raise HalCodecError(f"E2E payload must be {FRAME_LENGTH} bytes, got {len(payload)}")
        counter = self._counters.get(data_id, 0)
        payload[1] = (payload[1] & 0xF0) | counter
        payload[0] = e2e_crc(data_id, payload)
        self._counters[data_id] = (counter + 1) % COUNTER_MODULO
        return payload


class E2EReceiver:
    """Checks incoming frames and keeps the per-id counter state.

    ``rx_ids`` maps the frame ids this node accepts to their E2E data ids; ``ignore_ids`` are
    valid ids of the database that this node sends itself (counted as ``ignored``). Every other
    standard or extended id is an unknown id. :meth:`check` records every verdict except
    :attr:`Verdict.OK`, which the caller records once the payload decoded (or records
    :attr:`Verdict.DECODE_ERROR` instead), so each frame is counted exactly once.
    """

    def __init__(
        self,
        rx_ids: Mapping[int, int],
        ignore_ids: Iterable[int] = (),
        *,
        max_delta: int = DEFAULT_MAX_DELTA,
        reinit_after_ns: int | None = DEFAULT_REINIT_AFTER_NS,
        stats: E2EStats | None = None,
        frame_length: int = FRAME_LENGTH,
        authenticate: Callable[[int, int, bytes], str | None] | None = None,
    ) -> None:
        if not 1 <= max_delta < COUNTER_MODULO:
            raise HalCodecError(f"max_delta must be in 1..{COUNTER_MODULO - 1}, got {max_delta}")
        self._rx = dict(rx_ids)
        self._ignore = frozenset(ignore_ids)
        self.max_delta = max_delta
        self.reinit_after_ns = reinit_after_ns
        self.stats = stats if stats is not None else E2EStats()
        self.frame_length = frame_length
        self.authenticate = authenticate
        """``(frame_id, data_id, data) -> None | verdict name``, checked after the length and
        before the CRC (SecOC, :class:`hal.secoc.SecOCVerifier`): a frame that is not authentic
        never touches the counter state."""
        self._last: dict[int, tuple[int, int]] = {}  # frame id -> (counter, t_ns)

    def reset(self) -> None:
        """Forget every counter (the next frame of each id is accepted as a first frame)."""
        self._last.clear()

    def check(self, msg: can.Message, t_ns: int) -> Verdict:
        """Verdict for one received frame; updates the counter state; never raises."""
        verdict, gap = self._verdict(msg, t_ns)
        if verdict is not Verdict.OK:
            self.stats.record(verdict)
        elif gap:
            self.stats.lost += gap
        return verdict

    def _verdict(self, msg: can.Message, t_ns: int) -> tuple[Verdict, int]:
        if msg.is_error_frame:
            return Verdict.ERROR_FRAME, 0
        frame_id = msg.arbitration_id
        data_id = None if msg.is_extended_id else self._rx.get(frame_id)
        if data_id is None:
            if not msg.is_extended_id and frame_id in self._ignore:
                return Verdict.IGNORED, 0
            return Verdict.UNKNOWN_ID, 0
        data = msg.data
        if msg.is_remote_frame or data is None or len(data) != self.frame_length:
            return Verdict.WRONG_LENGTH, 0
        if self.authenticate is not None:
            failed = self.authenticate(frame_id, data_id, data)
            if failed is not None:
                return Verdict(failed), 0
        if e2e_crc(data_id, data) != data[0]:
            return Verdict.BAD_CRC, 0
        counter = data[1] & 0x0F
        last = self._last.get(frame_id)
        self._last[frame_id] = (counter, t_ns)
        if last is None:
            return Verdict.OK, 0
        last_counter, last_t = last
        if self.reinit_after_ns is not None and t_ns - last_t > self.reinit_after_ns:
            return Verdict.OK, 0
        delta = (counter - last_counter) % COUNTER_MODULO
        if delta == 0:
            self._last[frame_id] = last  # a repeat does not refresh the silence timer
            return Verdict.REPEATED_COUNTER, 0
        if delta > self.max_delta:
            return Verdict.COUNTER_JUMP, 0
        return Verdict.OK, delta - 1
