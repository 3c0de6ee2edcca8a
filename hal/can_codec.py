"""Typed CAN frames of the HIL rig, encoded and decoded with cantools from ``hal/hil.dbc``.

The DBC is the single source of truth: ids, signal layouts, scalings, directions (the DBC's
transmitter and receiver nodes ``Controller`` and ``DSP``) and E2E data ids (message attribute
``E2EDataID``) all come from it (:mod:`hal.can_database`). This module encodes and decodes the
typed frames of :mod:`hal.can_frames` with the E2E protection of :mod:`hal.e2e` and the SecOC
trailer of :mod:`hal.secoc`:

* :class:`ControllerCodec` is the controller's side (sends :class:`TorqueCommand` and
  :class:`DspControl`, receives joint state, :class:`DspStatus` and :class:`Sync`);
* :class:`DspCodec` is the DSP's side (the emulated DSP node calls only these functions).

``decode`` never raises for a bad frame: it returns ``None`` and counts the verdict.
Physical values outside a signal's range are saturated to it on encode; NaN or infinite values
raise :class:`~hal.errors.HalCodecError` (a command is never silently invented).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import can

from hal.can_database import CONTROLLER, DBC_PATH, DSP, FD_FRAME_LENGTH, HilDatabase, load_database
from hal.can_frames import (
    FROM_SIGNALS,
    STRICT_SIGNALS,
    TO_SIGNALS,
    DspControl,
    DspStatus,
    Frame,
    JointPosition,
    JointVelocity,
    Sync,
    TorqueCommand,
)
from hal.drive_state import DspCommand
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
    SecOCSigner,
    SecOCVerifier,
    rig_key,
)


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
            name, to_signals = TO_SIGNALS[type(frame)]
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
            frame = FROM_SIGNALS[spec.name](spec.packer.decode(msg.data))
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
