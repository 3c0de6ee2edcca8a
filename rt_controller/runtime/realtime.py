"""Best-effort real-time process settings; each refusal becomes a warning, never an error."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
from dataclasses import dataclass, field

MCL_CURRENT, MCL_FUTURE = 1, 2
PR_SET_TIMERSLACK = 29


@dataclass
class RtReport:
    """What was applied and what was refused (with the reason)."""

    applied: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name or "libc.so.6", use_errno=True)
    except OSError:
        return None


def apply_realtime(priority: int = 80, cpu: int = -1, lock_memory: bool = True) -> RtReport:
    """SCHED_FIFO, CPU affinity, mlockall, 1 ns timer slack and a frozen GC heap."""
    rep = RtReport()
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        rep.applied.append(f"SCHED_FIFO priority {priority}")
    except (OSError, AttributeError) as exc:
        rep.warnings.append(f"SCHED_FIFO refused ({exc}); running with normal scheduling")
    if cpu >= 0:
        try:
            os.sched_setaffinity(0, {cpu})
            rep.applied.append(f"pinned to CPU {cpu}")
        except (OSError, ValueError) as exc:
            rep.warnings.append(f"CPU affinity {cpu} refused ({exc})")
    libc = _libc()
    if libc is None:
        rep.warnings.append("libc not found: no mlockall, no timer slack")
    else:
        if lock_memory:
            if libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
                rep.applied.append("mlockall")
            else:
                rep.warnings.append(f"mlockall refused ({os.strerror(ctypes.get_errno())})")
        if libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0:
            rep.applied.append("timer slack 1 ns")
        else:
            rep.warnings.append(f"timer slack refused ({os.strerror(ctypes.get_errno())})")
    gc.collect()
    gc.freeze()
    rep.applied.append("GC heap frozen")
    return rep


class GcPaused:
    """Context manager: the cyclic GC is off inside the loop and restored afterwards."""

    def __enter__(self) -> GcPaused:
        self._was = gc.isenabled()
        gc.disable()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._was:
            gc.enable()
