"""The ``hil`` command line: one console script, one subcommand per job.

Subcommands register themselves from small modules under :mod:`rt_controller.commands`; the
emulator-side ones dispatch to :mod:`plant_emulator`'s entry points (the only place the two
packages meet).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from hal.signals import run_standalone
from rt_controller.errors import ControllerError

Handler = Callable[[argparse.Namespace], int]

COMMAND_MODULES = (
    "up",
    "keygen",
    "emulator",
    "vision",
    "controller",
    "monitor",
    "simulate",
    "replay",
    "report",
    "experiment",
    "bench",
)
"""Modules of :mod:`rt_controller.commands`, each with ``register(subparsers)``."""


def build_parser() -> argparse.ArgumentParser:
    import importlib

    parser = argparse.ArgumentParser(
        prog="hil",
        description="Hardware-in-the-loop receding-horizon visual-servo controller.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"rt_controller.commands.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from rt_controller.rig.supervise import follow_parent

    follow_parent()  # a rig child never outlives `hil up`
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Handler = args.handler
    return run_standalone(f"hil {args.command}", lambda: handler(args), (ControllerError,))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
