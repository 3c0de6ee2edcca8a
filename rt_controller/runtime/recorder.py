"""MCAP recording of every controller cycle, plus the raw CAN frames and vision messages.

:class:`CycleRecorder` is built for a hard-cadence loop: the hot-path methods (:meth:`record_cycle`,
:meth:`record_can`, :meth:`record_vision`) only append a tuple to a bounded deque (O(1), no lock,
no I/O, never blocking). A background thread encodes the records as JSON and writes them into an
MCAP file in small zstd chunks; when the queue is full the record is dropped and counted.

Topics (all JSON with a JSON Schema, so Foxglove / Lichtblick plot them as they are):

==================== ======================== ================================================
topic                schema                   one message per
==================== ======================== ================================================
``/controller/cycle`` ``hil.ControllerCycle``  tick (fields: ``runtime/cycle_schema.json``)
``/hal/can/rx``       ``hil.CanFrame``         CAN frame received by the controller
``/hal/can/tx``       ``hil.CanFrame``         CAN frame sent by the controller
``/vision/features``  ``hil.VisionPayload``    vision message as received (raw bytes, base64)
==================== ======================== ================================================

Message ``log_time`` is the record's monotonic time shifted to the Unix epoch (the offset is
stored in the ``hil.run`` metadata), so viewers show wall-clock dates while ``t_ns`` inside the
messages stays the loop's monotonic clock.

Optional extras, both fed by the writer thread (never by the tick): ``live``, a callable given
the topic and the already-encoded JSON bytes of every ``/controller/cycle`` and ``/diagnostics``
record (the daemon publishes them on zenoh, ``hil/controller/cycle`` and
``hil/controller/diagnostics``); and ``scene``, a builder whose ``messages(record, log_time)``
turns a cycle record into Foxglove scene messages (:mod:`rt_controller.monitor.scene`), written on
their own protobuf channels (``/tf``, ``/scene/arm``, ``/camera/...``) for the ticks whose
number is a multiple of ``scene.every``.

Metadata: ``hil.config`` (key ``json``: :meth:`hal.config.RigConfig.to_json`), ``hil.run`` (law,
rate, clock, start time, host, versions, and the caller's ``run_info``), and at a clean close
``hil.recorder`` (written/dropped counters). Durability: the chunk in progress is closed and
flushed to the OS at least every ``flush_interval_s``, so a SIGKILLed process loses at most the
last ``flush_interval_s`` plus the queue; the finished chunks stay readable
(:func:`rt_controller.logtools.reader.read_log`).
"""

from __future__ import annotations

import atexit
import base64
import collections
import datetime as _dt
import json
import logging
import math
import os
import platform
import queue
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.writer import CompressionType, Writer

from hal.config import RigConfig
from rt_controller.errors import LogError
from rt_controller.runtime.diagnostics import DIAGNOSTICS_SCHEMA

log = logging.getLogger(__name__)

CYCLE_TOPIC = "/controller/cycle"
CAN_RX_TOPIC = "/hal/can/rx"
CAN_TX_TOPIC = "/hal/can/tx"
VISION_TOPIC = "/vision/features"
DIAGNOSTICS_TOPIC = "/diagnostics"
CONFIG_METADATA = "hil.config"
RUN_METADATA = "hil.run"
RECORDER_METADATA = "hil.recorder"
SCHEMA_VERSION = "1"

_CYCLE, _CAN_RX, _CAN_TX, _VISION, _DIAG = 0, 1, 2, 3, 4
_TOPICS = {
    _CYCLE: CYCLE_TOPIC,
    _CAN_RX: CAN_RX_TOPIC,
    _CAN_TX: CAN_TX_TOPIC,
    _VISION: VISION_TOPIC,
    _DIAG: DIAGNOSTICS_TOPIC,
}
_DIRECTIONS = {"rx": _CAN_RX, "tx": _CAN_TX}
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


def _can_dict(t_ns: int, msg: Any, data: bytes) -> dict[str, Any]:
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


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "unknown"


def _default_run_info(cfg: RigConfig, mono_ns: int, unix_ns: int) -> dict[str, str]:
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


def _demote_current_thread() -> None:
    """Best effort: the writer must not compete with a SCHED_FIFO loop it was spawned from."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        cpus = os.sched_getaffinity(0)
        everything = set(range(os.cpu_count() or 1))
        if len(cpus) == 1 and len(everything) > 1:
            os.sched_setaffinity(0, everything - cpus)
    except (AttributeError, OSError):
        pass


class CycleRecorder:
    """Context manager that records controller cycles and raw inputs into an MCAP file.

    Args:
        path: the ``.mcap`` file to create (parent folders are created).
        cfg: the run's configuration, stored as ``hil.config`` metadata.
        run_info: extra ``hil.run`` metadata (values are turned into strings); overrides the
            defaults taken from ``cfg`` (``law``, ``rate_hz``, ``clock``) and the environment.
        flush_interval_s: longest time a recorded message stays in memory before its chunk is
            written to the file (bounds what a SIGKILL loses).
        queue_size: records that may wait for the writer thread; more are dropped and counted.
        chunk_size: a chunk is also closed when it grows past this many bytes.

    The hot-path methods take ownership of what they are given: do not mutate a cycle dict (or
    the arrays in it) after passing it. ``close()`` is idempotent and safe to call from a
    signal handler: the writer thread drains the queue and finishes the file by itself.
    """

    #: How long the writer may hold the GIL in one go before it sleeps briefly.
    burst_s = 200e-6
    #: Writer's sleep between bursts when more work is waiting.
    yield_s = 100e-6
    #: Longest idle wait of the writer (it also wakes for each cycle record, for ``close`` and
    #: for the periodic flush).
    poll_s = 0.1

    def __init__(
        self,
        path: str | os.PathLike[str],
        cfg: RigConfig,
        *,
        run_info: dict[str, Any] | None = None,
        flush_interval_s: float = 0.5,
        queue_size: int = 16384,
        chunk_size: int = 64 * 1024,
        live: Callable[[str, bytes], Any] | None = None,
        scene: Any | None = None,
    ) -> None:
        if not flush_interval_s > 0:
            raise LogError(f"flush_interval_s must be positive, got {flush_interval_s}")
        if queue_size < 1:
            raise LogError(f"queue_size must be at least 1, got {queue_size}")
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.queue_size = int(queue_size)
        self._q: collections.deque[tuple[int, int, Any, Any]] = collections.deque()
        self._wake: queue.SimpleQueue[None] = queue.SimpleQueue()
        """Wakes the writer: a token per cycle or diagnostics record (the end of a tick: the
        writer never wakes in the middle of one to take the GIL from it) and on ``close``
        (``SimpleQueue.put`` is reentrant, safe from a signal handler)."""
        self._closed = False  # hot path refuses records once set
        self._stop = False  # writer drains, finishes the file and exits once set
        self._dropped = 0
        self._written = dict.fromkeys(_TOPICS, 0)
        self._encode_errors = 0
        self._live = live
        self.live_sent = 0
        """Records handed to the ``live`` sink."""
        self.live_errors = 0
        """Exceptions raised by the ``live`` sink (counted, never propagated)."""
        self._scene = scene
        self._scene_every = max(1, int(getattr(scene, "every", 1)))
        self._scene_channels: dict[str, int] = {}
        self.scene_written = 0
        """Scene messages written (not part of :meth:`as_dict`)."""
        self.scene_errors = 0
        self._error: BaseException | None = None
        self._finished = False
        self._released = False
        mono_ns, unix_ns = time.monotonic_ns(), time.time_ns()
        self._mono_to_unix = unix_ns - mono_ns
        info = _default_run_info(cfg, mono_ns, unix_ns)
        info.update({str(k): str(v) for k, v in (run_info or {}).items()})
        self.run_info = info
        self._stream: BinaryIO | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = open(self.path, "wb")  # noqa: SIM115 - closed by the writer thread
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
            if self._stream is not None:
                self._stream.close()
            if isinstance(exc, OSError):
                reason = exc.strerror or exc
                raise LogError(f"cannot create MCAP log {self.path}: {reason}") from exc
            raise
        self._thread = threading.Thread(target=self._run, name="hil-mcap-writer", daemon=True)
        atexit.register(self._atexit_close)
        self._thread.start()

    def _register_channels(self) -> dict[int, int]:
        w = self._writer
        cycle = w.register_schema("hil.ControllerCycle", "jsonschema", encode_json(cycle_schema()))
        can = w.register_schema("hil.CanFrame", "jsonschema", encode_json(CAN_SCHEMA))
        vision = w.register_schema("hil.VisionPayload", "jsonschema", encode_json(VISION_SCHEMA))
        diag = w.register_schema("hil.Diagnostics", "jsonschema", encode_json(DIAGNOSTICS_SCHEMA))
        schema_of = {_CYCLE: cycle, _CAN_RX: can, _CAN_TX: can, _VISION: vision, _DIAG: diag}
        return {k: w.register_channel(_TOPICS[k], "json", schema_of[k]) for k in _TOPICS}

    def _register_scene_channels(self, scene: Any) -> dict[str, int]:
        w, out = self._writer, {}
        for topic, cls in scene.schemas().items():
            schema = cls.get_schema()
            sid = w.register_schema(schema.name, schema.encoding, bytes(schema.data))
            out[topic] = w.register_channel(topic, "protobuf", sid)
        return out

    def set_live(self, sink: Callable[[str, bytes], Any] | None) -> None:
        """Attach (or detach with None) the ``live`` sink; safe while the writer runs."""
        self._live = sink

    # ----------------------------------------------------------------- hot path (loop thread)

    def record_cycle(self, record: dict[str, Any]) -> bool:
        """Queue one tick (a dict with the fields of ``cycle_schema.json``). False if dropped."""
        q = self._q
        if self._closed or len(q) >= self.queue_size:
            self._dropped += 1
            return False
        t_ns = record.get("t_ns")
        q.append((_CYCLE, time.monotonic_ns() if t_ns is None else t_ns, record, None))
        self._wake.put(None)
        return True

    def record_diagnostics(self, record: dict[str, Any], *, final: bool = False) -> bool:
        """Queue one ``/diagnostics`` record (see :mod:`rt_controller.runtime.diagnostics`). A final
        record is queued even when the queue is full (it carries the run's totals)."""
        q = self._q
        if self._closed or (len(q) >= self.queue_size and not final):
            self._dropped += 1
            return False
        q.append((_DIAG, int(record["t_ns"]), record, None))
        self._wake.put(None)
        return True

    def record_can(self, msg: Any, t_ns: int, direction: str) -> bool:
        """Queue a python-can ``Message`` received (``"rx"``) or sent (``"tx"``) at ``t_ns``."""
        kind = _DIRECTIONS.get(direction)
        if kind is None:
            raise LogError(f"CAN direction must be 'rx' or 'tx', got {direction!r}")
        q = self._q
        if self._closed or len(q) >= self.queue_size:
            self._dropped += 1
            return False
        q.append((kind, t_ns, msg, bytes(msg.data)))
        return True

    def record_vision(self, payload: bytes, t_ns: int) -> bool:
        """Queue a raw vision payload received at ``t_ns``. False if dropped."""
        q = self._q
        if self._closed or len(q) >= self.queue_size:
            self._dropped += 1
            return False
        q.append((_VISION, t_ns, bytes(payload), None))
        return True

    # ----------------------------------------------------------------- counters

    @property
    def written(self) -> int:
        """Messages written into the MCAP writer so far (all topics)."""
        return sum(self._written.values())

    @property
    def dropped(self) -> int:
        """Records refused because the queue was full or the recorder closed."""
        return self._dropped

    @property
    def pending(self) -> int:
        """Records waiting for the writer thread."""
        return len(self._q)

    @property
    def error(self) -> BaseException | None:
        """The exception that stopped the writer thread, if any."""
        return self._error

    def as_dict(self) -> dict[str, int]:
        """Counters per topic plus ``dropped``, ``encode_errors`` and ``pending``."""
        out = {_TOPICS[k]: v for k, v in self._written.items()}
        out.update(
            written=self.written,
            dropped=self._dropped,
            encode_errors=self._encode_errors,
            pending=len(self._q),
        )
        return out

    # ----------------------------------------------------------------- writer thread

    def _encode(self, item: tuple[int, int, Any, Any]) -> tuple[int, bytes]:
        kind, t_ns, obj, extra = item
        if kind == _DIAG:
            return t_ns, encode_json(obj)
        if kind == _CYCLE:
            if "t_ns" not in obj:
                obj = {**obj, "t_ns": t_ns}
            return t_ns, encode_json(obj)
        if kind == _VISION:
            b64 = base64.b64encode(obj).decode("ascii")
            return t_ns, encode_json({"t_ns": t_ns, "size": len(obj), "data": b64})
        return t_ns, encode_json(_can_dict(t_ns, obj, extra))

    def _write_one(self, item: tuple[int, int, Any, Any]) -> None:
        try:
            t_ns, data = self._encode(item)
            t_ns = int(t_ns)
        except (TypeError, ValueError) as exc:
            self._encode_errors += 1
            if self._encode_errors == 1:
                log.warning("recorder: cannot encode a %s record: %s", _TOPICS[item[0]], exc)
            return
        log_time = max(0, t_ns + self._mono_to_unix)
        kind = item[0]
        self._writer.add_message(self._channels[kind], log_time, data, log_time)
        self._written[kind] += 1
        if kind in (_CYCLE, _DIAG):
            live = self._live
            if live is not None:
                try:
                    live(_TOPICS[kind], data)
                    self.live_sent += 1
                except Exception as exc:  # a monitor never stops the log
                    self.live_errors += 1
                    if self.live_errors == 1:
                        log.warning("recorder: live sink failed: %s", exc)
            if kind == _CYCLE and self._scene is not None:
                self._write_scene(item[2], log_time)

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

    def _drain_burst(self) -> int:
        q, n = self._q, 0
        end = time.perf_counter() + self.burst_s
        while q:
            self._write_one(q.popleft())
            n += 1
            if time.perf_counter() >= end:
                break
        return n

    def _idle(self, next_flush: float) -> None:
        """Wait for a wake token (a tick ended, or ``close``), at most until the next flush."""
        wait = min(max(0.0, next_flush - time.monotonic()), self.poll_s)
        try:
            self._wake.get(timeout=wait)
            while True:  # several ticks may have ended: one pass drains them all
                self._wake.get_nowait()
        except queue.Empty:
            pass

    def _run(self) -> None:
        _demote_current_thread()
        next_flush = time.monotonic() + self.flush_interval_s
        dirty = False
        reported_drops = 0
        try:
            while True:
                stopping = self._stop
                n = self._drain_burst()
                dirty = dirty or n > 0
                now = time.monotonic()
                if now >= next_flush:
                    next_flush = now + self.flush_interval_s
                    if dirty:
                        self._writer.flush()  # closes the chunk in progress, flushes to the OS
                        dirty = False
                    if self._dropped != reported_drops and not self._stop:
                        log.warning("recorder: %d records dropped so far", self._dropped)
                        reported_drops = self._dropped
                if stopping and not self._q:
                    break
                if self._q:
                    time.sleep(self.yield_s)  # more work: let the control thread run first
                else:
                    self._idle(next_flush)
            self._writer.add_metadata(
                RECORDER_METADATA, {k: str(v) for k, v in self.as_dict().items()}
            )
            self._writer.finish()
            self._finished = True
        except BaseException as exc:  # disk full, I/O error...: keep the loop running
            self._error = exc
            self._closed = True
            log.error("recorder: writer thread failed: %s", exc)
        finally:
            if self._stream is not None:
                try:
                    self._stream.close()
                except OSError as exc:
                    self._error = self._error or exc

    # ----------------------------------------------------------------- closing

    def close(self, timeout: float | None = 30.0) -> None:
        """Stop accepting records, let the writer drain the queue and finish the file.

        Idempotent and safe from a signal handler: it only sets two flags and joins the writer
        thread (no lock shared with the loop or the writer). Returns when the writer thread has
        ended or after ``timeout`` seconds; the writer finishes the file by itself even if this
        call is interrupted, and an ``atexit`` hook closes a recorder nobody closed. A writer
        failure is kept in :attr:`error` (``__exit__`` raises it as :class:`LogError`).
        """
        self._closed = True
        self._stop = True
        self._wake.put(None)
        thread = self._thread
        if thread is not threading.current_thread() and thread.is_alive():
            thread.join(timeout)
        if not thread.is_alive() and not self._released:
            self._released = True
            atexit.unregister(self._atexit_close)

    def _atexit_close(self) -> None:
        self.close()

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
