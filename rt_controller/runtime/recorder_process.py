"""The MCAP recorder in a process of its own, so the control process runs no other Python thread.

:class:`RecorderService` starts one child process for a controller process (the runs of a plan
share it); :meth:`RecorderService.open` gives a :class:`RemoteRecorder`, the daemon's recorder.
The loop publishes each record once, as the MCAP message it will be in the log: encoded here,
framed by mcap's own ``Writer`` into an unchunked MCAP stream, written to a pipe once per tick.
The child (:mod:`rt_controller.runtime.recorder_child`) reads the stream with mcap's
``StreamReader``, writes the file and publishes the live stream. No protocol of our own: the
pipe carries MCAP, the answers are JSON lines.

A realtime tick never blocks on the child: the pipe is non-blocking (1 MiB where the kernel
allows it), what it cannot take waits in an outbox, and a record that would grow the outbox past
:attr:`RecorderService.outbox_limit` bytes is dropped and counted (the run is then not clean).
Lockstep has no deadline: there the tick waits for the child (``backpressure``), so a
Sync-paced log is never short because the host was busy.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import select
import subprocess
import sys
import termios
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from mcap.writer import IndexType, Writer

from hal.config import RigConfig
from rt_controller.errors import LogError
from rt_controller.runtime.recorder import (
    CONFIG_METADATA,
    CYCLE,
    DIAG,
    IMAGE,
    RUN_METADATA,
    TOPICS,
    Recorder,
    default_run_info,
    encode_record,
)
from rt_controller.runtime.recorder_child import IMAGE_TOPIC, LAUNCH, LIVE_METADATA, LOG_METADATA

REPLY_TIMEOUT_S = 30.0
"""How long opening or closing a log waits for the child's answer."""
MMAP_THRESHOLD = 128 << 10
"""glibc's mmap threshold for the recorder process, fixed: buffers of a chunk or a camera image
are mapped and given back when freed. Left to glibc, the threshold grows to the largest buffer
freed, and the heap keeps about 2 MB more after the first minutes (an in-process recorder fed
600 s of the soak's records: +2.7 MB against +0.5 MB)."""
_ENCODE_ERRORS = (TypeError, ValueError, AttributeError, RecursionError)


class _Outbox(bytearray):
    """The bytes of the stream not yet in the pipe (the file the stream ``Writer`` writes)."""

    written = 0

    def write(self, data: bytes) -> int:
        self += data
        self.written += len(data)
        return len(data)

    def tell(self) -> int:
        return self.written

    def flush(self) -> None:
        pass


class RemoteRecorder(Recorder):
    """One run's log, recorded by the service's child process (the interface and counters of
    :class:`~rt_controller.runtime.recorder.CycleRecorder`). ``record_*`` encode at once; the
    tick's records reach the pipe with its cycle record. Counters are this process's until
    :meth:`close`, then the child's final ones plus what this process dropped."""

    def __init__(self, service: RecorderService, path: Path, backpressure: bool) -> None:
        self.path = path
        self._service = service
        self._backpressure = backpressure
        self.closed = False
        self.error: str | None = None
        """Why the log is incomplete (the child's writer failed, or the child died)."""
        self._sent: Counter[int] = Counter()
        self._dropped = self._encode_errors = 0
        self._final: dict[str, Any] | None = None
        """The child's counters of the finished log."""
        self._lock = threading.Lock()  # images and Sync-paced features come from zenoh's thread
        self._writer = Writer(
            service.outbox,
            use_chunking=False,
            index_types=IndexType.NONE,
            repeat_channels=False,
            repeat_schemas=False,
            use_statistics=False,
            use_summary_offsets=False,
            enable_crcs=False,
        )
        self._writer.start(library="hil-rt_controller")
        topics = {**TOPICS, IMAGE: IMAGE_TOPIC}
        encoding = {IMAGE: "hil.vision_image"}
        self._channels = {
            kind: self._writer.register_channel(topic, encoding.get(kind, "json"), 0)
            for kind, topic in topics.items()
        }

    def write(self, kind: int, t_ns: int, obj: Any, final: bool = False) -> bool:
        """Encode one record item into the stream; a cycle or diagnostics record sends the
        tick's records to the pipe (a final one even past the outbox's limit: it carries the
        run's totals)."""
        try:
            data = bytes(obj) if kind == IMAGE else encode_record(kind, int(t_ns), obj)
        except _ENCODE_ERRORS:
            self._encode_errors += 1
            return False
        with self._lock:
            if self.closed or not self._service.room(self._backpressure or final):
                self._dropped += 1
                return False
            self._writer.add_message(self._channels[kind], int(t_ns), data, int(t_ns))
            self._sent[kind] += 1
            self._service.queued += 1
            if kind in (CYCLE, DIAG):
                self._service.send(wait=self._backpressure or final)
        return not self._service.dead

    def lost(self, n: int) -> None:
        """``n`` records sent that the child will never get (it died)."""
        self._dropped += n

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        with self._lock:
            self._writer.add_metadata(name, data)

    def stream_live(self) -> None:
        """Ask the child to publish this log's cycle and diagnostics records on zenoh."""
        self.add_metadata(LIVE_METADATA, self._service.link)
        self._service.send(wait=True)

    def end_stream(self) -> bool:
        """Refuse later records and end this log's MCAP stream (False: it was ended)."""
        with self._lock:
            if self.closed:
                return False
            self.closed = True
            self._writer.finish()
            return True

    def close(self, timeout: float | None = REPLY_TIMEOUT_S) -> None:
        """End the stream of this log, wait for the child's final counters. Idempotent."""
        if not self.end_stream():
            return
        self._final = self._service.finish(self, REPLY_TIMEOUT_S if timeout is None else timeout)

    @property
    def finished(self) -> bool:
        """The child finished the file cleanly (summary and footer written)."""
        return bool(self._final and self._final.get("finished"))

    @property
    def written(self) -> int:
        return self.as_dict()["written"]

    @property
    def dropped(self) -> int:
        return self.as_dict()["dropped"]

    @property
    def pending(self) -> int:
        return 0

    def as_dict(self) -> dict[str, int]:
        """The keys of ``CycleRecorder.as_dict``: the child's counts of the finished log, else
        what this process sent; ``backlog_bytes``: the stream's bytes in the outbox and the pipe
        (the child has not read them yet)."""
        final = self._final or {}
        counts = {t: int(final.get(t, self._sent[k])) for k, t in TOPICS.items()}
        counts.update(
            written=sum(counts.values()),
            dropped=self._dropped + int(final.get("dropped", 0)),
            encode_errors=self._encode_errors + int(final.get("encode_errors", 0)),
            pending=0,
            backlog_bytes=0 if self.closed else self._service.backlog_bytes(),
        )
        return counts


class RecorderService:
    """The recorder's child process and the two pipes to it (see the module docstring): ``cfg``
    (and ``zenoh_endpoint`` / ``zenoh_config``) for the live stream's session. One log at a
    time; :meth:`close` ends the child."""

    outbox_limit = 8 << 20
    """Bytes that may wait for the pipe; a realtime record beyond them is dropped and counted."""

    def __init__(
        self,
        cfg: RigConfig,
        *,
        zenoh_endpoint: str | None = None,
        zenoh_config: str | None = None,
    ) -> None:
        self.link = {"endpoint": zenoh_endpoint or "", "config": zenoh_config or ""}
        """Where the child opens the live stream's session (empty: the log's configuration)."""
        self.outbox = _Outbox()
        self.queued = 0
        """Records in the outbox, at most (it was last empty before them)."""
        self._answers = bytearray()
        self.dead: str | None = None
        """Why the child is gone (None while it serves)."""
        self._open: RemoteRecorder | None = None
        self._closed = False
        env = {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD), **os.environ}
        self._child = subprocess.Popen(
            [sys.executable, "-c", LAUNCH], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env
        )
        self.pid = self._child.pid
        self.start_method = "spawn"
        """How the child was started (a fresh interpreter), for the ``hil.run`` metadata."""
        self._out, self._in = self._child.stdin.fileno(), self._child.stdout.fileno()
        with contextlib.suppress(OSError):
            fcntl.fcntl(self._out, fcntl.F_SETPIPE_SZ, 1 << 20)  # Linux's unprivileged maximum
        os.set_blocking(self._out, False)
        os.set_blocking(self._in, False)

    def open(
        self,
        path: str | os.PathLike[str],
        cfg: RigConfig,
        *,
        run_info: dict[str, Any] | None = None,
        scene: bool = False,
        backpressure: bool = False,
        flush_interval_s: float = 1.0,
    ) -> RemoteRecorder:
        """Create the log ``path`` in the child (as ``CycleRecorder(path, cfg, ...)`` would,
        ``scene`` drawing the arm from ``cfg``); :class:`LogError` if it cannot."""
        if self._open is not None:
            raise LogError(f"the recorder process is still writing {self._open.path}")
        if self.dead or self._closed:
            raise LogError(f"cannot create MCAP log {path}: {self.dead or 'service closed'}")
        mono_ns, unix_ns = time.monotonic_ns(), time.time_ns()
        info = default_run_info(cfg, mono_ns, unix_ns)  # this process's pid, argv, ...
        info.update({str(k): str(v) for k, v in (run_info or {}).items()})
        rec = self._open = RemoteRecorder(self, Path(path), backpressure)
        how = {"path": str(path), "scene": "1" if scene else "0"}
        rec.add_metadata(LOG_METADATA, {**how, "flush_interval_s": repr(flush_interval_s)})
        rec.add_metadata(CONFIG_METADATA, {"json": cfg.to_json()})
        rec.add_metadata(RUN_METADATA, info)
        self.send(wait=True)
        answer = self._answer("opened", REPLY_TIMEOUT_S)
        if answer is None or answer["error"]:
            rec.end_stream()  # the child reads on to the next log's stream
            self.send(wait=True)
            self._open = None
            error = self.dead or "no answer" if answer is None else answer["error"]
            raise LogError(error if answer else f"cannot create MCAP log {path}: {error}")
        return rec

    def room(self, wait: bool) -> bool:
        """Whether a record may join the outbox (never when the child is gone; when ``wait``
        is false, only while the outbox is under its limit)."""
        if self.dead is not None:
            return False
        if wait or len(self.outbox) <= self.outbox_limit:
            return True
        self._pump()
        return len(self.outbox) <= self.outbox_limit

    def send(self, *, wait: bool) -> None:
        """Write what the pipe takes now; with ``wait`` (lockstep, the run's final record, a
        control record) all of it, however long the child takes."""
        self._pump()
        deadline = time.monotonic() + REPLY_TIMEOUT_S
        while wait and self.outbox and self.dead is None:
            if time.monotonic() >= deadline:
                self._die(f"the recorder process took nothing for {REPLY_TIMEOUT_S:g} s")
                break
            select.select([], [self._out], [], 0.1)
            self._pump()

    def _pump(self) -> None:
        """Write what the pipe takes now (never blocks)."""
        out = self.outbox
        while out and self.dead is None:
            try:
                n = os.write(self._out, out)
            except BlockingIOError:
                return
            except OSError as exc:  # EPIPE: the child is gone
                self._die(f"the recorder process is gone ({exc.strerror or exc})")
                return
            del out[:n]
        self.queued = 0

    def backlog_bytes(self) -> int:
        """The stream's bytes the child has not read: the outbox and the pipe's content."""
        buf = bytearray(4)
        try:
            fcntl.ioctl(self._out, termios.FIONREAD, buf)
        except OSError:
            return len(self.outbox)
        return len(self.outbox) + int.from_bytes(buf, "little")

    def finish(self, rec: RemoteRecorder, timeout: float) -> dict[str, Any] | None:
        """Send the end of ``rec``'s stream and wait for the child's final counters."""
        self.send(wait=True)
        answer = self._answer("closed", timeout)
        if self._open is rec:
            self._open = None
        if answer is None:
            why = self.dead or f"the recorder process did not finish the log in {timeout:g} s"
            rec.error = rec.error or why
            return None
        rec.error = rec.error or answer["error"]
        return {**answer["counts"]}

    def _answer(self, kind: str, timeout: float) -> dict[str, Any] | None:
        """The child's next answer of ``kind`` (None: it died, or ``timeout`` ran out)."""
        deadline = time.monotonic() + timeout
        while True:
            line, nl, rest = self._answers.partition(b"\n")
            if nl:
                self._answers = bytearray(rest)
                answer = json.loads(line)
                if kind in answer:
                    return answer
                continue
            left = deadline - time.monotonic()
            if self.dead is not None or left <= 0:
                return None
            if not select.select([self._in], [], [], min(left, 0.1))[0]:
                continue
            try:
                data = os.read(self._in, 1 << 16)
            except BlockingIOError:
                continue
            except OSError as exc:
                data, why = b"", f" ({exc.strerror or exc})"
            else:
                why = self._exit_note()
            if not data:
                self._die(f"the recorder process exited{why}")
            self._answers += data

    def _die(self, reason: str) -> None:
        """The child is gone: the records still in the outbox are lost (counted)."""
        if self.dead is None:
            self.dead = reason
            if self._open is not None:
                self._open.error = self._open.error or reason
                self._open.lost(self.queued)
            self.outbox.clear()

    def close(self, timeout: float = REPLY_TIMEOUT_S) -> None:
        """Close the log still open, end the child (end of file on its pipe) and reap it.
        Idempotent."""
        if self._closed:
            return
        if self._open is not None:
            self._open.close(timeout)
        self._closed = True
        self._child.stdin.close()  # end of file: the child exits
        try:
            self._child.wait(timeout)
        except subprocess.TimeoutExpired:
            self._child.kill()
            self._child.wait()
        self._child.stdout.close()

    def _exit_note(self) -> str:
        """`` (status N)`` or `` (killed by signal N)`` once the child has exited, else ``""``."""
        try:
            status = self._child.wait(0.2)
        except subprocess.TimeoutExpired:
            return ""
        return f" (killed by signal {-status})" if status < 0 else f" (status {status})"

    def __enter__(self) -> RecorderService:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
