"""Validated argparse value types shared by every ``hil`` subcommand (controller and emulator
side alike): a bad number is refused while the command line is parsed, with argparse's one-line
``error: argument --X: ...`` and status 2, before anything starts or waits.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

MAX_DURATION_S = 7 * 24 * 3600.0
"""Longest run a command accepts (one week)."""


def bounded_float(
    lo: float, hi: float, *, lo_inclusive: bool = False, what: str = "value"
) -> Callable[[str], float]:
    """A float in ``(lo, hi]`` (``[lo, hi]`` with ``lo_inclusive``); NaN and inf refused."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, got {text!r}") from None
        above = value >= lo if lo_inclusive else value > lo
        if not (math.isfinite(value) and above and value <= hi):
            bracket = "[" if lo_inclusive else "("
            raise argparse.ArgumentTypeError(
                f"{what} must be in {bracket}{lo:g}, {hi:g}], got {text}"
            )
        return value

    parse.__name__ = what  # argparse names the type in its messages
    return parse


def bounded_int(lo: int, hi: int, *, what: str = "value") -> Callable[[str], int]:
    """An integer in ``[lo, hi]``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be an integer, got {text!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{what} must be in [{lo}, {hi}], got {text}")
        return value

    parse.__name__ = what
    return parse


def duration(*, zero_means_forever: bool = False) -> Callable[[str], float]:
    """Seconds in ``(0, one week]``; with ``zero_means_forever`` also 0 (run until stopped)."""
    return bounded_float(
        0.0, MAX_DURATION_S, lo_inclusive=zero_means_forever, what="duration in seconds"
    )


def path_given(text: str) -> str:
    """A path option's value that is not empty: ``--out ""`` would otherwise be taken as no
    option at all and write to the default place."""
    if not text.strip():
        raise argparse.ArgumentTypeError("the path is empty")
    return text


path_given.__name__ = "path"


def add_key_option(p: argparse.ArgumentParser) -> None:
    """``--key-file``: the rig key (``hil keygen FILE``), overriding ``transport.key_file``."""
    p.add_argument(
        "--key-file",
        metavar="FILE",
        help="rig key authenticating CAN frames and vision messages (make one with `hil keygen "
        "FILE`, mode 0600; default: transport.key_file of the config)",
    )


ZENOH_ROLES = {"auto": None, "hub": True, "client": False}
"""``--zenoh-role`` -> ``open_session``'s ``listen``."""


FILE_SETS = {
    "zenoh_endpoint": ("--zenoh-endpoint", "its own endpoints"),
    "zenoh_role": ("--zenoh-role", "the role: its mode and listen endpoints"),
    "wait": ("--wait", "how long a client waits for its hub: connect timeout_ms"),
}
"""The options a ``--zenoh-config`` file makes meaningless, and what in the file sets each."""


def check_zenoh_options(args: argparse.Namespace) -> None:
    """Refuse ``--zenoh-endpoint``, ``--zenoh-role`` or ``--wait`` beside ``--zenoh-config``
    (:class:`HalConfigError`, exit 2): the file sets each, and the option would be ignored
    without a word."""
    from hal.errors import HalConfigError

    if not getattr(args, "zenoh_config", None):
        return
    for name, (option, what) in FILE_SETS.items():
        if getattr(args, name, None) is not None:
            raise HalConfigError(
                f"{option} and --zenoh-config: give one (a zenoh config file sets {what})"
            )


def zenoh_session_options(args: argparse.Namespace) -> dict[str, Any]:
    """``open_session`` keywords from a process's ``--zenoh-endpoint``, ``--zenoh-config``,
    ``--zenoh-role`` and ``--wait`` (None: the default wait)."""
    out: dict[str, Any] = {
        "endpoint": args.zenoh_endpoint,
        "config_file": args.zenoh_config,
        "listen": ZENOH_ROLES[args.zenoh_role or "client"],
    }
    if getattr(args, "wait", None) is not None:
        out["wait_s"] = args.wait
    return out
