"""SCHED_FIFO for the calling thread, best effort: the rig's time-critical threads that are not
the controller's loop (the emulated camera, the frame grabber) ask for it once, from the thread
itself (Linux applies ``sched_setscheduler(0, ...)`` to the calling thread only). The other
way, a thread or a child process off every deadline's path lowers its priority
(:func:`raise_nice`); and a process whose threads share the GIL hands it over sooner
(:func:`short_gil_switch`)."""

from __future__ import annotations

import contextlib
import os
import sys

GIL_SWITCH_S = 0.0005
"""The GIL switch interval of a rig process whose deadline thread shares the GIL with a busy one
(Python's default is 5 ms: a thread that wants the GIL may wait that long for a thread running
Python). The emulator (the DSP thread beside the camera's renderer) and the vision process (the
frame grabber beside the image log's PNG thread) use it; figures in docs/benchmarks.md."""


def fifo_thread(priority: int) -> str | None:
    """Put the calling thread on SCHED_FIFO at ``priority`` (0: leave scheduling alone). A
    refusal (no CAP_SYS_NICE, no such policy) is returned as a one-line reason, never raised."""
    if priority <= 0:
        return None
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return f"SCHED_FIFO {priority} refused ({exc})"
    return None


def raise_nice(tid: int, by: int) -> None:
    """Raise the nice value of thread (or single-threaded process) ``tid`` by ``by`` (at most
    to 19), e.g. a child process just started (the threads it starts inherit the value) or a
    thread of this process (``threading.get_native_id()``): it then leaves most of a core to
    the threads at the default priority while they want one, and still has its share. Best
    effort, never raises."""
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + by, 19))


def short_gil_switch() -> None:
    """Lower this process's GIL switch interval to :data:`GIL_SWITCH_S` (never raise it)."""
    sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_S))
