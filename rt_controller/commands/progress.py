"""What a slow command is doing, on stderr (numba compiling on a cold cache, a long run).

A :meth:`Progress.stage` that ends within ``after_s`` (default 1 s, or ``$HIL_PROGRESS_AFTER_S``)
says nothing, so quick commands stay as quiet as before. Once a stage has lasted that long it
is announced: on a terminal as a rich spinner with the message, in a pipe or a log file as one
plain line ``"hil CMD: MESSAGE ..."`` (no animation). A stage that was announced ends with one
line ``"hil CMD: MESSAGE: done in 12.3 s"``; one that fails ends silently (the error line
follows). stdout is never written: it stays the JSON or summary that scripts parse.
``--quiet`` (:func:`add_quiet_option`) turns it all off.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import threading
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.console import Console

AFTER_ENV = "HIL_PROGRESS_AFTER_S"
DEFAULT_AFTER_S = 1.0
"""A stage announces itself after this long (a command silent for about 2 s looks hung)."""


def add_quiet_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages on stderr")


def _after_from_env() -> float:
    try:
        value = float(os.environ.get(AFTER_ENV, DEFAULT_AFTER_S))
    except ValueError:
        return DEFAULT_AFTER_S
    return value if value >= 0 else DEFAULT_AFTER_S


class Progress:
    """Progress messages of one command (``prog``, e.g. ``"hil simulate"``) on stderr."""

    def __init__(
        self,
        prog: str,
        *,
        quiet: bool = False,
        after_s: float | None = None,
        console: Console | None = None,
    ) -> None:
        self.prog = prog
        self.quiet = quiet
        self.after_s = _after_from_env() if after_s is None else after_s
        self._console = console

    @classmethod
    def of(cls, args: argparse.Namespace, prog: str) -> Progress:
        """The progress of a command whose parser has :func:`add_quiet_option`."""
        return cls(prog, quiet=getattr(args, "quiet", False))

    @property
    def console(self) -> Console:
        if self._console is None:
            from rich.console import Console

            self._console = Console(stderr=True)
        return self._console

    def line(self, message: str) -> None:
        """One plain line now (unless quiet)."""
        if not self.quiet:
            self.console.print(
                f"{self.prog}: {message}", markup=False, highlight=False, soft_wrap=True
            )

    @contextlib.contextmanager
    def stage(self, message: str) -> Iterator[None]:
        """Announce ``message`` once the block has run for ``after_s``; say when it is done."""
        if self.quiet:
            yield
            return
        lock = threading.Lock()
        state: dict[str, Any] = {"announced": False, "over": False, "status": None}

        def announce() -> None:
            with lock:
                if state["over"]:
                    return
                state["announced"] = True
                if self.console.is_terminal:
                    state["status"] = self.console.status(f"{self.prog}: {message}")
                    state["status"].start()
                else:
                    self.line(f"{message} ...")

        start = time.monotonic()
        timer: threading.Timer | None = None
        if self.after_s <= 0:
            announce()
        else:
            timer = threading.Timer(self.after_s, announce)
            timer.daemon = True
            timer.name = "hil-progress"
            timer.start()
        ok = False
        try:
            yield
            ok = True
        finally:
            if timer is not None:
                timer.cancel()
                timer.join()
            with lock:
                state["over"] = True
            if state["status"] is not None:
                state["status"].stop()
            if ok and state["announced"]:
                self.line(f"{message}: done in {time.monotonic() - start:.1f} s")
