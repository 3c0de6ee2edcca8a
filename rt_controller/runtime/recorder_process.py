"""A run's log written by a process of its own, so the control process runs no other thread.

:class:`RecorderProcess` is the daemon's recorder. The loop publishes each record once, as the
MCAP message it will be in the log: encoded here, framed by mcap's own ``Writer`` into a plain
MCAP stream (unchunked), written to the child's standard input once per tick. The child
(:func:`serve`, a fresh interpreter) reads it with mcap's ``StreamReader``, writes the file
with :class:`~rt_controller.runtime.recorder.CycleRecorder` (chunked, compressed, indexed, the
scene drawn, camera images converted, a ``cia402`` run's CANopen frames decoded), publishes
the live stream, and at the end of its input prints the log's counters as one JSON line. No
protocol of our own crosses the pipes.

A realtime tick never blocks on the child: the pipe is non-blocking (1 MiB where the kernel
allows it), what it cannot take waits in an outbox, and a record that would grow the outbox past
:attr:`RecorderProcess.outbox_limit` bytes is dropped and counted (the run is then not clean).
Lockstep has no deadline: there the tick waits for the child (``backpressure``), so a
Sync-paced log is never short because the host was busy. The child ignores SIGINT, SIGTERM and
SIGHUP (the controller decides when the log ends) and finishes the log at the end of its input,
so the log of a SIGKILLed controller is complete too.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import select
import signal
import struct
import subprocess
import sys
import termios
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import IndexType, Writer

from hal.config import RigConfig, config_from_json
from hal.fifo import raise_nice
from hal.zenoh_session import KEY_VISION_IMAGE
from rt_controller.errors import LogError
from rt_controller.runtime.recorder import (
    CONFIG_METADATA,
    CYCLE,
    DECODED_TOPICS,
    DIAG,
    IMAGE,
    RUN_METADATA,
    TOPICS,
    WRITER_COUNTERS,
    CycleRecorder,
    Recorder,
    run_metadata,
)

TIMEOUT_S = 30.0
"""How long a lockstep tick or the end of the log waits for the child."""
KIND_OF_TOPIC = {**{topic: kind for kind, topic in TOPICS.items()}, KEY_VISION_IMAGE: IMAGE}
MMAP_THRESHOLD = 128 << 10
"""glibc's mmap threshold for the recorder process, fixed: buffers of a chunk or a camera image
are mapped and given back when freed. Left to glibc, the threshold grows to the largest buffer
freed and the heap keeps what it grew to (the soak, ``hil bench soak``, watches the RSS)."""
START_TIMEOUT_S = 60.0
"""How long the log's start waits for the child to have opened the file (its imports included:
seconds on a slow host such as user-mode Linux)."""
READY = b"ready\n"
"""The child's line once the log is open (or failed to open): the run may start."""
LOCKSTEP_NICE = 10
"""Lockstep (``backpressure``): the recorder process's nice value is raised by this much. A
Sync-paced period is a chain through the emulator, the vision process and the controller that
waits for nothing else; the log is off that chain and, at the same priority, takes a core from
it on a small host (docs/benchmarks.md, "Design choices, measured"). It still has every idle
moment of a core, and the tick waits for it when the pipe is full, so nothing is lost.
Realtime keeps the default: there a starved recorder would drop records."""
IDLE_S = 0.25
"""How often the waiting child looks whether the log is due for a flush."""


class _Outbox(bytearray):
    """The bytes of the stream not yet in the pipe (the file the stream's ``Writer`` writes)."""

    written = 0

    def write(self, data: bytes) -> int:
        self += data
        self.written += len(data)
        return len(data)

    def tell(self) -> int:
        return self.written

    def flush(self) -> None:
        pass


def _demote(pid: int, nice: int = 0) -> None:
    """Best effort, before the child has imported anything: it must not compete with a
    SCHED_FIFO loop that started it (a later run of a plan: the policy and a single-CPU
    affinity are inherited); ``nice``: raise its nice value by that much (its threads
    inherit it)."""
    if nice > 0:
        raise_nice(pid, nice)
    try:
        os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))
        cpus, everything = os.sched_getaffinity(pid), set(range(os.cpu_count() or 1))
        if len(cpus) == 1 and len(everything) > 1:
            os.sched_setaffinity(pid, everything - cpus)
    except OSError:
        pass


class RecorderProcess(Recorder):
    """One run's log ``path`` of ``cfg``, written by a child process (see the module
    docstring), with :class:`CycleRecorder`'s arguments and counters: this process's until
    :meth:`close`, then the child's final ones plus what this process dropped. ``live``:
    the child publishes the cycle and diagnostics records on zenoh (``cfg.transport``).
    ``replace=False`` refuses an existing ``path`` (it is created with ``O_EXCL``: a file made
    after the command line checked it is not replaced either). ``stop`` set: the start no longer
    waits for the child (which gives up waiting for the live stream's hub once its input ends)."""

    outbox_limit = 8 << 20
    """Bytes that may wait for the pipe; a realtime record beyond them is dropped and counted."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        cfg: RigConfig,
        *,
        run_info: dict[str, Any] | None = None,
        scene: bool = False,
        live: bool = False,
        backpressure: bool = False,
        flush_interval_s: float = 1.0,
        replace: bool = True,
        stop: threading.Event | None = None,
    ) -> None:
        self.path = Path(path)
        try:  # a bad path is this process's clear error, before the child starts
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.open("wb" if replace else "xb").close()
        except FileExistsError:
            if not self.path.parent.is_dir():
                raise LogError(f"cannot create MCAP log {path}: not a directory") from None
            raise LogError(f"{path}: exists (pass --force to replace it)") from None
        except OSError as exc:
            raise LogError(f"cannot create MCAP log {path}: {exc.strerror or exc}") from exc
        self._backpressure = backpressure
        self.error: str | None = None
        """Why the log is incomplete (the child's writer failed, or the child died)."""
        self.dead: str | None = None
        """Why the child is gone before the end of the log (None while it serves)."""
        self._outbox = _Outbox()
        self._queued = 0  # records in the outbox, at most (it was last empty before them)
        self.counts: Counter[int] = Counter()  # sent; the child's written once it finished
        self.confirmed = False
        """Whether :attr:`counts` are the child's own (it finished); else records sent to it."""
        self._lock = threading.Lock()  # images and Sync-paced features come from zenoh's thread
        how = json.dumps(
            {"path": str(path), "scene": scene, "live": live, "flush": flush_interval_s}
        )
        self._child = subprocess.Popen(
            [sys.executable, "-c", LAUNCH, how],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env={"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD), **os.environ},
        )
        self.pid = self._child.pid
        _demote(self.pid, LOCKSTEP_NICE if backpressure else 0)
        self._pipe = self._child.stdin.fileno()
        with contextlib.suppress(OSError):
            fcntl.fcntl(self._pipe, fcntl.F_SETPIPE_SZ, 1 << 20)  # Linux's unprivileged maximum
        os.set_blocking(self._pipe, False)
        w = self._writer = Writer(
            self._outbox,
            use_chunking=False,
            index_types=IndexType.NONE,
            repeat_channels=False,
            repeat_schemas=False,
            use_statistics=False,
            use_summary_offsets=False,
            enable_crcs=False,
        )
        w.start(library="hil-rt_controller")
        self._channels = {k: w.register_channel(t, "json", 0) for k, t in TOPICS.items()}
        self._channels[IMAGE] = w.register_channel(KEY_VISION_IMAGE, "hil.vision_image", 0)
        # the stream names the camera images by their zenoh key; the file gets protobuf topics
        w.add_metadata(CONFIG_METADATA, {"json": cfg.to_json()})
        w.add_metadata(RUN_METADATA, run_metadata(cfg, run_info))  # this process's pid, argv
        self._send(wait=True)
        self._printed = self._await_start(stop or threading.Event())

    def _await_start(self, stop: threading.Event) -> bytes:
        """Wait for the child's :data:`READY`: its start-up (imports, the file opened) is then
        behind it, not inside the run, where a lockstep tick would wait on a pipe nobody reads
        yet. What the child printed (the result comes later on the same pipe)."""
        fd, printed = self._child.stdout.fileno(), b""
        deadline = time.monotonic() + START_TIMEOUT_S
        while READY not in printed and self.dead is None and not stop.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                self._die(f"the recorder process did not start in {START_TIMEOUT_S:g} s")
            elif select.select([fd], [], [], min(left, 0.1))[0]:
                data = os.read(fd, 4096)
                if not data:
                    self._die("the recorder process exited before it opened the log")
                printed += data
        return printed

    def add(self, kind: int, t_ns: int, data: bytes, obj: Any = None, final: bool = False) -> bool:
        """Put one encoded record into the stream; a cycle or diagnostics record sends the
        tick's records to the pipe (a final one even past the outbox's limit: it carries the
        run's totals)."""
        wait = self._backpressure or final
        with self._lock:
            if self.closed or not self._room(wait):
                self.dropped += 1
                return False
            self._writer.add_message(self._channels[kind], t_ns, data, t_ns)
            self.counts[kind] += 1
            self.images_written += kind == IMAGE  # sent, as the topics' counts, until close
            self._queued += 1
            if kind in (CYCLE, DIAG):
                self._send(wait)
        return self.dead is None

    def _room(self, wait: bool) -> bool:
        """Whether a record may join the outbox (never when the child is gone; unless ``wait``,
        only while the outbox is under its limit)."""
        if self.dead is not None:
            return False
        if not wait and len(self._outbox) > self.outbox_limit:
            self._pump()
        return wait or len(self._outbox) <= self.outbox_limit

    def _send(self, wait: bool) -> None:
        """Write what the pipe takes now; with ``wait`` all of it, however long the child takes
        (up to :data:`TIMEOUT_S` without progress)."""
        self._pump()
        deadline = time.monotonic() + TIMEOUT_S
        while wait and self._outbox and self.dead is None:
            if time.monotonic() >= deadline:
                self._die(f"the recorder process took nothing for {TIMEOUT_S:g} s")
            elif select.select([], [self._pipe], [], 0.1)[1]:
                self._pump()
                deadline = time.monotonic() + TIMEOUT_S

    def _pump(self) -> None:
        """Write what the pipe takes now (never blocks)."""
        out = self._outbox
        while out and self.dead is None:
            try:
                n = os.write(self._pipe, out)
            except BlockingIOError:
                return
            except OSError as exc:  # EPIPE: the child is gone
                self._die(f"the recorder process is gone ({exc.strerror or exc})")
                return
            del out[:n]
        self._queued = 0

    def _die(self, reason: str) -> None:
        """The child is gone: the records still in the outbox are lost (counted)."""
        if self.dead is None:
            self.dead = self.error = reason
            self.dropped += self._queued
            self._outbox.clear()

    def backlog_bytes(self) -> int:
        """The stream's bytes the child has not read: the outbox and the pipe's content."""
        buf = bytearray(4)
        with contextlib.suppress(OSError):
            fcntl.ioctl(self._pipe, termios.FIONREAD, buf)
        return len(self._outbox) + int.from_bytes(buf, "little")

    def close(self, timeout: float = TIMEOUT_S) -> None:
        """End the stream, wait for the child to finish the file, take its final counters.
        Idempotent."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._writer.finish()
            self._send(wait=True)
        try:
            out, _ = self._child.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self._child.kill()
            out, _ = self._child.communicate()
            self._die(f"the recorder process did not finish the log in {timeout:g} s")
        status = self._child.returncode
        results = [line for line in (self._printed + out).splitlines() if line.startswith(b"{")]
        if not results:  # it died before the end of its input (what the pipe said is replaced)
            self._die("")
            self.dead = self.error = f"the recorder process {_ended(status)} before the log's end"
            return
        final = json.loads(results[-1])
        self.error = self.error or final["error"]
        if "written" in final:  # the child wrote the log: its counts replace what was sent
            self.counts = Counter({k: final[t] for k, t in TOPICS.items()})
            self.counts.update({k: final[t] for k, t in DECODED_TOPICS.items() if t in final})
            self.dropped += final["dropped"]
            for key in WRITER_COUNTERS:
                setattr(self, key, int(final.get(key, 0)))
            self.finished = final["finished"]
            self.confirmed = True

    def as_dict(self) -> dict[str, int]:
        """The counters; once closed without the child's own counts (it died), ``written`` is
        ``sent``: what reached the file is the log's to say, not this process's."""
        out = super().as_dict()
        if self.closed and not self.confirmed:
            out["sent"] = out.pop("written")
        return out


def _ended(status: int) -> str:
    """``was killed by SIGKILL`` or ``exited with status 1``."""
    if status >= 0:
        return f"exited with status {status}"
    try:
        return f"was killed by {signal.Signals(-status).name}"
    except ValueError:
        return f"was killed by signal {-status}"


class _PipeInput:
    """The child's standard input as the file ``StreamReader`` reads: ``read(n)`` gives ``n``
    bytes (fewer only at its end) and calls ``idle`` while it waits. The reader asks for each
    field of a record on its own (1, 8, 2, 4 bytes...), so the pipe is read in large blocks
    into a buffer and the fields are served from it, not one system call each."""

    def __init__(self, idle: Any) -> None:
        self.idle = idle
        self.eof = False
        self._buf = bytearray()

    def read(self, n: int = -1) -> bytes:
        buf = self._buf
        while len(buf) < n and not self.eof:
            if not select.select([0], [], [], IDLE_S)[0]:
                self.idle()
                continue
            data = os.read(0, 1 << 20)
            self.eof = not data
            buf += data
        out = bytes(buf[: max(n, 0)])
        del buf[: len(out)]
        return out


class _LogCopy:
    """The child's side: the stream's records into the file and the live stream."""

    def __init__(self, how: dict[str, Any]) -> None:
        self.how = how
        self.rec: CycleRecorder | None = None
        self.error: str | None = None
        self.kinds: dict[int, int] = {}
        self.cfg_json = ""
        self.session: Any = None

    def handle(self, record: Any) -> None:
        if isinstance(record, Message):
            kind = self.kinds.get(record.channel_id)
            if self.rec is not None and kind is not None:
                self.rec.add(kind, record.log_time, record.data)
        elif isinstance(record, Channel):
            self.kinds[record.id] = KIND_OF_TOPIC[record.topic]
        elif isinstance(record, Metadata) and record.name == CONFIG_METADATA:
            self.cfg_json = record.metadata["json"]
        elif isinstance(record, Metadata) and record.name == RUN_METADATA:
            try:
                self.rec = self.open(config_from_json(self.cfg_json), record.metadata)
            except Exception as exc:  # the stream is still read to its end
                self.error = str(exc) or type(exc).__name__
            with contextlib.suppress(OSError):
                os.write(1, READY)

    def open(self, cfg: RigConfig, info: dict[str, str]) -> CycleRecorder:
        scene = None
        if self.how["scene"]:
            from rt_controller.monitor.scene import SceneBuilder

            scene = SceneBuilder(cfg)
        rec = CycleRecorder(
            self.how["path"], cfg, run_info=info, flush_interval_s=self.how["flush"], scene=scene
        )
        if self.how["live"]:
            from hal.errors import HalError
            from hal.zenoh_session import open_session
            from rt_controller.monitor.live import LivePublisher

            try:  # the controller may end the stream before the hub answers (stopped)
                self.session = open_session(cfg, listen=False, wait_s=5.0, stop_event=_hang_up())
                rec.live = LivePublisher(self.session)
            except HalError as exc:
                print(f"hil controller: warning: no live stream: {exc}", file=sys.stderr)
        return rec

    def idle(self) -> None:
        if self.rec is not None:
            self.rec.flush_if_due()  # a quiet log still reaches the disk

    def close(self) -> dict[str, Any]:
        """Finish the file; its counters, ``finished`` and ``error``."""
        rec = self.rec
        if rec is None:
            return {"finished": False, "error": self.error or "no log in the stream"}
        rec.close()
        if rec.live is not None:
            rec.live.close()
        if self.session is not None:
            self.session.close()
        error = str(rec.error) if rec.error else None
        if not (error or rec.finished):
            error = "the writer did not finish the file"
        return {**rec.as_dict(), "finished": rec.finished, "error": error}


def _hang_up() -> threading.Event:
    """Set once the controller has closed the child's standard input (POLLHUP: its stream is
    complete, or the controller is gone), whatever the pipe still holds."""
    ended = threading.Event()

    def watch() -> None:
        poll = select.poll()
        poll.register(0, 0)  # no events asked: POLLHUP and POLLERR are always reported
        while not poll.poll():
            pass
        ended.set()

    threading.Thread(target=watch, name="stream-end", daemon=True).start()
    return ended


def serve(how: str) -> None:
    """The child's program: the log's MCAP stream from standard input into the file, then the
    log's counters as one JSON line on standard output. Warnings go to stderr."""
    copy = _LogCopy(json.loads(how))
    pipe = _PipeInput(copy.idle)
    try:
        for record in StreamReader(pipe, record_size_limit=None).records:
            copy.handle(record)  # the stream ends after the Footer's magic
    except (McapError, struct.error, ValueError) as exc:  # the controller died mid-log
        if not pipe.eof:
            print(f"hil controller: recorder: bad record stream: {exc}", file=sys.stderr)
    result = json.dumps(copy.close()).encode() + b"\n"
    with contextlib.suppress(OSError):  # the controller is gone: the log is finished all the same
        os.write(1, result)


LAUNCH = (
    "import signal, sys\n"
    "for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP): signal.signal(s, signal.SIG_IGN)\n"
    "from rt_controller.runtime.recorder_process import serve\n"
    "serve(sys.argv[1])\n"
)
"""The child's program (``python -c``): signals ignored before anything is imported."""
