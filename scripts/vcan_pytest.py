#!/usr/bin/env python3
"""Run the ``vcan``-marked pytest tests (or any command) on a real SocketCAN ``vcan0``.

Usage::

    scripts/vcan_pytest.py [OPTIONS] [-- PYTEST_ARGS...]
    scripts/vcan_pytest.py [OPTIONS] --exec -- CMD [ARGS...]

Examples::

    .venv/bin/python scripts/vcan_pytest.py                  # python -m pytest -m vcan
    .venv/bin/python scripts/vcan_pytest.py -- -x -k smoke   # extra pytest arguments
    .venv/bin/python scripts/vcan_pytest.py --exec -- ip -details link show vcan0
    .venv/bin/python scripts/vcan_pytest.py --exec -- hil emulator --can socketcan:vcan0

Where the command runs, first match wins:

1. Native: the host already has a ``vcan0`` interface (``/sys/class/net/vcan0`` exists).
   Create one with ``sudo modprobe vcan; sudo ip link add dev vcan0 type vcan;
   sudo ip link set vcan0 mtu 72; sudo ip link set up vcan0`` (MTU 72: CAN FD frames).
2. User-mode Linux (UML): ``linux.uml`` and its module tree ``/usr/lib/uml/modules/<version>``
   are installed (Debian/Ubuntu package ``user-mode-linux``). UML is a real Linux kernel running
   as an ordinary process, so this works in containers and CI runners whose kernel has no
   SocketCAN. The script boots UML with the host filesystem as its root (hostfs), and a generated
   init script mounts /proc, /sys, a tmpfs on /dev/shm (zenoh and multiprocessing need it),
   brings ``lo`` up, loads can, can-raw, can-bcm, can-dev and vcan with ``insmod``, creates
   ``vcan0``, runs the command with a curated environment, records its output and exit
   status in a temporary directory and powers the virtual machine off. The host streams that
   output while the command runs and exits with the command's exit status. A host-side timeout
   (``--timeout``, default 1200 s) kills the UML process group, so a wedged guest never hangs CI.
3. Running as root with ``apt-get`` available: install ``user-mode-linux kmod can-utils``
   (plus ``iproute2`` if ``ip`` is missing), then use UML (disable with ``--no-install``).
4. Otherwise: with ``CI=true`` fail (exit 1) with a clear message; locally print one line saying
   why the vcan tests are skipped and how to enable them, and exit 0.

On a CPU with AMX tiles (Intel Sapphire Rapids and later), Debian bookworm's UML 6.1 panics in
the guest's init ("userspace - ptrace set fp regs failed, errno = 14": its XSAVE buffer is
smaller than the host's ptrace regset) before anything runs. That boot failure is recognised,
and the command is run again under Debian unstable's UML 7.x, which boots there
(``uml_newer.py``: installed into ``.uml/`` on first use, checked as apt checks packages). If
that cannot be installed either, the vcan tests are reported "NOT RUN" with the reason: exit 1
under ``CI=true`` or ``--exec``, 0 locally.

Where it runs: pytest from the repository root; an ``--exec`` command in the caller's working
directory, so relative paths (``--key-file rig.key``) and the logs it writes stay there. The UML
guest sees the host's whole file system at the same paths (hostfs) except /proc, /sys and /dev,
which it mounts anew: ``--exec`` refuses to start from a directory under those.

In pytest mode, exit status 5 (no tests collected) is an error under ``CI=true`` (the vcan tests
must run); locally it is reported as a warning and the script exits 0.

Inside the command's environment ``HIL_VCAN_REQUIRED=1`` is set (``tests/support/vcan.py`` then
turns a missing ``vcan0`` into a failure instead of a skip) and, under UML, ``HIL_IN_UML=1``.
Under UML the command gets no standard input, the guest has no IPv6 and runs roughly 10x slower
than the host; network traffic stays inside the guest (only ``lo`` and ``vcan0`` exist there).

Only the standard library is used, so the script runs with any Python >= 3.9. Its parts:
``vcan_host.py`` (what the host offers, the command's environment) and ``vcan_uml.py`` (the
run inside user-mode Linux).
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from vcan_host import (
    REPO_ROOT,
    VCAN_CHANNEL,
    apt_install,
    build_guest_env,
    default_python,
    is_ci,
    is_root,
    log,
    native_vcan_state,
    uml_missing,
)
from vcan_uml import EXIT_UML_CANNOT_BOOT, UML_FP_PANIC, guest_hidden_mount, run_uml

ENABLE_HINT = (
    "enable with: sudo modprobe vcan; sudo ip link add dev vcan0 type vcan; "
    "sudo ip link set vcan0 mtu 72; sudo ip link set up vcan0  "
    "(or: sudo apt-get install user-mode-linux kmod can-utils)"
)
EXIT_NO_TESTS = 5


# --------------------------------------------------------------------------------------------
# Native run
# --------------------------------------------------------------------------------------------


def run_native(cmd: list[str], env: dict[str, str], cwd: Path) -> int:
    state = native_vcan_state()
    if state == "down":
        log(f"warning: {VCAN_CHANNEL} exists but is down (sudo ip link set up {VCAN_CHANNEL})")
    log(f"native {VCAN_CHANNEL} found; running: {shlex.join(cmd)}")
    try:
        return subprocess.run(cmd, cwd=cwd, env=env, check=False).returncode
    except FileNotFoundError as exc:
        log(f"cannot run {cmd[0]!r}: {exc}")
        return 127


# --------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    if "--" in argv:
        split = argv.index("--")
        ours, rest = argv[:split], argv[split + 1 :]
    else:
        ours, rest = argv, []
    parser = argparse.ArgumentParser(
        prog="vcan_pytest.py",
        description=(
            "Run the vcan-marked pytest tests (or, with --exec, any command) where a real "
            "SocketCAN vcan0 exists: natively, else inside user-mode Linux."
        ),
        epilog=(
            "Arguments after `--` go to pytest (or are the command with --exec). "
            "Options of this script must come before `--` (pytest's own --timeout goes after)."
        ),
        allow_abbrev=False,
    )
    parser.add_argument(
        "--exec",
        dest="exec_mode",
        action="store_true",
        help=(
            "run the command after `--` instead of pytest (e.g. --exec -- ip link show vcan0), "
            "in the current directory (pytest runs in the repository root); user-mode Linux "
            "sees the host's files except under /proc, /sys and /dev"
        ),
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=1200.0,
        metavar="SECONDS",
        help="host-side limit on the whole UML boot + run (default: %(default)s)",
    )
    parser.add_argument(
        "--mode",
        choices=("auto", "native", "uml"),
        default="auto",
        help="force native vcan0 or user-mode Linux (default: auto)",
    )
    parser.add_argument(
        "--mem", type=int, default=1024, metavar="MIB", help="UML guest RAM (default: %(default)s)"
    )
    parser.add_argument(
        "--python", default=None, help="interpreter that runs pytest (default: venv python)"
    )
    parser.add_argument(
        "--env",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="extra environment variable for the command (repeatable)",
    )
    parser.add_argument(
        "--no-install", action="store_true", help="never apt-get install user-mode-linux"
    )
    parser.add_argument(
        "--keep", action="store_true", help="keep the UML work dir (init script and logs)"
    )
    args, unknown = parser.parse_known_args(ours)
    if args.exec_mode and unknown:
        parser.error(f"unexpected arguments before `--`: {' '.join(unknown)}")
    if args.exec_mode and not rest:
        parser.error("--exec needs a command after `--`")
    if args.timeout <= 0:
        parser.error("--timeout must be positive")
    return args, unknown + rest


def run_newer_uml(cmd: list[str], env: dict[str, str], args: argparse.Namespace, cwd: Path) -> int:
    """The distribution's UML could not boot on this CPU (AMX tiles: ``uml_newer``): run
    ``cmd`` under Debian unstable's newer UML instead, installed on first use."""
    import uml_newer

    log("the distribution's user-mode Linux cannot boot on this CPU; trying a newer one")
    try:
        newer = uml_newer.fetch()
    except uml_newer.UmlFetchError as exc:
        log(f"cannot install a newer user-mode Linux: {exc}")
        return EXIT_UML_CANNOT_BOOT
    kernel = (str(newer.binary), newer.modules_root)
    return run_uml(cmd, env, args.timeout, args.mem, args.keep, kernel, cwd)


def main(argv: list[str] | None = None) -> int:
    args, rest = parse_args(sys.argv[1:] if argv is None else argv)
    python = args.python or default_python()
    if args.exec_mode:
        cmd = rest
    else:
        cmd = [python, "-m", "pytest", "-m", "vcan", *rest]
        if sys.stdout.isatty() and not any(a.startswith("--color") for a in rest):
            cmd.append("--color=yes")

    mode = args.mode
    if mode == "auto":
        if native_vcan_state() is not None:
            mode = "native"
        elif not uml_missing():
            mode = "uml"
        elif is_root() and shutil.which("apt-get") and not args.no_install:
            mode = "uml" if apt_install() and not uml_missing() else "unavailable"
        else:
            mode = "unavailable"
    elif mode == "native" and native_vcan_state() is None:
        log(f"--mode native but the host has no {VCAN_CHANNEL}; {ENABLE_HINT}")
        return 1
    elif mode == "uml" and uml_missing():
        log(f"--mode uml but missing: {', '.join(uml_missing())}")
        return 1

    what = "command" if args.exec_mode else "vcan tests"
    if mode == "unavailable":
        missing = ", ".join(uml_missing()) or "user-mode-linux"
        reason = f"no {VCAN_CHANNEL} on this host and user-mode Linux unavailable ({missing})"
        if is_ci() or args.exec_mode:
            log(f"error: cannot run the {what}: {reason}; {ENABLE_HINT}")
            return 1
        print(f"vcan tests skipped: {reason}; {ENABLE_HINT}")
        return 0

    cwd = Path.cwd() if args.exec_mode else REPO_ROOT
    hidden = guest_hidden_mount(cwd) if mode == "uml" else None
    if hidden:
        log(
            f"error: user-mode Linux cannot see the current directory {cwd} (the guest mounts "
            f"its own {hidden}); run from another directory"
        )
        return 2
    env = build_guest_env(python, args.env, in_uml=(mode == "uml"))
    if mode == "native":
        rc = run_native(cmd, env, cwd)
    else:
        rc = run_uml(cmd, env, args.timeout, args.mem, args.keep, cwd=cwd)

    if rc == EXIT_UML_CANNOT_BOOT:
        rc = run_newer_uml(cmd, env, args, cwd)
    if rc == EXIT_UML_CANNOT_BOOT:
        log(
            f"{what} NOT RUN: neither the distribution's user-mode Linux nor a newer one "
            f"boots on this host's CPU ('{UML_FP_PANIC}, errno = 14' above); {ENABLE_HINT}"
        )
        return 1 if args.exec_mode or is_ci() else 0
    if not args.exec_mode and rc == EXIT_NO_TESTS:
        if is_ci():
            log(
                "error: pytest collected no vcan-marked tests (exit 5); under CI=true the "
                "vcan tests must run: check the -m vcan marker and the test selection"
            )
            return EXIT_NO_TESTS
        log("warning: pytest collected no vcan-marked tests (exit 5)")
        return 0
    return rc


if __name__ == "__main__":
    sys.exit(main())
