"""Process supervision shared by ``hil up`` (the supervisor) and its children.

* :func:`follow_parent`: a child asks the kernel for SIGTERM when the supervisor dies
  (``PR_SET_PDEATHSIG``), so even a SIGKILLed ``hil up`` leaves nothing running;
* :func:`supervised`: SIGTERM, SIGINT and SIGHUP to the supervisor become
  :class:`RigInterrupted`, so it stops its children in order before it exits;
* :func:`signals_deferred`: those signals wait while the children are being stopped;
* :func:`group_running`: whether a process of the children's group still runs.

Light on purpose (no numpy, python-can or zenoh): :mod:`rt_controller.cli` calls
:func:`follow_parent` before it builds its parser.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

from hal.signals import STACKS_SIGNAL
from rt_controller.errors import ControllerError

PARENT_ENV = "HIL_SUPERVISOR_PID"
"""Set in each child's environment to the supervisor's pid (see :func:`follow_parent`)."""
SUPERVISED_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
STACKS_WAIT_S = 1.0
"""How long a hung child gets to print its stacks before SIGKILL (the dump is immediate)."""
_PR_SET_PDEATHSIG = 1


class RigInterrupted(ControllerError):
    """The supervisor was told to stop by a signal; the children have been stopped."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        self.summary: dict | None = None
        """The controller's summary of the run so far, when the supervisor got one."""
        super().__init__(f"interrupted by {signal.Signals(signum).name}")

    @property
    def exit_code(self) -> int:
        """The shell's convention for a process ended by a signal: 128 + its number."""
        return 128 + self.signum


def follow_parent() -> None:
    """In a rig child: ask for SIGTERM when the supervisor dies, so the child never outlives it.

    Does nothing outside a rig (no :data:`PARENT_ENV`). If the supervisor already died before
    the request took effect, the child sends itself the signal at once.
    """
    parent = os.environ.get(PARENT_ENV)
    if not parent or not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != int(parent):
        os.kill(os.getpid(), signal.SIGTERM)


def kill_with_stacks(proc: subprocess.Popen, dump_wait_s: float = STACKS_WAIT_S) -> None:
    """End a child that did not stop when told: :data:`hal.signals.STACKS_SIGNAL` first, so its
    stderr ends in every thread's stack (where it hung), then SIGKILL; reaped."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(STACKS_SIGNAL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(dump_wait_s)  # a child without the dump ends on the signal itself
    if proc.poll() is None:
        proc.kill()
    proc.wait()


def group_running(pgid: int) -> bool:
    """Whether a process of group ``pgid`` still runs (zombies, which only wait to be reaped,
    do not count). Read from ``/proc``; elsewhere: whether the group can be signalled."""
    proc = Path("/proc")
    if not (proc / "self" / "stat").exists():
        try:
            os.killpg(pgid, 0)
        except (ProcessLookupError, PermissionError):
            return False
        return True
    for stat in proc.glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # it ended while we looked
        if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
            return True
    return False


@contextlib.contextmanager
def supervised() -> Iterator[None]:
    """While inside, SIGTERM/SIGINT/SIGHUP raise :class:`RigInterrupted` in the main thread
    (the previous handlers are restored on exit). Outside the main thread it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, _frame: object) -> None:
        raise RigInterrupted(signum)

    previous = {sig: signal.signal(sig, interrupt) for sig in SUPERVISED_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextlib.contextmanager
def signals_deferred(deliver: bool = True) -> Iterator[None]:
    """Hold the supervised signals until the block ends, then deliver them to the handlers in
    force (a second SIGTERM must not cut an orderly stop short; a Ctrl-C must not split a
    journal write from its table row). ``deliver=False`` drops them instead: a second stop
    signal while the supervisor already stops on the first asks for nothing more.

    The hold is at the Python level: a process-directed signal reaches whichever thread does
    not block it, and CPython runs the handler in the main thread anyway, so a signal mask
    defers nothing once a library has started a thread. Outside the main thread it does
    nothing (handlers can only be changed there).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []

    def hold(signum: int, _frame: object) -> None:
        held.append(signum)

    previous = {sig: signal.signal(sig, hold) for sig in SUPERVISED_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        for signum in dict.fromkeys(held if deliver else ()):
            signal.raise_signal(signum)
