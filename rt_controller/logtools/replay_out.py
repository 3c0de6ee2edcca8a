"""The ``--out`` log of ``hil replay``: the replayed cycles and the recorded raw inputs, written
with :class:`~rt_controller.runtime.recorder.CycleRecorder` (the record shapes are in
:mod:`rt_controller.logtools.replay`)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hal.config import RigConfig
from hal.whole_file import written_whole
from rt_controller.errors import LogError
from rt_controller.logtools.reader import LoadedLog
from rt_controller.runtime.recorder import CYCLE_TOPIC, CycleRecorder


def cycle_record_at(log: LoadedLog, i: int) -> dict[str, Any]:
    """Tick ``i`` of the log as a cycle dict (NaN stays NaN; the recorder writes null)."""
    rec: dict[str, Any] = {}
    for key, col in log.cycles.items():
        v = col[i]
        if col.ndim == 2:
            rec[key] = [float(x) for x in v]
        elif col.dtype == bool:
            rec[key] = bool(v)
        elif col.dtype.kind == "i":
            rec[key] = int(v)
        elif col.dtype.kind == "f":
            rec[key] = float(v)
        else:
            rec[key] = v
    return rec


PARTIAL_SOURCE = "replay_of_partial"
"""``hil.run`` key of a replayed log whose source was cut or damaged: what it lost."""


def inherited_loss(log: LoadedLog) -> str | None:
    """A note when ``log`` is whole as a file but holds only part of a run: a copy ``hil
    recover`` made of a cut or damaged log that lost records, or a replay (``--out``) of a
    partial log. None for any other log (its own damage is ``log.truncated``)."""
    partial = log.run_info.get(PARTIAL_SOURCE)
    if partial:
        src = log.run_info.get("replay_of", "?")
        return f"a replay of the partial log {src} ({partial}): the ticks it lost are not here"
    meta = log.recovered_info
    if meta is None:
        return None
    stopped = meta.get("stopped", "")
    skipped = meta.get("skipped_bytes", "0") not in ("", "0")
    if not skipped and (stopped.startswith("footer") or "(all data kept)" in stopped):
        return None
    src, kept, size = meta.get("from", "?"), meta.get("kept_bytes", "?"), meta.get("input_bytes")
    how = stopped or "unknown end"
    if skipped:
        how = f"{meta['skipped_bytes']} bytes of damaged chunks skipped; read to the {how}"
    return (
        f"a copy `hil recover` made of the damaged log {src}: kept {kept} of {size} bytes "
        f"({how}); the records it lost are not in this copy"
    )


def source_loss(log: LoadedLog) -> str | None:
    """What a replayed log inherits from its source ``log``: why it is partial, or None."""
    walk = log.walk
    if log.truncated and not (walk is not None and walk.data_end and not walk.skipped):
        return log.notes[0] if log.notes else "truncated"
    unread = log.rejected.get(CYCLE_TOPIC, 0)
    if unread:
        return f"{unread} unreadable cycle record(s) skipped"
    return inherited_loss(log)


class OutLog:
    """The ``--out`` writer: replayed cycles plus the recorded raw inputs, into ``tmp`` (see
    :func:`out_log`); its errors name ``path``, the file asked for."""

    def __init__(self, tmp: Path, path: Path, cfg: RigConfig, log: LoadedLog, tol: float) -> None:
        self.path = path
        info: dict[str, Any] = {f"source.{k}": v for k, v in log.run_info.items()}
        info.update(
            replay_of=str(log.path),
            replay_tol=repr(tol),
            replay_timing="zero (offline replay); tick, t_ns, sim_time_s and inputs as recorded",
            clock=log.run_info.get("clock", cfg.controller.clock),
            law=cfg.controller.law,
        )
        partial = source_loss(log)
        if partial:
            info[PARTIAL_SOURCE] = partial
        try:
            self.rec = CycleRecorder(tmp, cfg, run_info=info)
        except LogError as exc:
            raise LogError(str(exc).replace(str(tmp), str(path))) from None

    def _check(self) -> None:
        if self.rec.error is not None:
            raise LogError(f"cannot write {self.path}: {self.rec.error}") from self.rec.error

    def cycle(self, record: dict[str, Any]) -> None:
        self.rec.record_cycle(record)
        self._check()

    def raw_inputs(self, log: LoadedLog) -> None:
        import base64

        import can

        for r in log.can_rx:
            msg = can.Message(
                arbitration_id=int(r["arbitration_id"]),
                is_extended_id=bool(r.get("is_extended_id", False)),
                data=bytes.fromhex(r.get("data", "")),
                is_fd=bool(r.get("is_fd", False)),
                timestamp=float(r.get("timestamp", 0.0) or 0.0),
                check=False,
            )
            self.rec.record_can(msg, int(r["t_ns"]), "rx")
            self._check()
        for r in log.vision:
            self.rec.record_vision(base64.b64decode(r.get("data", "")), int(r["t_ns"]))
            self._check()

    def finish(self) -> None:
        """Finish the log; :class:`LogError` if it could not be written whole."""
        self.rec.close()
        self._check()


@contextlib.contextmanager
def out_log(path: Path, cfg: RigConfig, log: LoadedLog, tol: float) -> Iterator[OutLog]:
    """An :class:`OutLog` written beside ``path`` and renamed onto it when the block ends
    whole (:func:`~hal.whole_file.written_whole`); a failed or interrupted replay leaves no
    half log and the file that was there stays."""
    with written_whole(path) as tmp:
        writer = OutLog(tmp, path, cfg, log, tol)
        try:
            yield writer
            writer.finish()
        except OSError as exc:  # a full disk while closing: named by the file asked for
            with contextlib.suppress(Exception):
                writer.rec.close()
            if isinstance(exc, LogError):
                raise
            raise LogError(f"cannot write {path}: {exc.strerror or exc}") from None
        except BaseException:
            with contextlib.suppress(Exception):
                writer.rec.close()
            raise
