"""The MCAP log of a run: every controller cycle, the raw CAN frames and vision messages.

:class:`CycleRecorder` writes each record at once with mcap's synchronous
:class:`~mcap.writer.Writer` (zstd chunks). In a run it lives in the recorder's own process
(:mod:`rt_controller.runtime.recorder_process`); ``hil replay --out`` and tests use it directly.

One JSON topic per record kind (:data:`TOPICS`, each with its JSON Schema; the table is in
``docs/concepts/logs.md``), and in a ``cia402`` run's log ``/hal/canopen``, the CAN frames
decoded by the writer itself (:data:`DECODED_TOPICS`). ``log_time`` is the record's monotonic
time shifted to the Unix epoch (the offset is in the ``hil.run`` metadata). ``live`` gets the
topic and JSON bytes of each cycle and diagnostics record (for zenoh); ``scene``
(:mod:`rt_controller.monitor.scene`) draws every ``scene.every``-th cycle on protobuf channels.
Metadata: ``hil.config``, ``hil.run`` and, at a clean close, ``hil.recorder`` (counters). The
first record ``flush_interval_s`` after the last flush closes the chunk and flushes the file to
the OS, so a SIGKILLed writer loses about that much at most.
"""

from __future__ import annotations

import base64
import datetime as _dt
import json
import logging
import os
import platform
import socket
import sys
import time
from collections.abc import Callable
from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, BinaryIO, Self

import numpy as np
from mcap.writer import CompressionType, Writer

from hal.config import RigConfig
from hal.log_topics import (
    CAN_RX_TOPIC,
    CAN_TX_TOPIC,
    CANOPEN_TOPIC,
    CYCLE_TOPIC,
    DIAGNOSTICS_TOPIC,
    EVENTS_TOPIC,
    PARAMETERS_TOPIC,
    VISION_TOPIC,
)
from rt_controller import compile_target
from rt_controller.calibration.operator import EVENT_SCHEMA
from rt_controller.calibration.parameters import PARAMETERS_SCHEMA
from rt_controller.errors import LogError
from rt_controller.runtime.cycle_record import cycle_schema
from rt_controller.runtime.diagnostics import DIAGNOSTICS_SCHEMA
from rt_controller.runtime.record_encoding import (
    CAN_SCHEMA,
    CANOPEN_SCHEMA,
    VISION_SCHEMA,
    can_dict,
    canopen_dict,
    encode_json,
)

log = logging.getLogger(__name__)

CONFIG_METADATA = "hil.config"
RUN_METADATA = "hil.run"
RECORDER_METADATA = "hil.recorder"
SCHEMA_VERSION = "1"

CYCLE, CAN_RX, CAN_TX, VISION, DIAG, PARAMS, EVENTS = 0, 1, 2, 3, 4, 5, 6
"""Record kinds: the first element of a record item ``(kind, t_ns, obj)``
(:meth:`Recorder.write`)."""
TOPICS = {
    CYCLE: CYCLE_TOPIC,
    CAN_RX: CAN_RX_TOPIC,
    CAN_TX: CAN_TX_TOPIC,
    VISION: VISION_TOPIC,
    DIAG: DIAGNOSTICS_TOPIC,
    PARAMS: PARAMETERS_TOPIC,
    EVENTS: EVENTS_TOPIC,
}
"""The topic of each record kind."""
IMAGE = 7
"""Record kind of a ``hil/vision/image`` payload (what the camera saw): written as the protobuf
topics of :mod:`rt_controller.monitor.camera_view`, not as JSON."""
CANOPEN = 8
DECODED_TOPICS = {CANOPEN: CANOPEN_TOPIC}
"""Topics the file's writer derives from the records it is given, never sent by the loop:
``/hal/canopen``, each ``/hal/can/*`` frame of a ``cia402`` run decoded (:func:`canopen_dict`),
so the decoding costs the control process nothing."""
CHUNK_SIZE = 4 << 20
"""Bytes of records a chunk holds before it is closed: more than a second of the rig's records
(about 2.5 MB with camera images), so chunks are closed by the flushes, one a second. mcap's
writer keeps an index of about 1 kB per chunk until the end of the log (the soak's RSS)."""
DIRECTIONS = {"rx": CAN_RX, "tx": CAN_TX}
"""The record kind of a CAN frame by its direction (``record_can``)."""
_ENCODE_ERRORS = (TypeError, ValueError, AttributeError, RecursionError)


def encode_record(kind: int, t_ns: int, obj: Any) -> bytes:
    """The JSON message of one record item."""
    if kind == VISION:
        data = bytes(obj)
        b64 = base64.b64encode(data).decode("ascii")
        return encode_json({"t_ns": t_ns, "size": len(data), "data": b64})
    if kind in (CAN_RX, CAN_TX):
        return encode_json(can_dict(t_ns, obj))
    return encode_json(obj)


def _version(dist: str) -> str:
    try:
        return version(dist)
    except PackageNotFoundError:
        return "unknown"


def run_metadata(cfg: RigConfig, extra: dict[str, Any] | None = None) -> dict[str, str]:
    """The ``hil.run`` metadata of a run of ``cfg`` starting now in this process, ``extra``
    (values become strings) overriding the defaults."""
    info = default_run_info(cfg, time.monotonic_ns(), time.time_ns())
    info.update({str(k): str(v) for k, v in (extra or {}).items()})
    return info


def default_run_info(cfg: RigConfig, mono_ns: int, unix_ns: int) -> dict[str, str]:
    """The ``hil.run`` metadata of a run of ``cfg`` started at these clock readings, in this
    process (pid, argv, host, versions, numba's compile target: see
    :mod:`rt_controller.compile_target`)."""
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
        **compile_target.run_info(),
    }


WRITER_COUNTERS = ("images_written", "image_errors", "scene_errors", "live_errors")
"""What the file's writer counts besides the topics' messages: camera images logged and those
that could not be, scene drawings that failed, records the live stream refused."""


class Recorder:
    """What both recorders share: the ``record_*`` calls of the loop, each one record item
    ``(kind, t_ns, obj)`` that :meth:`write` encodes for ``add``, the counters, and the context
    manager (``__exit__`` raises a log that ended early as :class:`LogError`)."""

    path: Path
    closed = finished = False
    """``finished``: the file has its summary and footer (a clean close)."""
    error: Any = None
    dropped = encode_errors = 0
    """Records refused (after :meth:`close`, a write failure, a full outbox...) and records
    that could not be encoded: counted, never raised into the tick."""
    images_written = image_errors = scene_errors = live_errors = 0
    """The writer's counters beyond the topics' (:data:`WRITER_COUNTERS`)."""
    counts: dict[int, int]
    """Messages written per record kind of :data:`TOPICS`."""
    add: Callable[..., bool]
    """``add(kind, t_ns, data, obj=None, final=False)``: record one encoded item; False if it
    was not (counted; ``final``: the run's last)."""
    close: Callable[[], None]

    def write(self, kind: int, t_ns: Any, obj: Any, final: bool = False) -> bool:
        """Encode and record one item (``kind`` one of :data:`TOPICS`, or :data:`IMAGE`; a
        record without an integer ``t_ns`` counts in ``encode_errors``)."""
        try:
            t_ns = int(t_ns)
            data = bytes(obj) if kind == IMAGE else encode_record(kind, t_ns, obj)
        except _ENCODE_ERRORS as exc:
            self._count("encode_errors", f"cannot encode a {TOPICS.get(kind)} record", exc)
            return False
        return self.add(kind, t_ns, data, obj, final)

    def _count(self, counter: str, what: str, exc: Exception) -> None:
        """Count a record, or a part of one, that could not be made (the first is logged)."""
        n = getattr(self, counter) + 1
        setattr(self, counter, n)
        if n == 1:
            log.warning("recorder: %s: %s", what, exc)

    def record_cycle(self, record: dict[str, Any]) -> bool:
        """One tick (a dict with the fields of ``cycle_schema.json``)."""
        return self.write(CYCLE, record.get("t_ns"), record)

    def record_diagnostics(self, record: dict[str, Any], *, final: bool = False) -> bool:
        """One ``/diagnostics`` record (``final``: the run's last, with its totals)."""
        return self.write(DIAG, record.get("t_ns"), record, final)

    def record_parameters(self, record: dict[str, Any]) -> bool:
        """One online parameter change (``/controller/parameters``)."""
        return self.write(PARAMS, record.get("t_ns"), record)

    def record_event(self, record: dict[str, Any]) -> bool:
        """One operator action, done or refused (``/controller/events``)."""
        return self.write(EVENTS, record.get("t_ns"), record)

    def record_can(self, msg: Any, t_ns: int, direction: str) -> bool:
        """A python-can ``Message`` received (``"rx"``) or sent (``"tx"``) at ``t_ns``."""
        kind = DIRECTIONS.get(direction)
        if kind is None:
            raise LogError(f"CAN direction must be 'rx' or 'tx', got {direction!r}")
        return self.write(kind, t_ns, msg)

    def record_vision(self, payload: bytes, t_ns: int) -> bool:
        """A raw vision payload received at ``t_ns``."""
        return self.write(VISION, t_ns, payload)

    @property
    def written(self) -> int:
        """Messages written so far (all topics)."""
        return sum(self.counts.values())

    def backlog_bytes(self) -> int:
        """Bytes of records on their way to the file: none here (written at once)."""
        return 0

    def as_dict(self) -> dict[str, int]:
        """Counters per topic plus ``written``, ``dropped``, ``encode_errors``, the
        :data:`WRITER_COUNTERS` and ``backlog_bytes``."""
        out = {t: self.counts[k] for k, t in TOPICS.items()}
        out.update({t: self.counts[k] for k, t in DECODED_TOPICS.items() if k in self.counts})
        out.update(written=self.written, dropped=self.dropped, encode_errors=self.encode_errors)
        out.update({k: getattr(self, k) for k in WRITER_COUNTERS})
        out.update(backlog_bytes=0 if self.closed else self.backlog_bytes())
        return out

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close()
        err = self.error
        if err is not None and exc_type is None:
            cause = err if isinstance(err, BaseException) else None
            raise LogError(f"MCAP log {self.path} is incomplete: {err}") from cause


class CycleRecorder(Recorder):
    """Writes controller cycles and raw inputs into an MCAP file.

    Args:
        path: the ``.mcap`` file to create (parent folders are created).
        cfg: the run's configuration, stored as ``hil.config`` metadata.
        run_info: extra ``hil.run`` metadata (values become strings); overrides the defaults.
        flush_interval_s: how often records flush the file to the OS (bounds a SIGKILL's loss);
            each flush closes a chunk.
        chunk_size: a chunk is also closed when it grows past this many bytes.
        live, scene: see the module docstring.

    A ``cia402`` configuration's log also gets ``/hal/canopen``: right after each CAN frame
    record, the same frame decoded, at the same log time (:data:`DECODED_TOPICS`).

    ``record_*`` write at once (True) and never raise: a record that cannot be encoded counts
    in ``encode_errors``, one after :meth:`close` or a write failure (which ends the log and
    stays in :attr:`error`) in ``dropped``; a failing ``live`` sink, scene or camera image in
    ``live_errors``, ``scene_errors``, ``image_errors``. One thread records and closes.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        cfg: RigConfig,
        *,
        run_info: dict[str, Any] | None = None,
        flush_interval_s: float = 1.0,
        chunk_size: int = CHUNK_SIZE,
        live: Callable[[str, bytes], Any] | None = None,
        scene: Any | None = None,
    ) -> None:
        if not flush_interval_s > 0:
            raise LogError(f"flush_interval_s must be positive, got {flush_interval_s}")
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.live = live
        """The live sink (None: none); its exceptions are counted, never propagated."""
        self.live_sent = 0
        self._scene = scene
        self._scene_every = max(1, int(getattr(scene, "every", 1)))
        self.scene_written = 0
        self.counts = dict.fromkeys(TOPICS, 0)
        self._canopen = cfg.hardware.profile == "cia402"
        if self._canopen:
            self.counts[CANOPEN] = 0
            import_module("hal.cia402_frames")  # canopen's import now, not at the first frame
        self._dirty = False  # messages since the last flush
        info = run_metadata(cfg, run_info)
        self._mono_to_unix = int(info["monotonic_to_unix_ns"])  # the run's, when it gave one
        self._stream: BinaryIO | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = open(self.path, "wb")  # noqa: SIM115 - closed by close()
            w = self._writer = Writer(
                self._stream, chunk_size=chunk_size, compression=CompressionType.ZSTD
            )
            w.start(profile="", library=f"hil-rt_controller/{info['hil_version']}")
            self._channels = self._register_channels()
            self._proto: dict[str, int] = {}
            for topic, cls in scene.schemas().items() if scene is not None else ():
                self._proto_channel(topic, cls)
            w.add_metadata(CONFIG_METADATA, {"json": cfg.to_json()})
            w.add_metadata(RUN_METADATA, info)
            self._stream.flush()
        except BaseException as exc:
            self._close_stream()
            if isinstance(exc, OSError):
                reason = exc.strerror or exc
                raise LogError(f"cannot create MCAP log {self.path}: {reason}") from exc
            raise
        self._next_flush = time.monotonic() + self.flush_interval_s

    def _register_channels(self) -> dict[int, int]:
        schemas = {
            CYCLE: ("hil.ControllerCycle", cycle_schema()),
            CAN_RX: ("hil.CanFrame", CAN_SCHEMA),
            VISION: ("hil.VisionPayload", VISION_SCHEMA),
            DIAG: ("hil.Diagnostics", DIAGNOSTICS_SCHEMA),
            PARAMS: ("hil.ParameterChange", PARAMETERS_SCHEMA),
            EVENTS: ("hil.OperatorEvent", EVENT_SCHEMA),
        }
        w = self._writer
        ids = {
            k: w.register_schema(n, "jsonschema", encode_json(b)) for k, (n, b) in schemas.items()
        }
        ids[CAN_TX] = ids[CAN_RX]  # one frame schema, two topics
        channels = {k: w.register_channel(topic, "json", ids[k]) for k, topic in TOPICS.items()}
        if self._canopen:
            sid = w.register_schema("hil.CanopenFrame", "jsonschema", encode_json(CANOPEN_SCHEMA))
            channels[CANOPEN] = w.register_channel(CANOPEN_TOPIC, "json", sid)
        return channels

    def _proto_channel(self, topic: str, cls: Any) -> int:
        """The protobuf channel of ``topic`` (registered on first use: a log has the camera's
        topics only if it saw an image)."""
        if topic not in self._proto:
            schema = cls.get_schema()
            sid = self._writer.register_schema(schema.name, schema.encoding, bytes(schema.data))
            self._proto[topic] = self._writer.register_channel(topic, "protobuf", sid)
        return self._proto[topic]

    def add(self, kind: int, t_ns: int, data: bytes, obj: Any = None, final: bool = False) -> bool:
        """Write one record already encoded (``data``: its message bytes, or an image's payload;
        ``obj``: the cycle the scene is drawn from, decoded from ``data`` when not given)."""
        if self.closed:
            self.dropped += 1
            return False
        if kind == IMAGE:
            return self._write_image(data)
        log_time = max(0, t_ns + self._mono_to_unix)
        if not self._put(self._channels[kind], log_time, data):
            return False
        self.counts[kind] += 1
        if self._canopen and kind in (CAN_RX, CAN_TX):
            self._write_canopen(kind, log_time, data)
        if kind == CYCLE and self._scene is not None:
            self._write_scene(json.loads(data) if obj is None else obj, log_time)
        if kind in (CYCLE, DIAG) and self.live is not None:
            try:
                self.live(TOPICS[kind], data)
                self.live_sent += 1
            except Exception as exc:  # a monitor never stops the log
                self._count("live_errors", "live sink failed", exc)
        return True

    def _put(self, channel: int, log_time: int, data: bytes) -> bool:
        """Write one message; False when the write failed (disk full, I/O error...), which ends
        the log while the caller goes on."""
        try:
            self._writer.add_message(channel, log_time, data, log_time)
        except Exception as exc:
            self._fail(exc)
            return False
        self._dirty = True
        self.flush_if_due()
        return True

    def _write_canopen(self, kind: int, log_time: int, data: bytes) -> None:
        """The ``/hal/canopen`` record of the frame record ``data``, at its log time; one that
        cannot be made counts in ``encode_errors`` (the run is then not clean)."""
        try:
            raw = json.loads(data)
            decoded = encode_json(canopen_dict("rx" if kind == CAN_RX else "tx", raw))
        except (*_ENCODE_ERRORS, KeyError) as exc:
            self._count("encode_errors", "cannot decode a CANopen frame record", exc)
            return
        if self._put(self._channels[CANOPEN], log_time, decoded):
            self.counts[CANOPEN] += 1

    def _write_scene(self, record: dict[str, Any], log_time: int) -> None:
        tick = record.get("tick")
        if not isinstance(tick, int) or tick % self._scene_every:
            return
        try:
            msgs = [(t, m.encode()) for t, m in self._scene.messages(record, log_time)]
        except Exception as exc:
            self._count("scene_errors", "cannot draw the scene of a cycle", exc)
            return
        for topic, data in msgs:
            if not self._put(self._proto[topic], log_time, data):
                return
            self.scene_written += 1

    def _write_image(self, payload: bytes) -> bool:
        """What the camera saw (:mod:`rt_controller.monitor.camera_view`), at its capture time;
        a payload that does not decode is counted in ``image_errors``."""
        from rt_controller.monitor.camera_view import SCHEMAS as VIEWS
        from rt_controller.monitor.camera_view import payload_messages

        try:
            log_time, views = payload_messages(payload, self._mono_to_unix)
            msgs = [(t, m.encode()) for t, m in views]
        except Exception as exc:
            self._count("image_errors", "cannot draw a camera image", exc)
            return False
        for topic, data in msgs:
            if not self._put(self._proto_channel(topic, VIEWS[topic]), log_time, data):
                return False
        self.images_written += 1
        return True

    def flush(self) -> None:
        """Close the chunk in progress and flush the file to the OS: what is written so far
        survives a SIGKILL of this process (no ``fsync``: not a power loss)."""
        if self.closed or not self._dirty:
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
        self.error = exc
        self.closed = True
        self.dropped += 1
        log.error("recorder: writing %s failed: %s", self.path, exc)
        self._close_stream()

    def _close_stream(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            try:
                stream.close()
            except OSError as exc:
                self.error = self.error or exc

    def close(self) -> None:
        """Finish the file (``hil.recorder`` counters, summary, footer); later records are
        refused. Idempotent. A failure is kept in :attr:`error`."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.add_metadata(
                RECORDER_METADATA, {k: str(v) for k, v in self.as_dict().items()}
            )
            self._writer.finish()
            self.finished = True
        except Exception as exc:
            self.error = exc
            log.error("recorder: finishing %s failed: %s", self.path, exc)
        finally:
            self._close_stream()
