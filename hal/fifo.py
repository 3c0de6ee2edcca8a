"""SCHED_FIFO for the calling thread, best effort: the rig's time-critical threads that are not
the controller's loop (the emulated camera, the frame grabber) ask for it once, from the thread
itself (Linux applies ``sched_setscheduler(0, ...)`` to the calling thread only). The other
way, a process off every deadline's path gets a lower priority (:func:`raise_nice`)."""

from __future__ import annotations

import contextlib
import os


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
    """Raise the nice value of thread (or single-threaded process) ``tid`` by ``by`` (at most to
    19), e.g. of a child process just started (the threads it starts inherit the value): it
    then leaves a core to the threads at the default priority while they want one. Lowering a
    priority needs no privilege. Best effort, never raises."""
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + by, 19))
