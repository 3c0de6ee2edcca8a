"""The recorder's process: the run's records arrive as an MCAP stream on a pipe, leave as files.

The controller process writes each log as a plain MCAP stream, unchunked, with mcap's own
``Writer`` (:mod:`rt_controller.runtime.recorder_process`); this process reads it with mcap's
``StreamReader`` and writes the file with
:class:`~rt_controller.runtime.recorder.CycleRecorder` (chunked, compressed, indexed, the scene
drawn, camera images converted), and publishes ``/controller/cycle`` and ``/diagnostics`` live
on zenoh. Logs follow each other on the pipe, each a whole MCAP from magic to magic; two
metadata records of the stream are the controller's instructions and are not copied:
``hil.log`` (the path and how to write it) and ``hil.live`` (publish live, on which zenoh
endpoint). Answers go back as JSON lines on the other pipe: ``{"opened": PATH, "error": ...}``
when a log was created (or could not be), ``{"closed": PATH, "counts": ..., "error": ...}``
with its counters when it was finished.

The controller starts it with :data:`LAUNCH` (a fresh interpreter: it holds none of the
controller's memory). It ignores SIGINT, SIGTERM and SIGHUP (the controller decides when its
logs end) and finishes the open log at end of file on its pipe, so the log of a SIGKILLed
controller is still complete. While it waits for records it flushes the log when it is due.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import struct
import sys
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader

from rt_controller.runtime.recorder import (
    CONFIG_METADATA,
    IMAGE,
    RUN_METADATA,
    TOPICS,
    CycleRecorder,
)

LOG_METADATA, LIVE_METADATA = "hil.log", "hil.live"
"""The controller's instructions in the stream (see the module docstring)."""
IMAGE_TOPIC = "hil/vision/image"
"""The stream's channel of the camera's images, as received (the file gets protobuf topics)."""
KIND_OF_TOPIC = {**{topic: kind for kind, topic in TOPICS.items()}, IMAGE_TOPIC: IMAGE}
IDLE_S = 0.25
"""How often a waiting recorder looks whether the log is due for a flush."""


class PipeInput:
    """The read end of the pipe as the file ``StreamReader`` reads: ``read(n)`` gives ``n``
    bytes (fewer only at end of file) and calls ``idle`` while it waits."""

    def __init__(self, fd: int, idle: Any) -> None:
        self.fd, self.idle = fd, idle
        self.eof = False

    def read(self, n: int = -1) -> bytes:
        parts, want = [], n
        while want > 0 and not self.eof:
            if not select.select([self.fd], [], [], IDLE_S)[0]:
                self.idle()
                continue
            data = os.read(self.fd, min(want, 1 << 20))
            if not data:
                self.eof = True
            parts.append(data)
            want -= len(data)
        return b"".join(parts)


class LogCopy:
    """One log of the stream into its file (and the live stream)."""

    def __init__(self, child: RecorderChild) -> None:
        self.child = child
        self.rec: CycleRecorder | None = None
        self.kinds: dict[int, int] = {}
        self.meta: dict[str, dict[str, str]] = {}

    def handle(self, record: Any) -> None:
        if isinstance(record, Message):
            kind = self.kinds.get(record.channel_id)
            if self.rec is not None and kind is not None:
                self.rec.add(kind, record.log_time, record.data)
        elif isinstance(record, Channel):
            self.kinds[record.id] = KIND_OF_TOPIC[record.topic]
        elif isinstance(record, Metadata):
            self.meta[record.name] = record.metadata
            if record.name == RUN_METADATA:  # hil.log and hil.config come before it
                self.open()
            elif record.name == LIVE_METADATA and self.rec is not None:
                self.rec.set_live(self.child.live_sink(self.meta, record.metadata))

    def open(self) -> None:
        from hal.config import config_from_json

        how = self.meta.get(LOG_METADATA, {})
        path = how.get("path", "")
        try:
            cfg = config_from_json(self.meta[CONFIG_METADATA]["json"])
            scene = None
            if how.get("scene") == "1":
                from rt_controller.monitor.scene import SceneBuilder

                scene = SceneBuilder(cfg)
            self.rec = CycleRecorder(
                path,
                cfg,
                run_info=self.meta[RUN_METADATA],
                flush_interval_s=float(how.get("flush_interval_s", 1.0)),
                scene=scene,
            )
        except Exception as exc:
            self.child.reply({"opened": path, "error": str(exc) or type(exc).__name__})
            return
        self.child.reply({"opened": path, "error": None})

    def close(self) -> None:
        rec, self.rec = self.rec, None
        if rec is None:
            return
        rec.close()
        rec.set_live(None)
        error = str(rec.error) if rec.error else None
        if not (error or rec.finished):
            error = "the writer did not finish the file"
        counts = {**rec.as_dict(), "finished": rec.finished}
        self.child.reply({"closed": str(rec.path), "counts": counts, "error": error})


class RecorderChild:
    """The process's side: the logs one after another, the live zenoh session."""

    def __init__(self, fd_in: int, fd_out: int) -> None:
        self.fd_out = fd_out
        os.set_blocking(fd_in, True)
        self.log: LogCopy | None = None
        self.input = PipeInput(fd_in, self.idle)
        self.session: Any = None
        self.live: Any = None
        self.live_failed = False

    def reply(self, message: dict[str, Any]) -> None:
        with contextlib.suppress(OSError):  # the controller is gone: the log still gets finished
            os.write(self.fd_out, json.dumps(message).encode() + b"\n")

    def idle(self) -> None:
        if self.log is not None and self.log.rec is not None:
            self.log.rec.flush_if_due()  # a quiet log still reaches the disk

    def run(self) -> None:
        """Serve logs until end of file on the input pipe; the last one is finished then."""
        while not self.input.eof:
            self.log = LogCopy(self)
            try:
                for record in StreamReader(self.input, record_size_limit=None).records:
                    self.log.handle(record)  # the stream ends after the Footer's magic
            except (McapError, struct.error, ValueError) as exc:  # the controller died mid-log
                if not self.input.eof:
                    print(f"hil controller: recorder: bad record stream: {exc}", file=sys.stderr)
                    self.input.eof = True
            self.log.close()
        if self.live is not None:
            self.live.close()
        if self.session is not None:
            self.session.close()

    def live_sink(self, meta: dict[str, dict[str, str]], link: dict[str, str]) -> Any:
        """The zenoh publisher of the live stream (the session opens on first use), or None."""
        if self.live is not None or self.live_failed:
            return self.live
        from hal.config import config_from_json
        from hal.errors import HalError
        from hal.zenoh_session import open_session
        from rt_controller.monitor.live import LivePublisher

        try:
            self.session = open_session(
                config_from_json(meta[CONFIG_METADATA]["json"]),
                listen=False,
                endpoint=link.get("endpoint") or None,
                config_file=link.get("config") or None,
                wait_s=5.0,
            )
            self.live = LivePublisher(self.session)
        except HalError as exc:
            self.live_failed = True
            print(f"hil controller: warning: no live stream: {exc}", file=sys.stderr)
        return self.live


def _demote() -> None:
    """Best effort: the recorder must not compete with a SCHED_FIFO loop that started it (the
    policy and a single-CPU affinity are inherited)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        cpus = os.sched_getaffinity(0)
        everything = set(range(os.cpu_count() or 1))
        if len(cpus) == 1 and len(everything) > 1:
            os.sched_setaffinity(0, everything - cpus)
    except (AttributeError, OSError):
        pass


def serve(fd_in: int = 0, fd_out: int = 1) -> None:
    """The process's main loop: logs from ``fd_in`` until its end of file, the last one
    finished then; answers on ``fd_out``. Warnings go to stderr."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    _demote()
    RecorderChild(fd_in, fd_out).run()


LAUNCH = (
    "import signal\n"
    "for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP): signal.signal(s, signal.SIG_IGN)\n"
    "from rt_controller.runtime.recorder_child import serve\n"
    "serve()\n"
)
"""The process's program (``python -c``): signals ignored before anything is imported, then
:func:`serve` on its standard input and output."""
