"""The MCAP recorder in a process of its own, so the control process runs no other Python thread.

:class:`RecorderService` starts one child process for a controller process (the runs of a plan
share it); :meth:`RecorderService.open` gives a :class:`RemoteRecorder`, which the daemon uses
like a :class:`~rt_controller.runtime.recorder.CycleRecorder`. In the control thread a record
costs a list append; once per tick, with the cycle record, the tick's batch is pickled and
written to a pipe. The child owns a ``CycleRecorder`` (JSON encoding, MCAP writer, zstd chunks,
the Foxglove scene) and the live zenoh stream (``hil/controller/cycle``, ``.../diagnostics``) on
a session of its own. Nothing in the control process takes the GIL from a tick.

A realtime tick never blocks on the child: the pipe is non-blocking (1 MiB where the kernel
allows it), what it cannot take waits in an outbox, and a batch that would grow the outbox past
:attr:`RecorderService.outbox_limit` bytes is dropped and counted (``dropped``: the run reports
the loss and exits non-zero). Lockstep has no deadline: there the tick waits for the child
(``backpressure``), so a lockstep log is never short because the host was busy.

The child is forked while the controller process still has a single OS thread (no zenoh or CAN
threads yet; the start costs a millisecond and the imported modules are shared); otherwise it is
spawned with ``python -m rt_controller.runtime.recorder_process``. It ignores SIGINT, SIGTERM and
SIGHUP (a Ctrl-C reaches the whole process group; the controller decides when its logs end) and
finishes every open log when its pipe reaches end of file, so the logs of a controller that was
SIGKILLed are still complete.

Wire format, both directions: a 4-byte little-endian length, then a pickled tuple. Parent to
child: ``(LINK, cfg_json, zenoh_endpoint, zenoh_config)`` first, then ``(OPEN, rid, path,
cfg_json, run_info, scene, flush_interval_s)``, ``(RECORDS, rid, items)``, ``(LIVE, rid)`` and
``(CLOSE, rid)``. Child to parent: ``(OPENED, rid, error)`` and ``(COUNTS, rid, counts, error,
final)``.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import logging
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import time
from collections import namedtuple
from pathlib import Path
from typing import Any

from hal.config import RigConfig
from rt_controller.errors import LogError
from rt_controller.runtime.recorder import _CAN_RX, _CAN_TX, _CYCLE, _DIAG, _TOPICS, _VISION

LINK, OPEN, RECORDS, LIVE, CLOSE = "link", "open", "records", "live", "close"
OPENED, COUNTS = "opened", "counts"
_HEADER = struct.Struct("<I")
_PIPE_SIZE = 1 << 20
"""Requested pipe capacity (``F_SETPIPE_SZ``; Linux's default unprivileged maximum)."""
_READ_SIZE = 1 << 20
REPLY_TIMEOUT_S = 30.0
"""How long opening or closing a log waits for the child's answer."""
COUNTS_EVERY_S = 0.25
"""The child reports a log's counters at most this often (and at its close)."""
_DIRECTION_OF = {_CAN_RX: "rx", _CAN_TX: "tx"}
log = logging.getLogger(__name__)

CanFrame = namedtuple(
    "CanFrame",
    "arbitration_id is_extended_id dlc data is_fd bitrate_switch is_error_frame "
    "is_remote_frame channel timestamp",
)
"""A received or sent CAN frame as it crosses the pipe (the attributes of a python-can
``Message`` that the ``/hal/can/*`` records keep)."""


def can_frame(msg: Any) -> CanFrame:
    """The picklable :class:`CanFrame` of a python-can ``Message``."""
    channel = msg.channel
    return CanFrame(
        msg.arbitration_id,
        msg.is_extended_id,
        msg.dlc,
        bytes(msg.data),
        msg.is_fd,
        msg.bitrate_switch,
        msg.is_error_frame,
        msg.is_remote_frame,
        "" if channel is None else str(channel),
        msg.timestamp,
    )


_UNPICKLABLE = (pickle.PicklingError, TypeError, AttributeError, ValueError, RecursionError)


def _picklable(obj: Any) -> bool:
    try:
        pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    except _UNPICKLABLE:
        return False
    return True


def _frame(message: tuple) -> bytes:
    body = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    return _HEADER.pack(len(body)) + body


def _split_frames(buf: bytearray) -> list[tuple]:
    """Remove and unpickle every whole frame at the start of ``buf``."""
    out, pos, size = [], 0, len(buf)
    while size - pos >= _HEADER.size:
        (n,) = _HEADER.unpack_from(buf, pos)
        if size - pos - _HEADER.size < n:
            break
        start = pos + _HEADER.size
        out.append(pickle.loads(buf[start : start + n]))
        pos = start + n
    del buf[:pos]
    return out


def _grow_pipe(fd: int) -> None:
    with contextlib.suppress(OSError, AttributeError):
        fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, _PIPE_SIZE)


def _os_threads() -> int:
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 2  # unknown: do not fork


class RemoteRecorder:
    """One run's log, recorded by the service's child process (the interface of
    :class:`~rt_controller.runtime.recorder.CycleRecorder` that the daemon uses).

    The ``record_*`` methods take ownership of what they are given, as ``CycleRecorder``'s do.
    Counters come from the child's latest report (at most :data:`COUNTS_EVERY_S` old when
    :meth:`as_dict` reads it while the run goes on; exact after :meth:`close`); ``dropped`` adds
    the batches this process dropped.
    """

    def __init__(self, service: RecorderService, rid: int, path: Path, backpressure: bool):
        self.path = path
        self._service = service
        self._rid = rid
        self._backpressure = backpressure
        self._batch: collections.deque[tuple[int, int, Any, Any]] = collections.deque()
        """Records since the last send (a deque: lockstep feeds vision from zenoh's thread)."""
        self._closed = False
        self._sent = 0
        self._dropped = 0
        self._counts: dict[str, Any] = {}
        self._error: str | None = None
        self._final = False
        self._encode_errors = 0
        """Records that could not be pickled for the child (counted with its encode errors)."""

    # ----------------------------------------------------------------- hot path (loop thread)

    def record_can(self, msg: Any, t_ns: int, direction: str) -> bool:
        """Queue a python-can ``Message`` received (``"rx"``) or sent (``"tx"``) at ``t_ns``."""
        if direction == "rx":
            kind = _CAN_RX
        elif direction == "tx":
            kind = _CAN_TX
        else:
            raise LogError(f"CAN direction must be 'rx' or 'tx', got {direction!r}")
        if self._closed:
            self._dropped += 1
            return False
        self._batch.append((kind, t_ns, can_frame(msg), None))
        return True

    def record_vision(self, payload: bytes, t_ns: int) -> bool:
        """Queue a raw vision payload received at ``t_ns``."""
        if self._closed:
            self._dropped += 1
            return False
        self._batch.append((_VISION, t_ns, bytes(payload), None))
        return True

    def record_cycle(self, record: dict[str, Any]) -> bool:
        """Queue one tick and send the tick's batch to the child. False if it was dropped."""
        if self._closed:
            self._dropped += 1
            return False
        t_ns = record.get("t_ns")
        self._batch.append((_CYCLE, time.monotonic_ns() if t_ns is None else t_ns, record, None))
        return self.send()

    def record_diagnostics(self, record: dict[str, Any], *, final: bool = False) -> bool:
        """Queue one ``/diagnostics`` record and send the batch (a final record is sent even
        when the outbox is full: it carries the run's totals)."""
        if self._closed:
            self._dropped += 1
            return False
        self._batch.append((_DIAG, int(record["t_ns"]), record, None))
        return self.send(force=final)

    def send(self, *, force: bool = False) -> bool:
        """Hand the records queued since the last send to the child; False if any was
        dropped (the outbox was full) or could not be pickled (counted in ``encode_errors``)."""
        queued = self._batch
        if not queued:
            return True
        pop = queued.popleft
        batch = [pop() for _ in range(len(queued))]
        wait, lost = self._backpressure or force, 0
        try:
            ok = self._service.send_records(self._rid, batch, wait)
        except _UNPICKLABLE:  # a record of a type that cannot cross: count it, keep the rest
            good = [item for item in batch if _picklable(item)]
            lost, batch = len(batch) - len(good), good
            if not self._encode_errors:
                log.warning("recorder: a record cannot be sent to the recorder process")
            self._encode_errors += lost
            ok = self._service.send_records(self._rid, batch, wait)
        if ok:
            self._sent += len(batch)
        else:
            self._dropped += len(batch)
        return ok and not lost

    # ----------------------------------------------------------------- control

    def stream_live(self) -> None:
        """Ask the child to publish this log's cycle and diagnostics records on zenoh."""
        self._service.send_control((LIVE, self._rid))

    def _update(self, counts: dict[str, Any], error: str | None, final: bool) -> None:
        self._counts = counts
        if error and not self._error:
            self._error = error
        self._final = self._final or final

    def _lost(self, reason: str) -> None:
        self._error = self._error or reason

    def close(self, timeout: float | None = REPLY_TIMEOUT_S) -> None:
        """Send what is queued, ask the child to finish the file and wait for its final
        counters. Idempotent."""
        if self._closed:
            return
        self.send(force=True)
        self._closed = True
        self._service.finish(self._rid, REPLY_TIMEOUT_S if timeout is None else timeout)

    # ----------------------------------------------------------------- counters

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def finished(self) -> bool:
        """The child finished the file cleanly (summary and footer written)."""
        return self._final and bool(self._counts.get("finished"))

    @property
    def error(self) -> str | None:
        """Why the log is incomplete (the child's writer failed, or the child died)."""
        return self._error

    @property
    def written(self) -> int:
        return int(self._counts.get("written", 0))

    @property
    def dropped(self) -> int:
        return self._dropped + int(self._counts.get("dropped", 0))

    @property
    def pending(self) -> int:
        """Records sent that the child has not written yet (as of its last report), plus those
        still queued here."""
        received = int(self._counts.get("received", 0))
        in_child = max(0, self._sent - received) + int(self._counts.get("pending", 0))
        return len(self._batch) + in_child

    def as_dict(self) -> dict[str, int]:
        """Counters per topic plus ``written``, ``dropped``, ``encode_errors`` and ``pending``
        (the keys of ``CycleRecorder.as_dict``), with the child's latest report."""
        self._service.poll()
        counts = self._counts
        out = {topic: int(counts.get(topic, 0)) for topic in _TOPICS.values()}
        out.update(
            written=self.written,
            dropped=self.dropped,
            encode_errors=self._encode_errors + int(counts.get("encode_errors", 0)),
            pending=self.pending,
        )
        return out

    def __enter__(self) -> RemoteRecorder:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close()
        if self._error is not None and exc_type is None:
            raise LogError(f"MCAP log {self.path} is incomplete: {self._error}")

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"RemoteRecorder({str(self.path)!r}, {state}, written={self.written})"


class RecorderService:
    """The recorder's child process and the two pipes to it (see the module docstring).

    Args:
        cfg: the rig configuration (the child's zenoh session for the live stream uses its
            transport section, with ``zenoh_endpoint`` / ``zenoh_config`` overriding it).
        start: ``"auto"`` (fork while this process has one OS thread, else spawn), ``"fork"``
            or ``"spawn"``.

    A context manager; :meth:`close` ends the child (it finishes any log still open).
    """

    outbox_limit = 8 << 20
    """Bytes that may wait for the pipe; a realtime batch beyond them is dropped and counted."""

    def __init__(
        self,
        cfg: RigConfig,
        *,
        zenoh_endpoint: str | None = None,
        zenoh_config: str | None = None,
        start: str = "auto",
    ) -> None:
        if start not in ("auto", "fork", "spawn"):
            raise LogError(f"recorder start must be auto, fork or spawn, not {start!r}")
        self._next_rid = 0
        self._recorders: dict[int, RemoteRecorder] = {}
        self._outbox = bytearray()
        self._inbox = bytearray()
        self._dead: str | None = None
        self._closed = False
        self._pid = 0
        self._status: int | None = None
        self._popen: subprocess.Popen[bytes] | None = None
        self._opened: dict[int, str | None] = {}
        child_in, self._out = os.pipe()
        self._in, child_out = os.pipe()
        _grow_pipe(self._out)
        fork = start == "fork" or (start == "auto" and _os_threads() == 1)
        self.start_method = "fork" if fork else "spawn"
        """How the child was started (``fork`` or ``spawn``)."""
        try:
            if self.start_method == "fork":
                self._fork(child_in, child_out)
            else:
                self._spawn(child_in, child_out)
        except BaseException:
            for fd in (self._out, self._in):
                os.close(fd)
            raise
        finally:
            os.close(child_in)
            os.close(child_out)
        os.set_blocking(self._out, False)
        os.set_blocking(self._in, False)
        self.send_control((LINK, cfg.to_json(), zenoh_endpoint, zenoh_config))

    def _fork(self, child_in: int, child_out: int) -> None:
        sys.stdout.flush()  # or the child would write the parent's buffered output again
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # the child: never returns into the caller's code
            status = 1
            try:
                os.close(self._out)
                os.close(self._in)
                serve(child_in, child_out)
                status = 0
            except BaseException as exc:  # report, then leave without the parent's cleanup
                with contextlib.suppress(Exception):
                    print(f"hil controller: recorder process failed: {exc}", file=sys.stderr)
            finally:
                with contextlib.suppress(Exception):
                    sys.stderr.flush()
                os._exit(status)
        self._pid = pid

    def _spawn(self, child_in: int, child_out: int) -> None:
        argv = [sys.executable, "-m", __name__, str(child_in), str(child_out)]
        quiet = subprocess.DEVNULL  # stdout is the controller's (its JSON summary)
        self._popen = subprocess.Popen(
            argv, pass_fds=(child_in, child_out), stdin=quiet, stdout=quiet
        )
        self._pid = self._popen.pid

    @property
    def pid(self) -> int:
        return self._pid

    # ----------------------------------------------------------------- logs

    def open(
        self,
        path: str | os.PathLike[str],
        cfg: RigConfig,
        *,
        run_info: dict[str, Any] | None = None,
        scene: bool = False,
        backpressure: bool = False,
        flush_interval_s: float = 0.5,
    ) -> RemoteRecorder:
        """Create the log ``path`` in the child (as ``CycleRecorder(path, cfg, ...)`` would,
        ``scene`` drawing the arm from ``cfg``); :class:`LogError` if it cannot."""
        from rt_controller.runtime.recorder import _default_run_info

        if not flush_interval_s > 0:
            raise LogError(f"flush_interval_s must be positive, got {flush_interval_s}")
        mono_ns, unix_ns = time.monotonic_ns(), time.time_ns()
        info = _default_run_info(cfg, mono_ns, unix_ns)  # this process's pid, argv, ...
        info.update({str(k): str(v) for k, v in (run_info or {}).items()})
        self._next_rid += 1
        rid = self._next_rid
        rec = RemoteRecorder(self, rid, Path(path), backpressure)
        self._recorders[rid] = rec
        self.send_control((OPEN, rid, str(path), cfg.to_json(), info, scene, flush_interval_s))
        reply = self._await(lambda: rid in self._opened, REPLY_TIMEOUT_S)
        error = self._opened.pop(rid, None) if reply else self._dead or "no answer"
        if error:
            self._recorders.pop(rid, None)
            raise LogError(error if reply else f"cannot create MCAP log {path}: {error}")
        return rec

    def send_records(self, rid: int, items: list, wait: bool) -> bool:
        """Queue one batch for the child; False (dropped) when the outbox is full and ``wait``
        is false, or the child is gone. The tick's only system call is the pipe write (the
        child's replies are read by :meth:`poll`, about once a second)."""
        if self._dead is not None or self._closed:
            return False
        if not wait and len(self._outbox) > self.outbox_limit:
            self._pump_out()
            if len(self._outbox) > self.outbox_limit:
                return False
        frame = _frame((RECORDS, rid, items))
        if self._outbox:  # keep the order: behind what waits already
            self._outbox += frame
            self._pump_out()
        else:  # the usual case: one write, no copy
            self._write_now(frame)
        if wait and len(self._outbox) > self.outbox_limit:
            self._drain_out(REPLY_TIMEOUT_S)
        return self._dead is None

    def send_control(self, message: tuple) -> None:
        """Queue a control message and wait until the pipe took it."""
        if self._dead is not None or self._closed:
            return
        self._outbox += _frame(message)
        self._drain_out(REPLY_TIMEOUT_S)

    def finish(self, rid: int, timeout: float) -> None:
        """Close log ``rid`` in the child and wait for its final counters."""
        rec = self._recorders.get(rid)
        if rec is None:
            return
        self.send_control((CLOSE, rid))
        if not self._await(lambda: rec._final, timeout):
            rec._lost(self._dead or f"the recorder process did not finish the log in {timeout:g} s")
        self._recorders.pop(rid, None)

    # ----------------------------------------------------------------- pipes

    def poll(self) -> None:
        """Apply the child's replies that arrived (counters, errors); never blocks."""
        self._pump_in()

    def _write_now(self, frame: bytes) -> None:
        """Write ``frame`` with the outbox empty; what the pipe does not take goes there."""
        try:
            n = os.write(self._out, frame)
        except BlockingIOError:
            n = 0
        except OSError as exc:  # EPIPE: the child is gone
            self._die(f"the recorder process is gone ({exc.strerror or exc})")
            return
        if n < len(frame):
            self._outbox += memoryview(frame)[n:]

    def _pump_out(self) -> None:
        """Write what the pipe takes now (never blocks)."""
        out = self._outbox
        while out:
            try:
                n = os.write(self._out, out)
            except BlockingIOError:
                return
            except OSError as exc:  # EPIPE: the child is gone
                self._die(f"the recorder process is gone ({exc.strerror or exc})")
                return
            del out[:n]

    def _drain_out(self, timeout: float) -> None:
        """Block until the outbox is empty, the child died or ``timeout`` ran out."""
        deadline = time.monotonic() + timeout
        while self._outbox and self._dead is None:
            self._pump_out()
            if not self._outbox:
                return
            left = deadline - time.monotonic()
            if left <= 0:
                self._die(f"the recorder process took nothing for {timeout:g} s")
                return
            readable, _, _ = select.select([self._in], [self._out], [], min(left, 0.1))
            if readable:
                self._pump_in()

    def _pump_in(self) -> None:
        """Read and apply the child's replies that arrived (never blocks)."""
        while True:
            try:
                data = os.read(self._in, _READ_SIZE)
            except BlockingIOError:
                break
            except OSError as exc:
                self._die(f"the recorder process is gone ({exc.strerror or exc})")
                return
            if not data:
                self._die(f"the recorder process exited{self._exit_status()}")
                break
            self._inbox += data
        for message in _split_frames(self._inbox):
            self._apply(message)

    def _apply(self, message: tuple) -> None:
        kind, rid = message[0], message[1]
        if kind == OPENED:
            self._opened[rid] = message[2]
        elif kind == COUNTS:
            rec = self._recorders.get(rid)
            if rec is not None:
                rec._update(message[2], message[3], message[4])

    def _await(self, done: Any, timeout: float) -> bool:
        """Read replies until ``done()`` holds (True), the child died or ``timeout`` ran out."""
        deadline = time.monotonic() + timeout
        while True:
            self._pump_in()
            if done():
                return True
            left = deadline - time.monotonic()
            if self._dead is not None or left <= 0:
                return False
            select.select([self._in], [], [], min(left, 0.1))

    def _exit_status(self) -> str:
        status = self._reap(0.2)
        if status is None:
            return ""
        if status < 0:
            return f" (killed by signal {-status})"
        return f" (status {status})"

    def _reap(self, timeout: float) -> int | None:
        """The child's exit status (negative: killed by that signal), None while it runs."""
        if self._status is not None:
            return self._status
        if self._popen is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._status = self._popen.wait(timeout)
            return self._status
        deadline = time.monotonic() + timeout
        while True:
            try:
                pid, status = os.waitpid(self._pid, os.WNOHANG)
            except ChildProcessError:  # reaped by someone else
                self._status = 0
                return 0
            if pid:
                self._status = os.waitstatus_to_exitcode(status)
                return self._status
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.005)

    def _die(self, reason: str) -> None:
        if self._dead is not None:
            return
        self._dead = reason
        for rec in self._recorders.values():
            rec._lost(reason)

    # ----------------------------------------------------------------- closing

    def close(self, timeout: float = REPLY_TIMEOUT_S) -> None:
        """Close every log still open, end the child (end of file on its pipe) and reap it.
        Idempotent."""
        if self._closed:
            return
        for rec in list(self._recorders.values()):
            rec.close(timeout)
        self._closed = True
        if self._dead is None:
            self._drain_out(timeout)
        os.close(self._out)
        with contextlib.suppress(OSError):  # read to the end: the child exits after replying
            self._await(lambda: False, timeout) if self._dead is None else None
        os.close(self._in)
        if self._reap(timeout) is None and self._pid > 0:
            with contextlib.suppress(OSError):
                os.kill(self._pid, signal.SIGKILL)
            self._reap(timeout)

    def __enter__(self) -> RecorderService:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- the child


class _Child:
    """The child's side: one ``CycleRecorder`` per open log, the live zenoh session."""

    def __init__(self, fd_in: int, fd_out: int) -> None:
        self.fd_in, self.fd_out = fd_in, fd_out
        self.cfg_json: str | None = None
        self.endpoint: str | None = None
        self.config_file: str | None = None
        self.logs: dict[int, Any] = {}
        self.reported: dict[int, tuple] = {}
        self.received: dict[int, int] = {}
        self.session: Any = None
        self.live: Any = None
        self.live_failed = False

    def reply(self, message: tuple) -> None:
        with contextlib.suppress(OSError):  # the parent is gone: the logs still get finished
            os.write(self.fd_out, _frame(message))

    def handle(self, message: tuple) -> None:
        kind, rid = message[0], message[1]
        if kind == LINK:
            self.cfg_json, self.endpoint, self.config_file = message[1:]
            return
        if kind == RECORDS:
            rec = self.logs.get(rid)
            if rec is not None:
                self.record(rec, message[2])
                self.received[rid] += len(message[2])
        elif kind == OPEN:
            self.open(rid, *message[2:])
        elif kind == LIVE:
            rec = self.logs.get(rid)
            if rec is not None:
                rec.set_live(self.live_sink())
        elif kind == CLOSE:
            self.close(rid)

    @staticmethod
    def record(rec: Any, items: list) -> None:
        for kind, t_ns, obj, _ in items:
            if kind == _CYCLE:
                rec.record_cycle(obj)
            elif kind == _DIAG:
                rec.record_diagnostics(obj, final=True)  # never refused here
            elif kind == _VISION:
                rec.record_vision(obj, t_ns)
            else:
                rec.record_can(obj, t_ns, _DIRECTION_OF[kind])

    def open(
        self, rid: int, path: str, cfg_json: str, info: dict, scene: bool, flush_s: float
    ) -> None:
        from hal.config import config_from_json
        from rt_controller.runtime.recorder import CycleRecorder

        try:
            cfg = config_from_json(cfg_json)
            builder = None
            if scene:
                from rt_controller.monitor.scene import SceneBuilder

                builder = SceneBuilder(cfg)
            rec = CycleRecorder(
                path,
                cfg,
                run_info=info,
                flush_interval_s=flush_s,
                queue_size=1 << 22,
                scene=builder,
            )
        except Exception as exc:
            self.reply((OPENED, rid, str(exc) or type(exc).__name__))
            return
        rec.burst_s, rec.yield_s = 0.01, 0.0  # no control loop shares this interpreter
        self.received[rid] = 0
        self.logs[rid] = rec
        self.reply((OPENED, rid, None))

    def counts(self, rid: int, rec: Any) -> dict[str, Any]:
        out: dict[str, Any] = rec.as_dict()
        out.update(received=self.received.get(rid, 0), finished=rec.finished)
        return out

    def report(self, force: bool = False) -> None:
        for rid, rec in self.logs.items():
            counts = self.counts(rid, rec)
            key = tuple(counts.values())
            if force or self.reported.get(rid) != key:
                self.reported[rid] = key
                error = None if rec.error is None else str(rec.error)
                self.reply((COUNTS, rid, counts, error, False))

    def close(self, rid: int) -> None:
        rec = self.logs.pop(rid, None)
        self.reported.pop(rid, None)
        if rec is None:
            return
        rec.close(None)
        rec.set_live(None)
        error = None if rec.error is None else str(rec.error)
        if rec.error is None and not rec.finished:
            error = "the writer did not finish the file"
        counts = self.counts(rid, rec)
        self.received.pop(rid, None)
        self.reply((COUNTS, rid, counts, error, True))

    def live_sink(self) -> Any:
        """The zenoh publisher of the live stream (the session opens on first use), or None."""
        if self.live is not None or self.live_failed or self.cfg_json is None:
            return self.live
        from hal.config import config_from_json
        from hal.errors import HalError
        from hal.zenoh_session import open_session
        from rt_controller.monitor.live import LivePublisher

        try:
            self.session = open_session(
                config_from_json(self.cfg_json),
                listen=False,
                endpoint=self.endpoint,
                config_file=self.config_file,
                wait_s=5.0,
            )
            self.live = LivePublisher(self.session)
        except HalError as exc:
            self.live_failed = True
            print(f"hil controller: warning: no live stream: {exc}", file=sys.stderr)
        return self.live

    def run(self) -> None:
        buf = bytearray()
        last_report = time.monotonic()
        while True:
            readable, _, _ = select.select([self.fd_in], [], [], COUNTS_EVERY_S)
            if readable:
                data = os.read(self.fd_in, _READ_SIZE)
                if not data:
                    break  # the controller closed its end (or died)
                buf += data
                for message in _split_frames(buf):
                    self.handle(message)
            now = time.monotonic()
            if now - last_report >= COUNTS_EVERY_S:
                last_report = now
                self.report()
        for rid in list(self.logs):
            self.close(rid)
        if self.live is not None:
            self.live.close()
        if self.session is not None:
            self.session.close()


def serve(fd_in: int, fd_out: int) -> None:
    """The child's main loop: until end of file on ``fd_in``, then every open log finished.
    Standard input and output become ``/dev/null`` (the controller's stdout carries its JSON
    summary, and whoever reads it must not wait for this process); warnings go to stderr."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    devnull = os.open(os.devnull, os.O_RDWR)
    for fd in (0, 1):
        with contextlib.suppress(OSError):
            os.dup2(devnull, fd)
    os.close(devnull)
    os.set_blocking(fd_in, True)
    _Child(fd_in, fd_out).run()


def main(argv: list[str]) -> int:
    """``python -m rt_controller.runtime.recorder_process FD_IN FD_OUT`` (spawned child)."""
    serve(int(argv[0]), int(argv[1]))
    return 0


if __name__ == "__main__":
    sys.stdout.flush()
    code = main(sys.argv[1:])
    sys.stderr.flush()
    os._exit(code)
