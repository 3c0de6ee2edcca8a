"""The ``hil`` command line: one console script, one subcommand per job.

Subcommands register themselves from small modules under :mod:`rt_controller.commands`; the
emulator-side ones dispatch to :mod:`plant_emulator`'s entry points (the only place the two
packages meet).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from typing import Any

from hal.errors import HalError
from rt_controller.errors import ControllerError

Handler = Callable[[argparse.Namespace], int]

COMMAND_MODULES = (
    "up",
    "emulator",
    "vision",
    "controller",
    "simulate",
    "replay",
    "report",
    "experiment",
    "bench",
)
"""Modules of :mod:`rt_controller.commands`, each with ``register(subparsers)``."""


def print_summary(summary: dict[str, Any], as_json: bool, title: str) -> None:
    """One JSON object on stdout, or a two-column table for people."""
    if as_json:
        print(json.dumps(summary, sort_keys=False))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, show_header=False)
    for key, value in summary.items():
        if isinstance(value, float):
            text = f"{value:.6g}"
        elif isinstance(value, list):
            text = ", ".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in value)
        else:
            text = str(value)
        table.add_row(key, text)
    Console().print(table)


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
    from rt_controller.supervise import follow_parent

    follow_parent()  # a rig child never outlives `hil up`
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except (HalError, ControllerError) as exc:
        print(f"hil {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
