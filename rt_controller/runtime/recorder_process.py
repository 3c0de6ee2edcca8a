"""The MCAP recorder in a process of its own, so the control process runs no other Python thread.

:class:`RecorderService` starts one child process for a controller process (the runs of a plan
share it); :meth:`RecorderService.open` gives a :class:`RemoteRecorder`, the daemon's recorder.
A record costs the control thread a list append; once per tick, with the cycle record, the
tick's batch is pickled and written to a pipe. The child (:mod:`rt_controller.runtime.
recorder_child`, which also defines the wire format) writes the logs with
:class:`~rt_controller.runtime.recorder.CycleRecorder` and streams them live.

A realtime tick never blocks on the child: the pipe is non-blocking (1 MiB where the kernel
allows it), what it cannot take waits in an outbox, and a batch that would grow the outbox past
:attr:`RecorderService.outbox_limit` bytes is dropped and counted (the run is then not clean).
Lockstep has no deadline: there the tick waits for the child (``backpressure``), so a
Sync-paced log is never short because the host was busy.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import pickle
import select
import time
from pathlib import Path
from typing import Any

from hal.config import RigConfig
from rt_controller.errors import LogError
from rt_controller.runtime.recorder import (
    CAN_RX,
    CAN_TX,
    CYCLE,
    DIAG,
    TOPICS,
    VISION,
    Recorder,
    default_run_info,
)
from rt_controller.runtime.recorder_child import (
    CLOSE,
    COUNTS,
    LINK,
    LIVE,
    OPEN,
    OPENED,
    READ_SIZE,
    RECORDS,
    ChildProcess,
    can_frame,
    encode_frame,
    split_frames,
)

REPLY_TIMEOUT_S = 30.0
"""How long opening or closing a log waits for the child's answer."""
log = logging.getLogger(__name__)

_UNPICKLABLE = (pickle.PicklingError, TypeError, AttributeError, ValueError, RecursionError)


def _picklable(obj: Any) -> bool:
    try:
        pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    except _UNPICKLABLE:
        return False
    return True


class RemoteRecorder(Recorder):
    """One run's log, recorded by the service's child process (the interface and counters of
    :class:`~rt_controller.runtime.recorder.CycleRecorder`). ``record_*`` take ownership of
    what they are given (pickled at the end of the tick). Counters are the child's latest report
    (exact after :meth:`close`) plus the batches this process dropped."""

    def __init__(self, service: RecorderService, rid: int, path: Path, backpressure: bool):
        self.path = path
        self._service = service
        self._rid = rid
        self._backpressure = backpressure
        self._batch: collections.deque[tuple[int, int, Any]] = collections.deque()
        """Records since the last send (a deque: Sync-paced runs feed it from zenoh's thread)."""
        self.closed = False
        self.error: str | None = None
        """Why the log is incomplete (the child's writer failed, or the child died)."""
        self._sent = self._dropped = 0
        self._counts: dict[str, Any] = {}
        self.final_report = False
        """The child's final counters for this log arrived."""
        self._encode_errors = 0
        """Records that could not be pickled for the child (counted with its encode errors)."""

    def write(self, kind: int, t_ns: int, obj: Any, final: bool = False) -> bool:
        """Queue one record item; a cycle or diagnostics record sends the tick's batch (a final
        one even when the outbox is full: it carries the run's totals)."""
        if self.closed:
            self._dropped += 1
            return False
        if kind in (CAN_RX, CAN_TX):
            obj = can_frame(obj)
        elif kind == VISION:
            obj = bytes(obj)
        self._batch.append((kind, t_ns, obj))
        return self.send(force=final) if kind in (CYCLE, DIAG) else True

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

    def stream_live(self) -> None:
        """Ask the child to publish this log's cycle and diagnostics records on zenoh."""
        self._service.send_control((LIVE, self._rid))

    def update(self, counts: dict[str, Any], error: str | None, final: bool) -> None:
        """The child's report on this log (the service applies it)."""
        self._counts = counts
        self.error = self.error or error
        self.final_report = self.final_report or final

    def close(self, timeout: float | None = REPLY_TIMEOUT_S) -> None:
        """Send what is queued, ask the child to finish the file and wait for its final
        counters. Idempotent."""
        if self.closed:
            return
        self.send(force=True)
        self.closed = True
        self._service.finish(self._rid, REPLY_TIMEOUT_S if timeout is None else timeout)

    @property
    def finished(self) -> bool:
        """The child finished the file cleanly (summary and footer written)."""
        return self.final_report and bool(self._counts.get("finished"))

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
        """The keys of ``CycleRecorder.as_dict``, with the child's latest report."""
        self._service.poll()
        counts = self._counts
        out = {topic: int(counts.get(topic, 0)) for topic in TOPICS.values()}
        out.update(
            written=self.written,
            dropped=self.dropped,
            encode_errors=self._encode_errors + int(counts.get("encode_errors", 0)),
            pending=self.pending,
        )
        return out


class RecorderService:
    """The recorder's child process and the two pipes to it (see the module docstring): ``cfg``
    (and ``zenoh_endpoint`` / ``zenoh_config``) for the live stream's session, ``start`` as
    :class:`~rt_controller.runtime.recorder_child.ChildProcess`. :meth:`close` ends the child."""

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
        self._next_rid = 0
        self._recorders: dict[int, RemoteRecorder] = {}
        self._outbox = bytearray()
        self._inbox = bytearray()
        self._dead: str | None = None
        self._closed = False
        self._opened: dict[int, str | None] = {}
        self._child = ChildProcess(start)
        self._out, self._in = self._child.fd_out, self._child.fd_in
        self.start_method, self.pid = self._child.start_method, self._child.pid
        """How the child was started (``fork`` or ``spawn``), and its pid."""
        self.send_control((LINK, cfg.to_json(), zenoh_endpoint, zenoh_config))

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
        mono_ns, unix_ns = time.monotonic_ns(), time.time_ns()
        info = default_run_info(cfg, mono_ns, unix_ns)  # this process's pid, argv, ...
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
        self._outbox += encode_frame((RECORDS, rid, items))
        self._pump_out()
        if wait and len(self._outbox) > self.outbox_limit:
            self._drain_out(REPLY_TIMEOUT_S)
        return self._dead is None

    def send_control(self, message: tuple) -> None:
        """Queue a control message and wait until the pipe took it."""
        if self._dead is not None or self._closed:
            return
        self._outbox += encode_frame(message)
        self._drain_out(REPLY_TIMEOUT_S)

    def finish(self, rid: int, timeout: float) -> None:
        """Close log ``rid`` in the child and wait for its final counters."""
        rec = self._recorders.get(rid)
        if rec is None:
            return
        self.send_control((CLOSE, rid))
        if not self._await(lambda: rec.final_report, timeout):
            why = self._dead or f"the recorder process did not finish the log in {timeout:g} s"
            rec.error = rec.error or why
        self._recorders.pop(rid, None)

    # ----------------------------------------------------------------- pipes

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
        if not self._await(lambda: not self._outbox, timeout, writing=True) and not self._dead:
            self._die(f"the recorder process took nothing for {timeout:g} s")

    def poll(self) -> None:
        """Read and apply the child's replies that arrived (counters, errors); never blocks."""
        while True:
            try:
                data = os.read(self._in, READ_SIZE)
            except BlockingIOError:
                break
            except OSError as exc:
                self._die(f"the recorder process is gone ({exc.strerror or exc})")
                return
            if not data:
                self._die(f"the recorder process exited{self._child.exit_note()}")
                break
            self._inbox += data
        for message in split_frames(self._inbox):
            self._apply(message)

    def _apply(self, message: tuple) -> None:
        kind, rid = message[0], message[1]
        if kind == OPENED:
            self._opened[rid] = message[2]
        elif kind == COUNTS:
            rec = self._recorders.get(rid)
            if rec is not None:
                rec.update(*message[2:])

    def _await(self, done: Any, timeout: float, *, writing: bool = False) -> bool:
        """Read replies (and, ``writing``, write the outbox) until ``done()`` holds (True), the
        child died or ``timeout`` ran out."""
        deadline = time.monotonic() + timeout
        while True:
            if writing:
                self._pump_out()
            self.poll()
            if done():
                return True
            left = deadline - time.monotonic()
            if self._dead is not None or left <= 0:
                return False
            select.select([self._in], [self._out] if writing else [], [], min(left, 0.1))

    def _die(self, reason: str) -> None:
        if self._dead is not None:
            return
        self._dead = reason
        for rec in self._recorders.values():
            rec.error = rec.error or reason

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
        if self._dead is None:  # read to the end: the child exits after replying
            with contextlib.suppress(OSError):
                self._await(lambda: False, timeout)
        os.close(self._in)
        self._child.end(timeout)

    def __enter__(self) -> RecorderService:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
