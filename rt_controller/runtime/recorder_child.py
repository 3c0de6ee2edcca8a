"""The recorder's child process, and the pipe protocol it speaks with the controller process.

:class:`RecorderChild` reads the control process's batches from one pipe, writes each log with a
:class:`~rt_controller.runtime.recorder.CycleRecorder` and answers on the other pipe with each
log's counters. It owns the live zenoh stream (``hil/controller/cycle``, ``.../diagnostics``) on
a session of its own, opened on first use. The control side is
:mod:`rt_controller.runtime.recorder_process`.

The child ignores SIGINT, SIGTERM and SIGHUP (the controller decides when its logs end) and
finishes every open log at end of file on its pipe, so the logs of a SIGKILLed controller are
still complete. While it waits it flushes the logs that are due (``flush_interval_s``).

Wire format, both directions: a 4-byte little-endian length, then a pickled tuple. Parent to
child: ``(LINK, cfg_json, zenoh_endpoint, zenoh_config)`` first, then ``(OPEN, rid, path,
cfg_json, run_info, scene, flush_interval_s)``, ``(RECORDS, rid, items)`` (each item
``(kind, t_ns, obj)`` of :meth:`CycleRecorder.write`, a CAN frame as a :class:`CanFrame`),
``(LIVE, rid)`` and ``(CLOSE, rid)``. Child to parent: ``(OPENED, rid, error)`` and ``(COUNTS,
rid, counts, error, final)``.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import pickle
import select
import signal
import struct
import sys
import time
from collections import namedtuple
from typing import Any

from rt_controller.errors import LogError
from rt_controller.runtime.recorder import CycleRecorder

LINK, OPEN, RECORDS, LIVE, CLOSE = "link", "open", "records", "live", "close"
OPENED, COUNTS = "opened", "counts"
READ_SIZE = 1 << 20
"""Bytes read from a pipe in one call."""
COUNTS_EVERY_S = 0.25
"""The child reports a log's counters at most this often (and at its close)."""
_HEADER = struct.Struct("<I")
_PIPE_SIZE = 1 << 20
"""Requested pipe capacity (``F_SETPIPE_SZ``; Linux's default unprivileged maximum)."""

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


def encode_frame(message: tuple) -> bytes:
    """One message on the wire: its length, then the pickled tuple."""
    body = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    return _HEADER.pack(len(body)) + body


def split_frames(buf: bytearray) -> list[tuple]:
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


class RecorderChild:
    """The child's side: one ``CycleRecorder`` per open log, the live zenoh session."""

    def __init__(self, fd_in: int, fd_out: int) -> None:
        self.fd_in, self.fd_out = fd_in, fd_out
        self.cfg_json: str | None = None
        self.endpoint: str | None = None
        self.config_file: str | None = None
        self.logs: dict[int, CycleRecorder] = {}
        self.reported: dict[int, tuple] = {}
        self.received: dict[int, int] = {}
        self.session: Any = None
        self.live: Any = None
        self.live_failed = False

    def reply(self, message: tuple) -> None:
        with contextlib.suppress(OSError):  # the parent is gone: the logs still get finished
            os.write(self.fd_out, encode_frame(message))

    def handle(self, message: tuple) -> None:
        kind, rid = message[0], message[1]
        if kind == LINK:
            self.cfg_json, self.endpoint, self.config_file = message[1:]
        elif kind == RECORDS:
            rec = self.logs.get(rid)
            if rec is not None:
                write = rec.write
                for item in message[2]:
                    write(*item)
                self.received[rid] += len(message[2])
        elif kind == OPEN:
            self.open(rid, *message[2:])
        elif kind == LIVE:
            rec = self.logs.get(rid)
            if rec is not None:
                rec.set_live(self.live_sink())
        elif kind == CLOSE:
            self.close(rid)

    def open(
        self, rid: int, path: str, cfg_json: str, info: dict, scene: bool, flush_s: float
    ) -> None:
        from hal.config import config_from_json

        try:
            cfg = config_from_json(cfg_json)
            builder = None
            if scene:
                from rt_controller.monitor.scene import SceneBuilder

                builder = SceneBuilder(cfg)
            rec = CycleRecorder(path, cfg, run_info=info, flush_interval_s=flush_s, scene=builder)
        except Exception as exc:
            self.reply((OPENED, rid, str(exc) or type(exc).__name__))
            return
        self.received[rid] = 0
        self.logs[rid] = rec
        self.reply((OPENED, rid, None))

    def counts(self, rid: int, rec: CycleRecorder) -> dict[str, Any]:
        out: dict[str, Any] = rec.as_dict()
        out.update(received=self.received.get(rid, 0), finished=rec.finished)
        return out

    def report(self) -> None:
        """Each open log's counters, when they changed since the last report."""
        for rid, rec in self.logs.items():
            counts = self.counts(rid, rec)
            if self.reported.get(rid) != (key := tuple(counts.values())):
                self.reported[rid] = key
                self.reply((COUNTS, rid, counts, rec.error and str(rec.error), False))

    def close(self, rid: int) -> None:
        rec = self.logs.pop(rid, None)
        self.reported.pop(rid, None)
        if rec is None:
            return
        rec.close()
        rec.set_live(None)
        error = str(rec.error) if rec.error else None
        if not (error or rec.finished):
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
        """Serve until end of file on the input pipe, then finish every open log."""
        buf = bytearray()
        last_report = time.monotonic()
        while True:
            readable, _, _ = select.select([self.fd_in], [], [], COUNTS_EVERY_S)
            if readable:
                data = os.read(self.fd_in, READ_SIZE)
                if not data:
                    break  # the controller closed its end (or died)
                buf += data
                for message in split_frames(buf):
                    self.handle(message)
            now = time.monotonic()
            if now - last_report >= COUNTS_EVERY_S:
                last_report = now
                for rec in self.logs.values():  # a quiet log still reaches the disk
                    rec.flush_if_due()
                self.report()
        for rid in list(self.logs):
            self.close(rid)
        if self.live is not None:
            self.live.close()
        if self.session is not None:
            self.session.close()


class ChildProcess:
    """The recorder's child as its parent sees it: ``start`` ``"auto"`` forks while the parent
    has one OS thread (else spawns ``python -m rt_controller.runtime.recorder_child``), or
    ``"fork"`` / ``"spawn"``; :attr:`fd_out` (to the child, grown) and :attr:`fd_in` (from it)
    are the parent's non-blocking ends of the two pipes."""

    def __init__(self, start: str = "auto") -> None:
        if start not in ("auto", "fork", "spawn"):
            raise LogError(f"recorder start must be auto, fork or spawn, not {start!r}")
        self._status: int | None = None
        child_in, self.fd_out = os.pipe()
        self.fd_in, child_out = os.pipe()
        with contextlib.suppress(OSError, AttributeError):
            fcntl.fcntl(self.fd_out, fcntl.F_SETPIPE_SZ, _PIPE_SIZE)
        fork = start == "fork" or (start == "auto" and _os_threads() == 1)
        self.start_method = "fork" if fork else "spawn"
        try:
            self.pid = (self._fork if fork else self._spawn)(child_in, child_out)
        except BaseException:
            os.close(self.fd_out)
            os.close(self.fd_in)
            raise
        finally:
            os.close(child_in)
            os.close(child_out)
        os.set_blocking(self.fd_out, False)
        os.set_blocking(self.fd_in, False)

    def _fork(self, child_in: int, child_out: int) -> int:
        sys.stdout.flush()  # or the child would write the parent's buffered output again
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # the child: never returns into the caller's code
            status = 1
            try:
                os.close(self.fd_out)
                os.close(self.fd_in)
                serve(child_in, child_out)
                status = 0
            except BaseException as exc:  # report, then leave without the parent's cleanup
                with contextlib.suppress(Exception):
                    print(f"hil controller: recorder process failed: {exc}", file=sys.stderr)
            finally:
                with contextlib.suppress(Exception):
                    sys.stderr.flush()
                os._exit(status)
        return pid

    @staticmethod
    def _spawn(child_in: int, child_out: int) -> int:
        os.set_inheritable(child_in, True)
        os.set_inheritable(child_out, True)
        argv = [sys.executable, "-m", __name__, str(child_in), str(child_out)]
        quiet = [(os.POSIX_SPAWN_OPEN, fd, os.devnull, os.O_RDWR, 0) for fd in (0, 1)]
        return os.posix_spawn(sys.executable, argv, os.environ, file_actions=quiet)

    def reap(self, timeout: float) -> int | None:
        """The child's exit status (negative: killed by that signal), None while it runs."""
        deadline = time.monotonic() + timeout
        while self._status is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped by someone else
                pid, status = self.pid, 0
            if pid:
                self._status = os.waitstatus_to_exitcode(status)
            elif time.monotonic() >= deadline:
                return None
            else:
                time.sleep(0.005)
        return self._status

    def exit_note(self) -> str:
        """`` (status N)`` or `` (killed by signal N)`` once the child has exited, else ``""``."""
        status = self.reap(0.2)
        if status is None:
            return ""
        return f" (killed by signal {-status})" if status < 0 else f" (status {status})"

    def end(self, timeout: float) -> None:
        """Reap the child (its input pipe closed, it exits by itself); SIGKILL it after
        ``timeout`` seconds."""
        if self.reap(timeout) is None and self.pid > 0:
            with contextlib.suppress(OSError):
                os.kill(self.pid, signal.SIGKILL)
            self.reap(timeout)


def _os_threads() -> int:
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 2  # unknown: do not fork


def _demote() -> None:
    """Best effort: the recorder must not compete with a SCHED_FIFO loop it was forked from."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        cpus = os.sched_getaffinity(0)
        everything = set(range(os.cpu_count() or 1))
        if len(cpus) == 1 and len(everything) > 1:
            os.sched_setaffinity(0, everything - cpus)
    except (AttributeError, OSError):
        pass


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
    _demote()
    RecorderChild(fd_in, fd_out).run()


if __name__ == "__main__":  # the spawned child: python -m ... FD_IN FD_OUT
    serve(int(sys.argv[1]), int(sys.argv[2]))
    sys.stderr.flush()
    os._exit(0)
