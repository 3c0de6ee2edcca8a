"""The ``hil`` command line: one console script, one subcommand per job.

Subcommands register themselves from small modules under :mod:`rt_controller.commands`; the
emulator-side ones dispatch to :mod:`plant_emulator`'s entry points (the only place the two
packages meet).
"""

from __future__ import annotations

import os

# One BLAS thread (before numpy is imported): the control law's matrices are tiny, and the
# control process runs no other thread of its own.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from hal.signals import run_standalone
from rt_controller.errors import ControllerError

Handler = Callable[[argparse.Namespace], int]
PACKAGE = "hil-rhc-visual-servo"

COMMAND_MODULES = (
    "up",
    "keygen",
    "camera",
    "emulator",
    "cia402",
    "vision",
    "controller",
    "monitor",
    "param",
    "simulate",
    "replay",
    "report",
    "info",
    "recover",
    "export",
    "experiment",
    "sweep",
    "bench",
)
"""Modules of :mod:`rt_controller.commands`, each with ``register(subparsers)``."""


class HilParser(argparse.ArgumentParser):
    """The parser of ``hil`` and of each of its (sub)commands (argparse makes the subcommands'
    of the parent's class): each puts itself in the namespace (``usage_parser``), so that an
    unknown option is reported with the usage of the command it was given to."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.set_defaults(usage_parser=self)
        self._intermixing = False
        self._args: list[str] = []

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        """A command without subcommands takes its options between its positionals too
        (``hil param set --at-tick 5 gains.kp=0.3``): plain argparse gives a ``nargs="*"``
        positional nothing once an option follows the first positional, and the rest is an
        "unrecognized argument"."""
        if not self._intermixing:
            self._args = list(sys.argv[1:] if args is None else args)  # for error()
        if self._intermixing or self._subparsers is not None:
            return super().parse_known_args(args, namespace)
        self._intermixing = True  # the intermixed parse calls this method again
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._intermixing = False

    def error(self, message: str) -> NoReturn:
        """argparse's error, with how to give a value that begins with ``-`` (``--dropout
        -1:2``: argparse takes ``-1:2`` for an option and says a value is missing)."""
        import re

        missing = re.fullmatch(r"argument (\S+): expected one argument", message)
        if missing:
            names, args = missing.group(1).split("/"), self._args
            given = [i for i, a in enumerate(args[:-1]) if a in names]
            if given and args[given[-1] + 1].startswith("-"):
                message += f" (a value that begins with '-' is written {names[-1]}=VALUE)"
        super().error(message)


def build_parser() -> argparse.ArgumentParser:
    import importlib

    parser = HilParser(
        prog="hil",
        description="Hardware-in-the-loop receding-horizon visual-servo controller.",
    )
    parser.add_argument("--version", action="version", version=f"hil {package_version()}")
    parser.add_argument(
        "--target-of",
        metavar="LOG.mcap",
        help="compile numba's code for the CPU target LOG records, when this host can run it "
        "(rerun an experiment's or a sweep's run as it was compiled)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"rt_controller.commands.{name}").register(sub)
    return parser


def package_version() -> str:
    """The installed version of the package (``importlib.metadata``), "unknown" when it runs
    from a source tree that was never installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(PACKAGE)
    except PackageNotFoundError:
        return "unknown"


def unrecognized(parser: argparse.ArgumentParser, unknown: list[str]) -> str:
    """argparse's "unrecognized arguments", with what the command calls an option of that name
    where it has one: another command's spelling (``hil controller --lockstep``: ``--clock
    lockstep``; ``hil emulator --clock lockstep``: ``--lockstep``) or a near miss
    (``--durations``)."""
    import difflib

    actions = {name: a for a in parser._actions for name in a.option_strings}
    hints: list[str] = []
    for i, token in enumerate(unknown):
        name = token.split("=", 1)[0]
        if not name.startswith("--"):
            continue
        value = token.partition("=")[2] or (unknown[i + 1] if i + 1 < len(unknown) else "")
        choice = [o for o, a in actions.items() if a.choices and name[2:] in a.choices]
        near = difflib.get_close_matches(name, list(actions), n=1, cutoff=0.8)
        if choice:
            hints.append(f"{choice[0]} {name[2:]}")
        elif f"--{value}" in actions and actions[f"--{value}"].nargs == 0:
            hints.append(f"--{value}")
        elif near:
            hints.append(near[0])
    said = f"unrecognized arguments: {' '.join(unknown)}"
    return f"{said} (did you mean {', '.join(hints)}?)" if hints else said


def main(argv: Sequence[str] | None = None) -> int:
    from rt_controller.rig.supervise import follow_parent

    follow_parent()  # a rig child never outlives `hil up`
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        args.usage_parser.error(unrecognized(args.usage_parser, unknown))
    handler: Handler = args.handler

    def body() -> int:
        if args.target_of is not None:
            from rt_controller.logtools.target_replay import rerun_on_log_target

            rest = without_option(list(sys.argv[1:] if argv is None else argv), "--target-of")
            status = rerun_on_log_target(args.target_of, rest, say_on_stderr)
            if status is not None:
                return status
        return explained_extras(handler, args)

    return run_standalone(args.usage_parser.prog, body, (ControllerError,))  # "hil param set"


def say_on_stderr(line: str) -> None:
    print(f"hil: {line}", file=sys.stderr)


def without_option(argv: list[str], option: str) -> list[str]:
    """``argv`` without ``option VALUE`` and ``option=VALUE``."""
    out, skip = [], False
    for token in argv:
        if skip:
            skip = False
        elif token == option:
            skip = True
        elif not token.startswith(f"{option}="):
            out.append(token)
    return out


def explained_extras(handler: Handler, args: argparse.Namespace) -> int:
    """Run ``handler``; a module of an extra that a code path imports without
    :func:`rt_controller.extras.require` still ends in the one-line error naming the extra."""
    from rt_controller.extras import as_missing_extra

    try:
        return handler(args)
    except ModuleNotFoundError as exc:
        explained = as_missing_extra(exc, "this command")
        if explained is None:
            raise
        raise explained from exc


def exit_now(status: int) -> None:
    """End the process with ``status`` without the interpreter's teardown, which costs a rig
    child about 0.2 s (numba's LLVM) after its work is done: stdio is flushed and the atexit
    handlers run first; every file, bus and session was closed by the command itself. With a
    non-daemon thread still running, or under a profiler or tracer (``-m cProfile``, coverage:
    they write their results at the normal exit), the normal exit is taken instead."""
    import atexit
    import contextlib
    import os
    import threading

    watched = sys.getprofile() is not None or sys.gettrace() is not None
    if watched or any(t.is_alive() and not t.daemon for t in threading.enumerate()[1:]):
        sys.exit(status)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed or broken pipe
            stream.flush()
    os._exit(status)


if __name__ == "__main__":  # pragma: no cover - how the rig starts its children
    exit_now(main())
