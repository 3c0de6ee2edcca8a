"""The ``--out`` log of ``hil replay``: the replayed cycles and the recorded raw inputs, written
with :class:`~rt_controller.runtime.recorder.CycleRecorder` (the record shapes are in
:mod:`rt_controller.logtools.replay`)."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

from hal.config import RigConfig
from rt_controller.errors import LogError
from rt_controller.logtools.reader import LoadedLog
from rt_controller.runtime.recorder import CycleRecorder


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


class OutLog:
    """The ``--out`` writer: replayed cycles plus the recorded raw inputs, written beside the
    file asked for and renamed onto it only when whole (:meth:`close`); a failed or interrupted
    replay leaves no half log (:meth:`discard`), errors name the file asked for."""

    def __init__(self, path: Path, cfg: RigConfig, log: LoadedLog, tol: float) -> None:
        self.path, self.partial = path, path.with_name(f".{path.name}.partial")
        info: dict[str, Any] = {f"source.{k}": v for k, v in log.run_info.items()}
        info.update(
            replay_of=str(log.path),
            replay_tol=repr(tol),
            replay_timing="zero (offline replay); tick, t_ns, sim_time_s and inputs as recorded",
            clock=log.run_info.get("clock", cfg.controller.clock),
            law=cfg.controller.law,
        )
        try:
            self.rec = CycleRecorder(self.partial, cfg, run_info=info)
        except LogError as exc:
            self.partial.unlink(missing_ok=True)
            raise LogError(str(exc).replace(str(self.partial), str(path))) from None

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

    def close(self) -> None:
        """Finish the log and rename it onto the file asked for; :class:`LogError` if it
        could not be written whole (nothing left then)."""
        self.rec.close()
        try:
            self._check()
            self.partial.replace(self.path)
        except LogError:  # before OSError, which it may derive from
            self.discard()
            raise
        except OSError as exc:
            self.discard()
            raise LogError(f"cannot write {self.path}: {exc.strerror or exc}") from None

    def discard(self) -> None:
        """Close and delete the unfinished log (the replay failed or was stopped)."""
        with contextlib.suppress(Exception):
            self.rec.close()
        self.partial.unlink(missing_ok=True)
