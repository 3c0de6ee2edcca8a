"""Process-level helpers shared by every stand-alone entry point (``hil`` and ``python -m``).

:func:`stop_on_signals` replaces the install-handlers-then-restore block each long-running
command needs; :func:`run_standalone` is the one ``main()`` error rule (a :class:`HalError` or a
subclass of ``errors`` becomes one line on stderr and exit status 2, an ``OSError`` one line
naming its path; a reader of stdout that went away ends the command quietly). Lives in
``hal`` because both ``plant_emulator`` and ``rt_controller`` use it and neither may import
the other.
"""

from __future__ import annotations

import contextlib
import errno
import faulthandler
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
STACKS_SIGNAL = signal.SIGUSR1
"""While inside :func:`stop_on_signals`, this signal prints every thread's stack to stderr at
once, from faulthandler's C handler: it needs neither the GIL nor the main thread, so it names
a hang that keeps the Python handlers from running (a thread blocked with the GIL held). A
supervisor sends it to a child that did not stop in time, before SIGKILL."""
STACKS_AFTER_S = 8.0
"""A process still stopping this long after a stop signal prints every thread's stack to
stderr, so a stop that hangs (the rig SIGKILLs after 10 s) names where it hung. An orphan
(its parent died before the signal, as when a SIGKILLed ``hil up`` sends its children the
parent-death signal) then exits with status 1: nobody is left to kill it."""


USAGE_ERRNOS = frozenset(
    {errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.EACCES, errno.EPERM}
    | {errno.EROFS, errno.ENAMETOOLONG}
)
"""An :class:`OSError` with one of these is a bad path given by the user: exit status 2 (any
other, such as a full disk, is a failed run: 1)."""

STOP_POLL_S = 0.1
"""How often a main thread waiting for the stop wakes (:func:`wait_for_stop`)."""


def wait_for_stop(
    stop: threading.Event, timeout_s: float | None = None, poll_s: float = STOP_POLL_S
) -> bool:
    """Block until ``stop`` is set (True) or ``timeout_s`` passed (False; None: no limit),
    waking every ``poll_s``. The kernel may deliver a stop signal to any thread (zenoh's,
    canopen's); that does not interrupt the main thread's untimed wait, and Python runs the
    handler that sets ``stop`` only in the main thread, when it next wakes. A long
    ``stop.wait()`` there can therefore sleep through the signal."""
    end = None if timeout_s is None else time.monotonic() + timeout_s
    while not stop.wait(poll_s if end is None else max(0.0, min(poll_s, end - time.monotonic()))):
        if end is not None and time.monotonic() >= end:
            return False
    return True


class StopEvent(threading.Event):
    """The event :func:`stop_on_signals` yields: a :class:`threading.Event` that also keeps
    which stop signal set it first, so a summary can say ``stopped by SIGTERM``."""

    signal_name: str | None = None
    """``"SIGTERM"`` or ``"SIGINT"``; None while no stop signal arrived."""


def signal_name_of(stop: threading.Event) -> str | None:
    """The stop signal that set ``stop`` inside :func:`stop_on_signals` (``"SIGTERM"``, ...);
    None if none did (set by the caller, or not yet set)."""
    name = getattr(stop, "signal_name", None)
    return name if isinstance(name, str) else None


def said_stopped_before_start(prog: str, stop: threading.Event, waiting_for_hub: bool) -> int:
    """Exit status 0 for a stop signal that came before a daemon's first measurement, said in
    one line on stderr (a ``--json`` reader gets no counters: nothing was measured)."""
    by = signal_name_of(stop) or "request"
    where = "waiting for the zenoh hub" if waiting_for_hub else "starting"
    print(f"{prog}: stopped by {by} while {where}; nothing measured", file=sys.stderr)
    return 0


@contextlib.contextmanager
def stop_on_signals(stop: threading.Event | None = None) -> Iterator[threading.Event]:
    """Yield an event that SIGTERM or SIGINT sets; restore the previous handlers on exit.

    The event keeps which signal set it first (:func:`signal_name_of`; a :class:`StopEvent`
    when none is given). Outside the main thread (where Python cannot install handlers) the
    event is only set by the caller. A signal also arms :data:`STACKS_AFTER_S`'s stack dump
    (and, in an orphan, exit), cancelled on exit; :data:`STACKS_SIGNAL` dumps the stacks at
    any time inside.
    """
    event = StopEvent() if stop is None else stop
    previous: dict[int, object] = {}
    parent = os.getppid()

    def on_signal(signum: int, _frame: object) -> None:
        if not event.is_set():
            with contextlib.suppress(AttributeError, ValueError):  # a caller's slotted event
                event.signal_name = signal.Signals(signum).name  # type: ignore[attr-defined]
            orphaned = os.getppid() != parent
            with contextlib.suppress(OSError, ValueError, AttributeError):
                faulthandler.dump_traceback_later(STACKS_AFTER_S, exit=orphaned, file=sys.stderr)
        event.set()

    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            previous[sig] = signal.signal(sig, on_signal)
        # a stderr without a file descriptor (captured in-process) gets no dump
        with contextlib.suppress(OSError, ValueError, AttributeError):
            faulthandler.register(STACKS_SIGNAL, file=sys.stderr, all_threads=True)
    try:
        yield event
    finally:
        if previous:
            faulthandler.cancel_dump_traceback_later()
            faulthandler.unregister(STACKS_SIGNAL)  # False if it was never registered
        for sig, handler in previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]


def run_standalone(
    prog: str, body: Callable[[], int], errors: tuple[type[BaseException], ...] = ()
) -> int:
    """Run ``body``; a :class:`HalError` (or one of ``errors``) is reported as
    ``"<prog>: error: <message>"`` on stderr with exit status 2, Ctrl-C as 130. ``prog``
    appears once: a message that starts with ``"<prog>: "`` already is not prefixed again.
    An :class:`OSError` (a path the user gave: missing, a directory, a full disk) is one line
    naming the path and the reason: status 2 for :data:`USAGE_ERRNOS`, else 1; stdout's reader
    gone (``| head``) is :data:`SIGPIPE_STATUS` without a word."""
    from hal.errors import HalError

    try:
        return body()
    except (HalError, *errors) as exc:
        message = str(exc)
        if message.startswith(f"{prog}: "):
            message = message[len(prog) + 2 :]
        print(f"{prog}: error: {message}", file=sys.stderr)
        return 2
    except OSError as exc:
        if isinstance(exc, BrokenPipeError) and stdout_reader_gone():
            return SIGPIPE_STATUS
        print(f"{prog}: error: {os_error_line(exc)}", file=sys.stderr)
        return 2 if exc.errno in USAGE_ERRNOS else 1
    except KeyboardInterrupt:
        return 130


SIGPIPE_STATUS = 128 + signal.SIGPIPE
"""The status of a filter whose reader went away (``hil info --json | head``): what a shell
shows for a process SIGPIPE ended. Python ignores SIGPIPE, so the write raised instead."""


def stdout_reader_gone() -> bool:
    """True when stdout is a pipe without a reader (poll's POLLERR); stdout then points at
    /dev/null, so the flush at exit does not fail again. A broken pipe elsewhere (a child's)
    stays an error."""
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        gone = any(event & select.POLLERR for _, event in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no real stdout (captured, closed)
        return False
    if gone:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, fd)
        os.close(devnull)
    return gone


def os_error_line(exc: OSError) -> str:
    """``PATH: reason`` (``reason`` alone when the error names no path), on one line."""
    reason, name = exc.strerror or str(exc) or type(exc).__name__, exc.filename
    if isinstance(name, str | bytes):
        name = os.fsdecode(name)
    line = reason if name is None else f"{name}: {reason}"
    return " ".join(line.split())
