"""An offline command (replay, recover, export, bench) stopped by a signal: one line naming
the signal and what was and was not written, and the shell's status for it (130, 143).

Kept apart from the commands' modules: no numpy at import, shared by every command that
writes files or runs for long without a rig supervisor of its own.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

INTERRUPT_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Interrupted(KeyboardInterrupt):
    """A stop signal (:data:`INTERRUPT_SIGNALS`) while an offline command worked. A
    :class:`KeyboardInterrupt`, so no ``except Exception`` on the way (a damaged-log walk, a
    library) takes it for a failure: it unwinds every ``written_whole`` block, which removes
    its file cut short and leaves the one it would have replaced as it was."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextlib.contextmanager
def _signals_handled(handler: Any) -> Iterator[None]:
    """While inside, :data:`INTERRUPT_SIGNALS` go to ``handler`` (main thread only); a signal
    ignored when the command started (``nohup``) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {
        sig: signal.signal(sig, handler)
        for sig in INTERRUPT_SIGNALS
        if signal.getsignal(sig) is not signal.SIG_IGN
    }
    try:
        yield
    finally:
        for sig, before in previous.items():
            signal.signal(sig, signal.SIG_DFL if before is None else before)


def _interrupt(signum: int, _frame: object) -> None:
    raise Interrupted(signum)


def run_interruptible(prog: str, body: Callable[[], int], left: Callable[[], str]) -> int:
    """``body()``; Ctrl-C, SIGTERM or SIGHUP end it with one line on stderr, ``PROG:
    interrupted by SIGINT; LEFT`` (``left()``: what was and was not written, or what was not
    measured), and the shell's status for the signal, 128 + its number (130, 143, 129). The
    signal unwinds ``body`` as Ctrl-C does, so its ``finally`` blocks stop what it started and
    remove its temporary files."""
    try:
        with _signals_handled(_interrupt):
            return body()
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else int(signal.SIGINT)
        with _signals_handled(signal.SIG_IGN):  # a second signal does not cut the line short
            tail = left()
            name = signal.Signals(signum).name
            print(f"{prog}: interrupted by {name}" + (f"; {tail}" if tail else ""), file=sys.stderr)
        return 128 + signum


def unwritten(path: Path, existed: bool) -> str:
    """``PATH not written`` for an output an interrupt stopped, removing its temporary file if
    a child process (killed on the signal) left one; the file there before is named as kept."""
    from hal.whole_file import partial_path

    with contextlib.suppress(OSError):
        partial_path(path).unlink(missing_ok=True)
    return f"{path} not written" + (" (the file there before is as it was)" if existed else "")


__all__ = ["INTERRUPT_SIGNALS", "Interrupted", "run_interruptible", "unwritten"]
