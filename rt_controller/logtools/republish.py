"""Play a log's recorded raw inputs back onto CAN and zenoh (``hil replay --republish``).

What the controller received is sent again, in the recorded order and at the recorded timing
(receive times ``t_ns``, divided by ``speed``; ``speed=0`` sends as fast as possible), so a live
``hil controller`` can be fed a recorded run:

* ``/hal/can/rx`` frames (joint state, DSP status, Sync, as the DSP sent them) go onto the CAN
  bus with arbitration id, flags and the E2E-protected bytes 0..7 as recorded (the rolling
  counters and CRCs are the original ones) and a new SecOC trailer (bytes 8..15: fresh freshness
  value and MAC with the live rig's ``key``, :mod:`hal.secoc`): the recorded trailer was made
  with the key of the recorded run and carries freshness values a live receiver has seen pass.
  Frames the controller itself sends (``TorqueCommand``, ``DspControl``: seen when a bus
  echoes them) and error frames are skipped.
* ``/vision/features`` payloads go onto zenoh key ``hil/vision/features``. Lockstep messages are
  judged by simulation time and keep their stamps. Realtime messages carry a capture stamp
  (``stamp_ns``, monotonic) that a live controller checks for staleness, so they are
  **re-stamped**: decoded, ``stamp_ns`` shifted by the replay offset of that message
  (its send time minus its recorded receive time), re-encoded. Each message therefore arrives
  exactly as old as it was when it was recorded. Every payload is re-signed with the live rig's
  key (its MAC covers the stamp). Undecodable payloads are sent as recorded.

The zenoh session defaults to ``listen=None``: the hub if the endpoint's port is free (nothing
else of the rig is running), else a client of the running hub. Before the first message the
player waits up to ``wait_subscriber_s`` for a subscriber on the features key, then
``lead_in_s`` more for the controller's CAN client (a controller started after the player
would otherwise miss the start of the run).

Feeding a live controller: nothing answers its torque, and the recorded timing of a lockstep
run is the pace the original controller kept (often 20x real time); a lockstep controller
takes the newest Sync when it falls behind, so give it slack with ``speed`` < 1 when every
tick matters. A realtime log is best played at ``speed=1``.
"""

from __future__ import annotations

import base64
import contextlib
import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from hal.can_codec import DspCodec
from hal.can_database import CONTROLLER, load_database
from hal.config import RigConfig
from hal.errors import HalCodecError, HalConfigError
from hal.secoc import rig_key
from hal.vision_codec import decode_features, encode_features
from rt_controller.logtools.reader import LoadedLog, read_log

_CAN, _VISION = 0, 1
WAIT_SUBSCRIBER_S = 10.0
LEAD_IN_S = 0.5
"""Pause between the subscriber appearing and the first message (the controller opens its CAN
client right after its zenoh subscriber, and nothing on CAN says when it is listening)."""


@dataclass
class RepublishResult:
    """What :func:`republish_log` sent."""

    path: Path
    speed: float
    can_frames: int = 0
    payloads: int = 0
    restamped: int = 0
    """Realtime vision payloads sent with a shifted capture stamp."""
    skipped: int = 0
    """Recorded frames not sent: the controller's own frames and error frames."""
    send_errors: int = 0
    duration_s: float = 0.0
    stopped: bool = False
    """Playback was interrupted by the stop event."""
    truncated: bool = False
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """The JSON object of ``hil replay --republish --json``."""
        return {
            "log": str(self.path),
            "speed": self.speed,
            "can_frames": self.can_frames,
            "payloads": self.payloads,
            "restamped": self.restamped,
            "skipped": self.skipped,
            "send_errors": self.send_errors,
            "duration_s": self.duration_s,
            "stopped": self.stopped,
            "truncated": self.truncated,
            "notes": list(self.notes),
        }


def _controller_ids() -> set[int]:
    return {spec.frame_id for spec in load_database().sent_by(CONTROLLER)}


def can_message(rec: dict[str, Any]) -> can.Message:
    """The recorded ``hil.CanFrame`` dict as a python-can message (data bytes unchanged)."""
    return can.Message(
        arbitration_id=int(rec["arbitration_id"]),
        is_extended_id=bool(rec.get("is_extended_id", False)),
        is_remote_frame=bool(rec.get("is_remote_frame", False)),
        is_fd=bool(rec.get("is_fd", False)),
        bitrate_switch=bool(rec.get("bitrate_switch", False)),
        data=bytes.fromhex(rec.get("data", "")),
        check=False,
    )


def restamp(payload: bytes, shift_ns: int, key: bytes | None = None) -> tuple[bytes, bool]:
    """``(payload to send, restamped)``: a realtime features payload with ``stamp_ns`` shifted
    by ``shift_ns``, a lockstep one unchanged, both signed with ``key`` (default: this process's
    ephemeral key); an undecodable payload as recorded."""
    try:
        msg = decode_features(payload)
        if msg.lockstep:
            return encode_features(msg, key), False
        return encode_features(msg._replace(stamp_ns=msg.stamp_ns + shift_ns), key), True
    except HalCodecError:
        return payload, False


def playback_events(log: LoadedLog, result: RepublishResult) -> list[tuple[int, int, Any]]:
    """``(t_ns, kind, payload)`` of every input to send, in recorded receive order."""
    own = _controller_ids()
    events: list[tuple[int, int, int, Any]] = []
    for i, rec in enumerate(log.can_rx):
        if rec.get("is_error_frame") or int(rec["arbitration_id"]) in own:
            result.skipped += 1
            continue
        events.append((int(rec["t_ns"]), _CAN, i, can_message(rec)))
    for i, rec in enumerate(log.vision):
        events.append((int(rec["t_ns"]), _VISION, i, base64.b64decode(rec.get("data", ""))))
    events.sort(key=lambda e: (e[0], e[1], e[2]))
    return [(t, kind, obj) for t, kind, _, obj in events]


def republish_log(
    path: str | Path,
    *,
    speed: float = 1.0,
    can_spec: str | None = None,
    zenoh_endpoint: str | None = None,
    zenoh_config: str | None = None,
    listen: bool | None = None,
    cfg: RigConfig | None = None,
    wait_subscriber_s: float = WAIT_SUBSCRIBER_S,
    lead_in_s: float = LEAD_IN_S,
    stop: threading.Event | None = None,
    key: bytes | None = None,
) -> RepublishResult:
    """Send the raw inputs recorded in ``path`` onto CAN and zenoh (see the module docstring).

    Transports default to the log's configuration (``transport.can``, ``zenoh_endpoint``,
    ``zenoh_config``), else ``cfg``, else the embedded defaults; a bus or session is only opened
    when the log has something to send on it. Playback starts ``lead_in_s`` after the features
    subscriber appeared (or after ``wait_subscriber_s`` without one, or at once when both are
    0). ``stop`` ends the playback early. ``key``: the live rig's key that CAN frames and
    features are re-signed with (default: ``cfg.transport.key_file`` of the ``cfg`` given, else
    this process's ephemeral key; never the log's, whose run is over). Raises
    :class:`~rt_controller.errors.LogError` for a bad file and :class:`~hal.errors.HalError`
    for a transport that cannot be opened.
    """
    from hal.bus import open_bus
    from hal.zenoh_session import KEY_FEATURES, open_session

    if not speed >= 0:
        raise HalConfigError(f"--speed must be non-negative (0 = as fast as possible), got {speed}")
    stop = stop or threading.Event()
    key = key if key is not None else rig_key(cfg)
    log = read_log(path)
    cfg = cfg or log.config or RigConfig()
    result = RepublishResult(Path(path), speed, truncated=log.truncated, notes=list(log.notes))
    events = playback_events(log, result)
    if not events:
        why = "it is cut or damaged before any" if log.truncated else "recorded with --no-raw?"
        result.notes.append(f"the log holds no raw inputs ({why})")
        return result
    with ExitStack() as stack:
        bus = publisher = None
        if any(kind == _CAN for _, kind, _ in events):
            bus = open_bus(can_spec or cfg.transport.can)
            stack.callback(bus.shutdown)
        if any(kind == _VISION for _, kind, _ in events):
            session = open_session(
                cfg,
                listen=listen,
                endpoint=zenoh_endpoint,
                config_file=zenoh_config,
                stop_event=stop,
            )
            stack.callback(session.close)
            publisher = session.publisher(KEY_FEATURES, block=True)
            if wait_subscriber_s > 0 and not session.has_subscriber(
                publisher, wait_subscriber_s, stop
            ):
                result.notes.append(
                    f"no subscriber on {KEY_FEATURES} after {wait_subscriber_s:g} s; "
                    "published anyway"
                )
        if lead_in_s > 0 and stop.wait(lead_in_s):
            result.stopped = True
            return result
        _play(events, bus, publisher, speed, stop, result, DspCodec(key=key), key)
    return result


def _play(
    events: list[tuple[int, int, Any]],
    bus: can.BusABC | None,
    publisher: Any,
    speed: float,
    stop: threading.Event,
    result: RepublishResult,
    signer: DspCodec,
    key: bytes,
) -> None:
    t0 = events[0][0]
    start = time.monotonic_ns()
    for t_ns, kind, obj in events:
        if stop.is_set():
            result.stopped = True
            break
        if speed > 0:
            wait_ns = start + (t_ns - t0) / speed - time.monotonic_ns()
            if wait_ns > 0 and stop.wait(wait_ns / 1e9):
                result.stopped = True
                break
        if kind == _CAN:
            with contextlib.suppress(HalCodecError):  # not a DSP frame: sent as recorded
                obj = signer.sign(obj)
            try:
                bus.send(obj, timeout=0.05)
                result.can_frames += 1
            except (can.CanError, OSError):
                result.send_errors += 1
            continue
        payload, shifted = restamp(obj, time.monotonic_ns() - t_ns, key)
        result.restamped += shifted
        publisher.put(payload)
        result.payloads += 1
    result.duration_s = (time.monotonic_ns() - start) / 1e9
    if result.send_errors:
        result.notes.append(f"{result.send_errors} CAN frame(s) could not be sent")
