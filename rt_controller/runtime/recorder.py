"""The MCAP log of a run: every controller cycle, the raw CAN frames and vision messages.

:class:`CycleRecorder` encodes each record as JSON and writes it at once with mcap's synchronous
:class:`~mcap.writer.Writer` (zstd chunks); no thread, no queue. In a run it lives in the
recorder's own process (:mod:`rt_controller.runtime.recorder_child`, fed by
:mod:`rt_controller.runtime.recorder_process`); ``hil replay --out`` and tests use it directly.

==================== ======================== ================================================
topic (JSON)         JSON Schema              one message per
==================== ======================== ================================================
``/controller/cycle`` ``hil.ControllerCycle``  tick (fields: ``runtime/cycle_schema.json``)
``/hal/can/rx``       ``hil.CanFrame``         CAN frame received by the controller
``/hal/can/tx``       ``hil.CanFrame``         CAN frame sent by the controller
``/vision/features``  ``hil.VisionPayload``    vision message as received (raw bytes, base64)
``/diagnostics``      ``hil.Diagnostics``      about a second of the run, and its end
==================== ======================== ================================================

``log_time`` is the record's monotonic time shifted to the Unix epoch (the offset is in the
``hil.run`` metadata); ``t_ns`` inside the messages stays the loop's monotonic clock. Extras:
``live`` gets the topic and JSON bytes of each cycle and diagnostics record (published on zenoh
as ``hil/controller/cycle`` and ``.../diagnostics``); ``scene``
(:mod:`rt_controller.monitor.scene`) draws every ``scene.every``-th cycle on protobuf channels
(``/tf``, ``/scene/arm``, ``/camera/...``).

Metadata: ``hil.config`` (key ``json``: :meth:`hal.config.RigConfig.to_json`), ``hil.run`` (law,
rate, clock, start time, host, versions, the caller's ``run_info``) and, at a clean close,
``hil.recorder`` (counters). Durability: the first record ``flush_interval_s`` after the last
flush closes the chunk in progress and flushes the file to the OS (the recorder process also
calls :meth:`CycleRecorder.flush_if_due` while it waits), so a SIGKILLed writer loses about
``flush_interval_s`` at most; finished chunks stay readable
(:func:`rt_controller.logtools.reader.read_log`).
"""

from __future__ import annotations

import base64
import datetime as _dt
import json
import logging
import math
import os
import platform
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.writer import CompressionType, Writer

from hal.config import RigConfig
from rt_controller.calibration.parameters import PARAMETERS_SCHEMA
from rt_controller.errors import LogError
from rt_controller.runtime.diagnostics import DIAGNOSTICS_SCHEMA

log = logging.getLogger(__name__)

CYCLE_TOPIC = "/controller/cycle"
CAN_RX_TOPIC = "/hal/can/rx"
CAN_TX_TOPIC = "/hal/can/tx"
VISION_TOPIC = "/vision/features"
DIAGNOSTICS_TOPIC = "/diagnostics"
PARAMETERS_TOPIC = "/controller/parameters"
CONFIG_METADATA = "hil.config"
RUN_METADATA = "hil.run"
RECORDER_METADATA = "hil.recorder"
SCHEMA_VERSION = "1"

CYCLE, CAN_RX, CAN_TX, VISION, DIAG, PARAMS = 0, 1, 2, 3, 4, 5
"""Record kinds: the first element of a record item ``(kind, t_ns, obj)``
(:meth:`CycleRecorder.write`; small ints, cheap to pickle for the recorder process)."""
TOPICS = {
    CYCLE: CYCLE_TOPIC,
    CAN_RX: CAN_RX_TOPIC,
    CAN_TX: CAN_TX_TOPIC,
    VISION: VISION_TOPIC,
    DIAG: DIAGNOSTICS_TOPIC,
    PARAMS: PARAMETERS_TOPIC,
}
"""The topic of each record kind."""
DIRECTIONS = {"rx": CAN_RX, "tx": CAN_TX}
"""The record kind of a CAN frame by its direction (``record_can``)."""
_SCHEMA_FILE = Path(__file__).with_name("cycle_schema.json")


def cycle_schema() -> dict[str, Any]:
    """The JSON Schema of ``/controller/cycle`` (``rt_controller/runtime/cycle_schema.json``)."""
    return json.loads(_SCHEMA_FILE.read_text(encoding="utf-8"))


CAN_SCHEMA: dict[str, Any] = {
    "title": "hil.CanFrame",
    "description": "A raw CAN frame as received (/hal/can/rx) or sent (/hal/can/tx).",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "time.monotonic_ns() at receive/send"},
        "timestamp": {"type": "number", "description": "python-can Message.timestamp, s"},
        "arbitration_id": {"type": "integer"},
        "is_extended_id": {"type": "boolean"},
        "dlc": {"type": "integer"},
        "data": {"type": "string", "description": "payload bytes as lowercase hex"},
        "is_fd": {"type": "boolean"},
        "bitrate_switch": {"type": "boolean"},
        "is_error_frame": {"type": "boolean"},
        "is_remote_frame": {"type": "boolean"},
        "channel": {"type": "string", "description": "bus channel, empty if unknown"},
    },
    "required": ["t_ns", "arbitration_id", "dlc", "data", "is_fd"],
}

VISION_SCHEMA: dict[str, Any] = {
    "title": "hil.VisionPayload",
    "description": "A vision message (zenoh key hil/vision/features) exactly as received: the "
    "raw payload bytes (decode them with hal's vision codec) and the receive time.",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "time.monotonic_ns() at receive"},
        "size": {"type": "integer", "description": "payload length, bytes"},
        "data": {"type": "string", "contentEncoding": "base64", "description": "raw payload"},
    },
    "required": ["t_ns", "size", "data"],
}


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, bytes | bytearray | memoryview):
        return bytes(obj).hex()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _finite(obj: Any) -> Any:
    """Copy of ``obj`` with NaN/inf replaced by None (JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


def encode_json(obj: Any) -> bytes:
    """Compact JSON; numpy values become lists/scalars, non-finite floats become null."""
    try:
        text = json.dumps(obj, default=_json_default, allow_nan=False, separators=(",", ":"))
    except ValueError:
        text = json.dumps(_finite(obj), default=_json_default, separators=(",", ":"))
    return text.encode()


def _can_dict(t_ns: int, msg: Any) -> dict[str, Any]:
    data = bytes(msg.data)
    channel = getattr(msg, "channel", None)
    return {
        "t_ns": t_ns,
        "timestamp": float(getattr(msg, "timestamp", 0.0) or 0.0),
        "arbitration_id": int(msg.arbitration_id),
        "is_extended_id": bool(getattr(msg, "is_extended_id", False)),
        "dlc": int(getattr(msg, "dlc", len(data))),
        "data": data.hex(),
        "is_fd": bool(getattr(msg, "is_fd", False)),
        "bitrate_switch": bool(getattr(msg, "bitrate_switch", False)),
        "is_error_frame": bool(getattr(msg, "is_error_frame", False)),
        "is_remote_frame": bool(getattr(msg, "is_remote_frame", False)),
        "channel": "" if channel is None else str(channel),
    }


def encode_record(kind: int, t_ns: int, obj: Any) -> bytes:
    """The JSON message of one record item (a cycle without ``t_ns`` gets the item's)."""
    if kind == VISION:
        data = bytes(obj)
        b64 = base64.b64encode(data).decode("ascii")
        return encode_json({"t_ns": t_ns, "size": len(data), "data": b64})
    if kind in (CAN_RX, CAN_TX):
        return encode_json(_can_dict(t_ns, obj))
    if kind == CYCLE and "t_ns" not in obj:
        obj = {**obj, "t_ns": t_ns}
    return encode_json(obj)


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "unknown"


def default_run_info(cfg: RigConfig, mono_ns: int, unix_ns: int) -> dict[str, str]:
    """The ``hil.run`` metadata of a run of ``cfg`` started at these clock readings, in this
    process (pid, argv, host, versions)."""
    start = _dt.datetime.fromtimestamp(unix_ns / 1e9, tz=_dt.UTC)
    return {
        "law": cfg.controller.law,
        "rate_hz": repr(cfg.rates.control_hz),
        "clock": cfg.controller.clock,
        "start_wall_time": start.isoformat(timespec="microseconds"),
        "start_unix_ns": str(unix_ns),
        "start_monotonic_ns": str(mono_ns),
        "monotonic_to_unix_ns": str(unix_ns - mono_ns),
        "hostname": socket.gethostname(),
        "pid": str(os.getpid()),
        "argv": " ".join(sys.argv),
        "python_version": platform.python_version(),
        "platform": platform.platform(),
        "hil_version": _version("hil-rhc-visual-servo"),
        "mcap_version": _version("mcap"),
        "numpy_version": np.__version__,
        "cycle_schema_version": SCHEMA_VERSION,
    }


class CycleRecorder:
    """Context manager that writes controller cycles and raw inputs into an MCAP file.

    Args:
        path: the ``.mcap`` file to create (parent folders are created).
        cfg: the run's configuration, stored as ``hil.config`` metadata.
        run_info: extra ``hil.run`` metadata (values become strings); overrides the defaults.
        flush_interval_s: how often records flush the file to the OS (bounds a SIGKILL's loss).
        chunk_size: a chunk is also closed when it grows past this many bytes.
        live, scene: see the module docstring.

    ``record_*`` write before they return (True) and never raise for a record: one that cannot
    be encoded counts in ``encode_errors``, one after :meth:`close` or a write failure in
    ``dropped`` (False). A write failure (disk full...) ends the log and stays in :attr:`error`
    (``__exit__`` raises it as :class:`LogError`). Not thread-safe: one thread records and closes.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        cfg: RigConfig,
        *,
        run_info: dict[str, Any] | None = None,
        flush_interval_s: float = 0.5,
        chunk_size: int = 64 * 1024,
        live: Callable[[str, bytes], Any] | None = None,
        scene: Any | None = None,
    ) -> None:
        if not flush_interval_s > 0:
            raise LogError(f"flush_interval_s must be positive, got {flush_interval_s}")
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self._closed = False  # records are refused once set
        self._finished = False
        self._dirty = False  # messages since the last flush
        self._dropped = 0
        self._written = dict.fromkeys(TOPICS, 0)
        self._encode_errors = 0
        self._error: BaseException | None = None
        self._live = live
        self.live_sent = 0  # records handed to the live sink
        self.live_errors = 0  # exceptions the live sink raised (counted, never propagated)
        self._scene = scene
        self._scene_every = max(1, int(getattr(scene, "every", 1)))
        self._scene_channels: dict[str, int] = {}
        self.scene_written = 0  # scene messages written (not part of as_dict)
        self.scene_errors = 0
        mono_ns, unix_ns = time.monotonic_ns(), time.time_ns()
        self._mono_to_unix = unix_ns - mono_ns
        info = default_run_info(cfg, mono_ns, unix_ns)
        info.update({str(k): str(v) for k, v in (run_info or {}).items()})
        self.run_info = info
        self._stream: BinaryIO | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = open(self.path, "wb")  # noqa: SIM115 - closed by close()
            self._writer = Writer(
                self._stream, chunk_size=chunk_size, compression=CompressionType.ZSTD
            )
            self._writer.start(profile="", library=f"hil-rt_controller/{info['hil_version']}")
            self._channels = self._register_channels()
            if scene is not None:
                self._scene_channels = self._register_scene_channels(scene)
            self._writer.add_metadata(CONFIG_METADATA, {"json": cfg.to_json()})
            self._writer.add_metadata(RUN_METADATA, info)
            self._stream.flush()
        except BaseException as exc:
            self._close_stream()
            if isinstance(exc, OSError):
                reason = exc.strerror or exc
                raise LogError(f"cannot create MCAP log {self.path}: {reason}") from exc
            raise
        self._next_flush = time.monotonic() + self.flush_interval_s

    def _register_channels(self) -> dict[int, int]:
        w = self._writer
        cycle = w.register_schema("hil.ControllerCycle", "jsonschema", encode_json(cycle_schema()))
        can = w.register_schema("hil.CanFrame", "jsonschema", encode_json(CAN_SCHEMA))
        vision = w.register_schema("hil.VisionPayload", "jsonschema", encode_json(VISION_SCHEMA))
        diag = w.register_schema("hil.Diagnostics", "jsonschema", encode_json(DIAGNOSTICS_SCHEMA))
        params = w.register_schema(
            "hil.ParameterChange", "jsonschema", encode_json(PARAMETERS_SCHEMA)
        )
        schema_of = {CYCLE: cycle, CAN_RX: can, CAN_TX: can, VISION: vision, DIAG: diag}
        schema_of[PARAMS] = params
        return {k: w.register_channel(TOPICS[k], "json", schema_of[k]) for k in TOPICS}

    def _register_scene_channels(self, scene: Any) -> dict[str, int]:
        w, out = self._writer, {}
        for topic, cls in scene.schemas().items():
            schema = cls.get_schema()
            sid = w.register_schema(schema.name, schema.encoding, bytes(schema.data))
            out[topic] = w.register_channel(topic, "protobuf", sid)
        return out

    def set_live(self, sink: Callable[[str, bytes], Any] | None) -> None:
        """Attach (or detach with None) the ``live`` sink."""
        self._live = sink

    # ----------------------------------------------------------------- records

    def record_cycle(self, record: dict[str, Any]) -> bool:
        """Write one tick (a dict with the fields of ``cycle_schema.json``)."""
        t_ns = record.get("t_ns")
        return self.write(CYCLE, time.monotonic_ns() if t_ns is None else t_ns, record)

    def record_diagnostics(self, record: dict[str, Any], *, final: bool = False) -> bool:
        """Write one ``/diagnostics`` record (``final``, for the interface, changes nothing)."""
        return self.write(DIAG, int(record["t_ns"]), record)

    def record_parameters(self, record: dict[str, Any]) -> bool:
        """Write one online parameter change (``/controller/parameters``)."""
        return self.write(PARAMS, int(record["t_ns"]), record)

    def record_can(self, msg: Any, t_ns: int, direction: str) -> bool:
        """Write a python-can ``Message`` received (``"rx"``) or sent (``"tx"``) at ``t_ns``."""
        kind = DIRECTIONS.get(direction)
        if kind is None:
            raise LogError(f"CAN direction must be 'rx' or 'tx', got {direction!r}")
        return self.write(kind, t_ns, msg)

    def record_vision(self, payload: bytes, t_ns: int) -> bool:
        """Write a raw vision payload received at ``t_ns``."""
        return self.write(VISION, t_ns, payload)

    def write(self, kind: int, t_ns: int, obj: Any) -> bool:
        """Encode and write one record item (``kind`` one of :data:`TOPICS`; the recorder
        process writes the batches it receives this way). False if it was not written."""
        if self._closed:
            self._dropped += 1
            return False
        try:
            t_ns = int(t_ns)
            data = encode_record(kind, t_ns, obj)
        except (TypeError, ValueError, AttributeError) as exc:
            self._encode_errors += 1
            if self._encode_errors == 1:
                log.warning("recorder: cannot encode a %s record: %s", TOPICS[kind], exc)
            return False
        log_time = max(0, t_ns + self._mono_to_unix)
        try:
            self._writer.add_message(self._channels[kind], log_time, data, log_time)
            self._written[kind] += 1
            self._dirty = True
            if kind == CYCLE and self._scene is not None:
                self._write_scene(obj, log_time)
            self.flush_if_due()
        except Exception as exc:  # disk full, I/O error...: the log ends, the caller goes on
            self._fail(exc)
            return False
        if kind in (CYCLE, DIAG) and self._live is not None:
            self._send_live(TOPICS[kind], data)
        return True

    def _send_live(self, topic: str, data: bytes) -> None:
        try:
            self._live(topic, data)
            self.live_sent += 1
        except Exception as exc:  # a monitor never stops the log
            self.live_errors += 1
            if self.live_errors == 1:
                log.warning("recorder: live sink failed: %s", exc)

    def _write_scene(self, record: dict[str, Any], log_time: int) -> None:
        tick = record.get("tick")
        if not isinstance(tick, int) or tick % self._scene_every:
            return
        try:
            msgs = [(t, m.encode()) for t, m in self._scene.messages(record, log_time)]
        except Exception as exc:
            self.scene_errors += 1
            if self.scene_errors == 1:
                log.warning("recorder: cannot draw the scene of a cycle: %s", exc)
            return
        for topic, data in msgs:
            self._writer.add_message(self._scene_channels[topic], log_time, data, log_time)
            self.scene_written += 1

    # ----------------------------------------------------------------- durability

    def flush(self) -> None:
        """Close the chunk in progress and flush the file to the OS: what is written so far
        survives a SIGKILL of this process (no ``fsync``: not a power loss)."""
        if self._closed or not self._dirty:
            return
        try:
            self._writer.flush()
        except Exception as exc:
            self._fail(exc)
            return
        self._dirty = False

    def flush_if_due(self) -> None:
        """:meth:`flush` if ``flush_interval_s`` has passed since the last due flush."""
        now = time.monotonic()
        if now >= self._next_flush:
            self._next_flush = now + self.flush_interval_s
            self.flush()

    def _fail(self, exc: Exception) -> None:
        self._error = exc
        self._closed = True
        self._dropped += 1
        log.error("recorder: writing %s failed: %s", self.path, exc)
        self._close_stream()

    def _close_stream(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            try:
                stream.close()
            except OSError as exc:
                self._error = self._error or exc

    # ----------------------------------------------------------------- counters

    @property
    def written(self) -> int:
        """Messages written into the MCAP writer so far (all topics)."""
        return sum(self._written.values())

    @property
    def dropped(self) -> int:
        """Records refused because the recorder was closed or its writing had failed."""
        return self._dropped

    @property
    def pending(self) -> int:
        """Records not written yet: always 0 (the recorder interface's counter)."""
        return 0

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the log early, if any."""
        return self._error

    def as_dict(self) -> dict[str, int]:
        """Counters per topic plus ``written``, ``dropped``, ``encode_errors`` and ``pending``."""
        out = {TOPICS[k]: v for k, v in self._written.items()}
        out.update(
            written=self.written,
            dropped=self._dropped,
            encode_errors=self._encode_errors,
            pending=0,
        )
        return out

    # ----------------------------------------------------------------- closing

    def close(self) -> None:
        """Finish the file (``hil.recorder`` counters, summary, footer); later records are
        refused. Idempotent. A failure is kept in :attr:`error`."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.add_metadata(
                RECORDER_METADATA, {k: str(v) for k, v in self.as_dict().items()}
            )
            self._writer.finish()
            self._finished = True
        except Exception as exc:
            self._error = exc
            log.error("recorder: finishing %s failed: %s", self.path, exc)
        finally:
            self._close_stream()

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def finished(self) -> bool:
        """The file has its summary and footer (a clean close)."""
        return self._finished

    def __enter__(self) -> CycleRecorder:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close()
        if self._error is not None and exc_type is None:
            raise LogError(f"MCAP log {self.path} is incomplete: {self._error}") from self._error

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"CycleRecorder({str(self.path)!r}, {state}, written={self.written})"
