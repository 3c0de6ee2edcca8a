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
def _signals_raise() -> Iterator[None]:
    """While inside, :data:`INTERRUPT_SIGNALS` raise :class:`Interrupted` (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, _frame: object) -> None:
        raise Interrupted(signum)

    previous = {sig: signal.signal(sig, interrupt) for sig in INTERRUPT_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run_interruptible(prog: str, body: Callable[[], int], left: Callable[[], str]) -> int:
    """``body()``; Ctrl-C, SIGTERM or SIGHUP end it with one line on stderr, ``PROG:
    interrupted by SIGINT; LEFT`` (``left()``: what was and was not written), and the
    shell's status for the signal, 128 + its number (130, 143)."""
    try:
        with _signals_raise():
            return body()
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else int(signal.SIGINT)
        with _signals_raise():  # a second signal does not cut the line short
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
