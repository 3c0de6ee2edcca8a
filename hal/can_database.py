"""The rig's CAN database ``hal/hil.dbc``, loaded once with cantools and validated (E2E and
SecOC layout, data ids), with each message's run-time packer (:class:`HeadPacker`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage

from hal.can_frames import TO_SIGNALS
from hal.e2e import FRAME_LENGTH
from hal.errors import HalCodecError
from hal.secoc import TRAILER_BYTES

DBC_PATH = Path(__file__).with_name("hil.dbc")
CONTROLLER = "Controller"
DSP = "DSP"
E2E_SIGNALS = ("CRC", "Counter")
SECOC_SIGNALS = ("Freshness", "Mac")
FD_FRAME_LENGTH = FRAME_LENGTH + TRAILER_BYTES
"""Every message: 8 E2E-protected bytes + SecOC trailer (freshness, MAC) = a 16-byte CAN FD
frame."""


class HeadPacker:
    """Bytes 0..7 of one message <-> its physical signal values, compiled once from the DBC:
    every signal is Intel byte order inside one 64-bit little-endian word, so a frame is one
    integer, shifts and masks. Equal to cantools' ``encode(..., scaling=True)`` and
    ``decode_simple(..., scaling=True, decode_choices=False)`` on these messages (the test
    suite compares the two on random values), at a fraction of the cost on the 1 kHz path.

    Encoding: raw = round((value - offset) / scale) for a scaled signal, round(value) for an
    integer one; a raw value that does not fit its bits raises :class:`HalCodecError`.
    Decoding: raw * scale + offset (a float) for a scaled signal, the raw int otherwise.
    """

    def __init__(self, message: DbcMessage) -> None:
        self.name = message.name
        enc, dec = [], []
        for sig in message.signals:
            kind = type(sig.conversion).__name__
            if kind == "NamedSignalConversion":
                kind = type(sig.conversion._conversion).__name__
            if kind not in ("IdentityConversion", "LinearConversion"):
                raise HalCodecError(f"{message.name}.{sig.name}: unsupported conversion {kind}")
            if sig.byte_order != "little_endian" or sig.start + sig.length > 64:
                raise HalCodecError(f"{message.name}.{sig.name}: not an Intel signal in bytes 0..7")
            if getattr(sig.conversion, "is_float", False):
                raise HalCodecError(f"{message.name}.{sig.name}: float signals are not supported")
            mask = (1 << sig.length) - 1
            lo, hi = (
                (-(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1)
                if sig.is_signed
                else (0, mask)
            )
            linear = kind == "LinearConversion"
            scale, offset = float(sig.scale), float(sig.offset)
            enc.append((sig.name, sig.start, mask, lo, hi, linear, scale, offset))
            sign = 1 << (sig.length - 1) if sig.is_signed else 0
            dec.append((sig.name, sig.start, mask, sign, linear, scale, offset))
        self._enc = tuple(enc)
        self._dec = tuple(dec)

    def encode(self, signals: dict[str, Any]) -> bytes:
        """The 8 bytes of ``signals`` (every signal of the message must be given)."""
        word = 0
        for name, shift, mask, lo, hi, linear, scale, offset in self._enc:
            value = signals[name]
            try:
                raw = round((value - offset) / scale) if linear else round(value)
            except (TypeError, ValueError, OverflowError) as exc:
                raise HalCodecError(f"cannot encode {self.name}.{name} = {value!r}") from exc
            if not lo <= raw <= hi:
                raise HalCodecError(f"{self.name}.{name}: raw value {raw} does not fit its bits")
            word |= (raw & mask) << shift
        return word.to_bytes(FRAME_LENGTH, "little")

    def decode(self, data: bytes | bytearray) -> dict[str, Any]:
        """The signals of the first 8 bytes of ``data``."""
        word = int.from_bytes(data[:FRAME_LENGTH], "little")
        out: dict[str, Any] = {}
        for name, shift, mask, sign, linear, scale, offset in self._dec:
            raw = (word >> shift) & mask
            if raw & sign:
                raw -= mask + 1
            out[name] = raw * scale + offset if linear else raw
        return out


@dataclass(frozen=True)
class MessageSpec:
    """One DBC message with what the codec needs at run time."""

    message: DbcMessage
    data_id: int
    clamps: tuple[tuple[str, float, float], ...]
    """(signal, lowest, highest) physical value of every scaled (non-integer) signal."""

    @functools.cached_property
    def head(self) -> DbcMessage:
        """The message's bytes 0..7 alone (E2E header and signals, no SecOC trailer): what the
        codec encodes and decodes with cantools, the trailer being :mod:`hal.secoc`'s."""
        m = self.message
        return DbcMessage(
            frame_id=m.frame_id,
            name=m.name,
            length=FRAME_LENGTH,
            signals=[s for s in m.signals if s.name not in SECOC_SIGNALS],
            senders=m.senders,
            strict=False,
        )

    @functools.cached_property
    def packer(self) -> HeadPacker:
        """:attr:`head` compiled for the run-time path (:class:`HeadPacker`)."""
        return HeadPacker(self.head)

    @property
    def name(self) -> str:
        return self.message.name

    @property
    def frame_id(self) -> int:
        return self.message.frame_id


def _clamps(msg: DbcMessage) -> tuple[tuple[str, float, float], ...]:
    out = []
    for sig in msg.signals:
        if (
            sig.name in E2E_SIGNALS
            or sig.name in SECOC_SIGNALS
            or (sig.scale == 1 and sig.offset == 0)
        ):
            continue
        raw_lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
        raw_hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
        out.append((sig.name, raw_lo * sig.scale + sig.offset, raw_hi * sig.scale + sig.offset))
    return tuple(out)


def _validate_e2e_layout(msg: DbcMessage) -> int:
    """Check that ``msg`` carries CRC/Counter where :mod:`hal.e2e` expects them; its data id."""
    where = f"{DBC_PATH.name}: message {msg.name}"
    if msg.length != FD_FRAME_LENGTH or msg.is_extended_frame or not msg.is_fd:
        raise HalCodecError(f"{where}: must be a 16-byte CAN FD frame with an 11-bit id")
    layout = {s.name: (s.start, s.length, s.byte_order, s.is_signed) for s in msg.signals}
    if layout.get("CRC") != (0, 8, "little_endian", False):
        raise HalCodecError(f"{where}: signal CRC must be unsigned 0|8@1+")
    if layout.get("Counter") != (8, 4, "little_endian", False):
        raise HalCodecError(f"{where}: signal Counter must be unsigned 8|4@1+")
    if layout.get("Freshness") != (64, 32, "little_endian", False):
        raise HalCodecError(f"{where}: signal Freshness must be unsigned 64|32@1+")
    if layout.get("Mac") != (96, 32, "little_endian", False):
        raise HalCodecError(f"{where}: signal Mac must be unsigned 96|32@1+")
    attr = msg.dbc.attributes.get("E2EDataID") if msg.dbc is not None else None
    if attr is None or not 0 < int(attr.value) <= 0xFFFF:
        raise HalCodecError(f"{where}: needs a non-zero E2EDataID attribute")
    return int(attr.value)


class HilDatabase:
    """The loaded DBC, validated, with :class:`MessageSpec` lookups by name and frame id."""

    def __init__(self, path: str | Path = DBC_PATH) -> None:
        try:
            self.db: Database = cantools.database.load_file(str(path))
        except Exception as exc:  # cantools raises several parser errors
            raise HalCodecError(f"cannot load CAN database {path}: {exc}") from exc
        self.by_name: dict[str, MessageSpec] = {}
        self.by_id: dict[int, MessageSpec] = {}
        data_ids: dict[int, str] = {}
        for msg in self.db.messages:
            data_id = _validate_e2e_layout(msg)
            if data_id in data_ids:
                raise HalCodecError(
                    f"{path}: E2EDataID {data_id:#06x} used by {data_ids[data_id]} and {msg.name}"
                )
            data_ids[data_id] = msg.name
            spec = MessageSpec(msg, data_id, _clamps(msg))
            self.by_name[msg.name] = spec
            self.by_id[msg.frame_id] = spec
        for _cls, (name, _fn) in TO_SIGNALS.items():
            if name not in self.by_name:
                raise HalCodecError(f"{path}: message {name} is missing")

    def sent_by(self, node: str) -> list[MessageSpec]:
        """Messages whose DBC transmitter is ``node``."""
        return [s for s in self.by_name.values() if node in s.message.senders]

    def received_by(self, node: str) -> list[MessageSpec]:
        """Messages that ``node`` receives from another node."""
        return [
            s
            for s in self.by_name.values()
            if node in s.message.receivers and node not in s.message.senders
        ]


def signal_range(message: str, signal: str) -> tuple[float, float]:
    """Lowest and highest physical value the DBC signal can carry (scaled signals only)."""
    for sig, lo, hi in load_database().by_name[message].clamps:
        if sig == signal:
            return lo, hi
    raise HalCodecError(f"{message}.{signal} is not a scaled signal of {DBC_PATH.name}")


@functools.cache
def load_database() -> HilDatabase:
    """The rig's database from :data:`DBC_PATH`, loaded and validated once per process."""
    return HilDatabase(DBC_PATH)
