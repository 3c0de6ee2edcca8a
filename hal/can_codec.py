"""Typed CAN frames of the HIL rig, encoded and decoded with cantools from ``hal/hil.dbc``.

The DBC is the single source of truth: ids, signal layouts, scalings, directions (the DBC's
transmitter and receiver nodes ``Controller`` and ``DSP``) and E2E data ids (message attribute
``E2EDataID``) all come from it. This module adds typed dataclasses and the E2E protection of
:mod:`hal.e2e`:

* :class:`ControllerCodec` is the controller's side (sends :class:`TorqueCommand` and
  :class:`DspControl`, receives joint state, :class:`DspStatus` and :class:`Sync`);
* :class:`DspCodec` is the DSP's side (the emulated DSP node calls only these functions).

``decode`` never raises for a bad frame: it returns ``None`` and counts the verdict.
Physical values outside a signal's range are saturated to it on encode; NaN or infinite values
raise :class:`~hal.errors.HalCodecError` (a command is never silently invented).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage

from hal.drive_state import DriveState, DspCommand, FaultReason
from hal.e2e import (
    DEFAULT_MAX_DELTA,
    DEFAULT_REINIT_AFTER_NS,
    FRAME_LENGTH,
    E2EReceiver,
    E2ESender,
    E2EStats,
    Verdict,
)
from hal.errors import HalCodecError
from hal.secoc import (
    DEFAULT_MAX_AGE_US,
    DEFAULT_MAX_SKEW_US,
    TRAILER_BYTES,
    SecOCSigner,
    SecOCVerifier,
    rig_key,
)

DBC_PATH = Path(__file__).with_name("hil.dbc")
CONTROLLER = "Controller"
DSP = "DSP"
E2E_SIGNALS = ("CRC", "Counter")
SECOC_SIGNALS = ("Freshness", "Mac")
FD_FRAME_LENGTH = FRAME_LENGTH + TRAILER_BYTES
"""Every message: 8 E2E-protected bytes + SecOC trailer (freshness, MAC) = a 16-byte CAN FD
frame."""

STRICT_SIGNALS = frozenset({"Q1", "Q2", "Dq1", "Dq2"})
"""Measurements that are never saturated on encode: a value beyond the signal's range raises
:class:`~hal.errors.HalCodecError` (a pinned joint angle or speed would lie to the controller;
the DSP faults with FaultReason ENCODER instead)."""

ENCODER_COUNTS_PER_REV = 1 << 20
RAD_PER_COUNT = 2.0 * math.pi / ENCODER_COUNTS_PER_REV
RELEASE_DELAY_SATURATED = 0xFFFF
"""Realtime ``TorqueCommand.Tick``: microseconds from the controller's release to the frame;
this value means "this long or more" (the DSP then does not learn the phase from it)."""
"""Resolution of the joint-angle signals Q1/Q2 (20-bit direct-drive encoder)."""


# --------------------------------------------------------------------------- typed frames


@dataclass(frozen=True, slots=True)
class TorqueCommand:
    """Controller -> DSP torque command (N·m). ``tick``: in lockstep the Sync period it answers
    (low 16 bits); in realtime the microseconds from the controller's release to this frame
    (:data:`RELEASE_DELAY_SATURATED` and above saturate)."""

    tau1: float
    tau2: float
    enable: bool = True
    tick: int = 0


@dataclass(frozen=True, slots=True)
class DspControl:
    """Controller -> DSP event command (the drive state machine, :mod:`hal.drive_state`)."""

    command: DspCommand


@dataclass(frozen=True, slots=True)
class JointPosition:
    """DSP -> controller joint angles (rad); ``sample`` is the DSP sample index mod 16."""

    q1: float
    q2: float
    sample: int = 0


@dataclass(frozen=True, slots=True)
class JointVelocity:
    """DSP -> controller joint velocities (rad/s); ``sample`` pairs it with a JointPosition."""

    dq1: float
    dq2: float
    sample: int = 0


@dataclass(frozen=True, slots=True)
class DspStatus:
    """DSP -> controller status flags, counters and drive state (see :mod:`hal.drive_state`).

    ``drive_state`` / ``fault_reason`` default to what the legacy flags imply (TorqueEnabled ->
    OPERATION_ENABLED, WatchdogTripped -> FAULT/WATCHDOG, else SWITCH_ON_DISABLED), so a status
    built from the flags alone round-trips. ``session`` is the DSP process's random id (0 =
    unknown); ``tick`` is carried mod 4096, ``watchdog_trips`` saturates at 15.
    """

    torque_enabled: bool
    watchdog_tripped: bool
    torque_saturated: bool = False
    lockstep: bool = False
    rejected_frames: int = 0
    watchdog_trips: int = 0
    tick: int = 0
    drive_state: DriveState | None = None
    fault_reason: FaultReason | None = None
    session: int = 0

    def __post_init__(self) -> None:
        state = self.drive_state
        if state is None:
            if self.watchdog_tripped:
                state = DriveState.FAULT
            elif self.torque_enabled:
                state = DriveState.OPERATION_ENABLED
            else:
                state = DriveState.SWITCH_ON_DISABLED
        object.__setattr__(self, "drive_state", DriveState(state))
        reason = self.fault_reason
        if reason is None:
            reason = (
                FaultReason.WATCHDOG
                if self.watchdog_tripped and state is DriveState.FAULT
                else FaultReason.NONE
            )
        object.__setattr__(self, "fault_reason", FaultReason(reason))

    @property
    def fault(self) -> bool:
        return self.drive_state is DriveState.FAULT


@dataclass(frozen=True, slots=True)
class Sync:
    """DSP -> controller lockstep clock: control period index ``tick``."""

    tick: int


@dataclass(frozen=True, slots=True)
class JointState:
    """One DSP sample of both joints, as the controller sees it.

    ``t_ns`` is the ``time.monotonic_ns()`` at which the second frame of the pair arrived.
    """

    q: tuple[float, float]
    dq: tuple[float, float]
    sample: int
    t_ns: int

    def age_s(self, now_ns: int | None = None) -> float:
        """Seconds since this state was received."""
        now = time.monotonic_ns() if now_ns is None else now_ns
        return (now - self.t_ns) * 1e-9


Frame = TorqueCommand | DspControl | JointPosition | JointVelocity | DspStatus | Sync


# ------------------------------------------------------------------- dataclass <-> signals


def _sat(value: int, limit: int) -> int:
    return max(0, min(int(value), limit))


def _control_signals(f: DspControl) -> dict[str, Any]:
    return {"Command": int(f.command)}


def _control_from(s: dict[str, Any]) -> DspControl:
    return DspControl(DspCommand(s["Command"]))


_TO_SIGNALS: dict[type, tuple[str, Callable[[Any], dict[str, Any]]]] = {
    TorqueCommand: (
        "TorqueCommand",
        lambda f: {
            "Enable": int(bool(f.enable)),
            "Tau1": f.tau1,
            "Tau2": f.tau2,
            "Tick": int(f.tick) & 0xFFFF,
        },
    ),
    DspControl: ("DspControl", lambda f: _control_signals(f)),
    JointPosition: (
        "JointPosition",
        lambda f: {"Sample": int(f.sample) & 0xF, "Q1": f.q1, "Q2": f.q2},
    ),
    JointVelocity: (
        "JointVelocity",
        lambda f: {"Sample": int(f.sample) & 0xF, "Dq1": f.dq1, "Dq2": f.dq2},
    ),
    DspStatus: (
        "DspStatus",
        lambda f: {
            "TorqueEnabled": int(bool(f.torque_enabled)),
            "WatchdogTripped": int(bool(f.watchdog_tripped)),
            "TorqueSaturated": int(bool(f.torque_saturated)),
            "Lockstep": int(bool(f.lockstep)),
            "RejectedFrames": _sat(f.rejected_frames, 255),
            "DriveState": int(f.drive_state),
            "FaultReason": int(f.fault_reason),
            "Session": int(f.session) & 0xFFFF,
            "WatchdogTrips": _sat(f.watchdog_trips, 15),
            "Tick": int(f.tick) & 0xFFF,
        },
    ),
    Sync: ("Sync", lambda f: {"Tick": int(f.tick) & 0xFFFFFFFF}),
}

_FROM_SIGNALS: dict[str, Callable[[dict[str, Any]], Frame]] = {
    "TorqueCommand": lambda s: TorqueCommand(s["Tau1"], s["Tau2"], bool(s["Enable"]), s["Tick"]),
    "DspControl": lambda s: _control_from(s),
    "JointPosition": lambda s: JointPosition(s["Q1"], s["Q2"], s["Sample"]),
    "JointVelocity": lambda s: JointVelocity(s["Dq1"], s["Dq2"], s["Sample"]),
    "DspStatus": lambda s: DspStatus(
        bool(s["TorqueEnabled"]),
        bool(s["WatchdogTripped"]),
        bool(s["TorqueSaturated"]),
        bool(s["Lockstep"]),
        s["RejectedFrames"],
        s["WatchdogTrips"],
        s["Tick"],
        DriveState(s["DriveState"]),
        FaultReason(s["FaultReason"]),
        s["Session"],
    ),
    "Sync": lambda s: Sync(s["Tick"]),
}


# ------------------------------------------------------------------------------- database


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
        for _cls, (name, _fn) in _TO_SIGNALS.items():
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


# ------------------------------------------------------------------------------- endpoints


class CanEndpoint:
    """One node's end of the link: protected encode of what it sends, checked decode of the rest.

    Every frame is authenticated (:mod:`hal.secoc`) with ``key``, the rig key (default:
    :func:`~hal.secoc.rig_key`: ``$HIL_KEY_FILE``, else this process's ephemeral key, so only
    endpoints of this process understand each other). ``verify=False`` skips the
    authentication checks on receive (offline tools reading a log whose key is gone); sending
    always signs.

    Not thread-safe per direction: call :meth:`encode` from one thread (or under a lock) and
    :meth:`decode` from one thread (the one that reads the bus); the two directions are independent.
    """

    def __init__(
        self,
        node: str,
        *,
        max_delta: int = DEFAULT_MAX_DELTA,
        reinit_after_s: float | None = DEFAULT_REINIT_AFTER_NS * 1e-9,
        database: HilDatabase | None = None,
        key: bytes | None = None,
        verify: bool = True,
        max_age_us: int = DEFAULT_MAX_AGE_US,
        max_skew_us: int = DEFAULT_MAX_SKEW_US,
    ) -> None:
        self.node = node
        self.database = database or load_database()
        self._tx = {s.name: s for s in self.database.sent_by(node)}
        rx = self.database.received_by(node)
        if not self._tx and not rx:
            raise HalCodecError(f"node {node!r} is not in {DBC_PATH.name}")
        self._rx = {s.frame_id: s for s in rx}
        self._sender = E2ESender()
        key = rig_key() if key is None else key
        self._signer = SecOCSigner(key, node)
        peers = {n for s in rx for n in s.message.senders}
        verifiers = {
            peer: SecOCVerifier(
                key, peer, max_age_us=max_age_us, max_skew_us=max_skew_us, verify=verify
            )
            for peer in peers
        }
        self._verifier_of = {s.frame_id: verifiers[s.message.senders[0]] for s in rx}
        self._rx_us: int | None = None
        """The receive stamp of the frame being decoded (microseconds, wall clock)."""
        reinit_ns = None if reinit_after_s is None else round(reinit_after_s * 1e9)
        self.receiver = E2EReceiver(
            {s.frame_id: s.data_id for s in rx},
            ignore_ids=[s.frame_id for s in self._tx.values()],
            max_delta=max_delta,
            reinit_after_ns=reinit_ns,
            frame_length=FD_FRAME_LENGTH,
            authenticate=self._authenticate,
        )

    def _authenticate(self, frame_id: int, data_id: int, data: bytes) -> str | None:
        return self._verifier_of[frame_id].check(frame_id, data_id, data, self._rx_us)

    def sign(self, msg: can.Message) -> can.Message:
        """``msg`` (a frame of this node, e.g. from a log) with a fresh SecOC trailer of this
        endpoint's key: bytes 0..7 (E2E CRC and counter included) as they were."""
        spec = next((s for s in self._tx.values() if s.frame_id == msg.arbitration_id), None)
        if spec is None or msg.data is None or len(msg.data) < FRAME_LENGTH:
            raise HalCodecError(f"{self.node} does not send frame id {msg.arbitration_id:#x}")
        data = self._signer.sign(spec.data_id, bytes(msg.data[:FRAME_LENGTH]))
        return can.Message(
            arbitration_id=spec.frame_id, is_extended_id=False, is_fd=True, data=data, check=False
        )

    @property
    def stats(self) -> E2EStats:
        """A snapshot of the receive counters."""
        return self.receiver.stats.copy()

    def encode(self, frame: Frame) -> can.Message:
        """A protected ``can.Message`` for ``frame`` (advances that message's rolling counter)."""
        try:
            name, to_signals = _TO_SIGNALS[type(frame)]
        except KeyError:
            raise HalCodecError(f"cannot encode {type(frame).__name__!r} as a CAN frame") from None
        spec = self._tx.get(name)
        if spec is None:
            raise HalCodecError(f"{self.node} does not send {name} (see {DBC_PATH.name})")
        signals = to_signals(frame)
        for sig, lo, hi in spec.clamps:
            value = float(signals[sig])
            if not math.isfinite(value):
                raise HalCodecError(f"{name}.{sig} must be finite, got {value!r}")
            if sig in STRICT_SIGNALS and not lo <= value <= hi:
                raise HalCodecError(f"{name}.{sig} = {value!r} is beyond the frame's [{lo}, {hi}]")
            signals[sig] = lo if value < lo else hi if value > hi else value
        signals["CRC"] = signals["Counter"] = 0
        head = self._sender.protect(spec.data_id, bytearray(spec.packer.encode(signals)))
        return can.Message(
            arbitration_id=spec.frame_id,
            is_extended_id=False,
            is_fd=True,
            data=self._signer.sign(spec.data_id, head),
            check=False,
        )

    def decode(self, msg: can.Message, t_ns: int | None = None) -> Frame | None:
        """The typed frame, or ``None`` for a rejected or ignored frame (counted in :attr:`stats`).

        ``t_ns`` is the receive time (``time.monotonic_ns()`` when omitted); it only matters for
        the re-initialisation of a counter after a long silence.
        """
        stats = self.receiver.stats
        try:
            now = time.monotonic_ns() if t_ns is None else t_ns
            # freshness is judged at the bus's receive stamp (wall clock), see SecOCVerifier
            self._rx_us = int(msg.timestamp * 1e6) if msg.timestamp else None
            if self.receiver.check(msg, now) is not Verdict.OK:
                return None
            spec = self._rx[msg.arbitration_id]
            frame = _FROM_SIGNALS[spec.name](spec.packer.decode(msg.data))
        except Exception:  # a bad frame must never escape the receive path
            stats.record(Verdict.DECODE_ERROR)
            return None
        stats.accepted += 1
        return frame


class ControllerCodec(CanEndpoint):
    """The controller's side: sends torque and control commands, decodes the DSP's frames."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(CONTROLLER, **kwargs)

    def encode_torque(
        self, tau1: float, tau2: float, *, enable: bool = True, tick: int = 0
    ) -> can.Message:
        return self.encode(TorqueCommand(tau1, tau2, enable, tick))

    def encode_control(self, command: DspCommand) -> can.Message:
        return self.encode(DspControl(DspCommand(command)))


class DspCodec(CanEndpoint):
    """The DSP's side: decodes torque and control commands, encodes state, status and Sync."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(DSP, **kwargs)

    def decode_command(
        self, msg: can.Message, t_ns: int | None = None
    ) -> TorqueCommand | DspControl | None:
        """A valid :class:`TorqueCommand` or :class:`DspControl`, else ``None`` (counted)."""
        frame = self.decode(msg, t_ns)
        return frame if isinstance(frame, TorqueCommand | DspControl) else None

    def encode_state(
        self, q: tuple[float, float], dq: tuple[float, float], sample: int
    ) -> tuple[can.Message, can.Message]:
        """JointPosition and JointVelocity of one sample (send them in this order)."""
        return (
            self.encode(JointPosition(q[0], q[1], sample)),
            self.encode(JointVelocity(dq[0], dq[1], sample)),
        )

    def encode_status(self, status: DspStatus) -> can.Message:
        return self.encode(status)

    def encode_sync(self, tick: int) -> can.Message:
        return self.encode(Sync(tick))


def bench_codec(n: int = 10_000) -> dict[str, float]:
    """Mean microseconds per call of the 1 kHz hot paths (for ``hil bench``; no assertions).

    ``encode_state``/``decode_state`` handle the JointPosition + JointVelocity pair of one
    sample; ``*_torque`` one TorqueCommand.
    """
    dsp, ctl = DspCodec(), ControllerCodec()
    states = [dsp.encode_state((0.5, -0.5), (0.1, -0.2), i) for i in range(n)]
    torques = [ctl.encode_torque(1.0, -0.5, tick=i) for i in range(n)]
    out: dict[str, float] = {}

    def timed(name: str, fn: Callable[[int], object]) -> None:
        t0 = time.perf_counter_ns()
        for i in range(n):
            fn(i)
        out[name] = (time.perf_counter_ns() - t0) / n / 1e3

    timed("encode_torque_us", lambda i: ctl.encode_torque(1.0, -0.5, tick=i))
    timed("decode_torque_us", lambda i: dsp.decode(torques[i], i))
    timed("encode_state_us", lambda i: dsp.encode_state((0.5, -0.5), (0.1, -0.2), i))
    timed("decode_state_us", lambda i: (ctl.decode(states[i][0], i), ctl.decode(states[i][1], i)))
    return out
