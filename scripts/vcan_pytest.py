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
   brings ``lo`` up, loads can, can-raw, can-dev and vcan with ``insmod``, creates ``vcan0``, runs
   the command from the repository root with a curated environment, records its output and exit
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

In pytest mode, exit status 5 (no tests collected) is an error under ``CI=true`` (the vcan tests
must run); locally it is reported as a warning and the script exits 0.

Inside the command's environment ``HIL_VCAN_REQUIRED=1`` is set (``tests/support/vcan.py`` then
turns a missing ``vcan0`` into a failure instead of a skip) and, under UML, ``HIL_IN_UML=1``.
Under UML the command gets no standard input, the guest has no IPv6 and runs roughly 10x slower
than the host; network traffic stays inside the guest (only ``lo`` and ``vcan0`` exist there).

Only the standard library is used, so the script runs with any Python >= 3.9.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
VCAN_CHANNEL = "vcan0"
UML_MODULES_ROOT = Path("/usr/lib/uml/modules")
# Loaded in this order (dependencies first); located by file name under the module tree.
CAN_MODULES = ("can", "can-raw", "can-dev", "vcan")
APT_PACKAGES = ("user-mode-linux", "kmod", "can-utils")
ENABLE_HINT = (
    "enable with: sudo modprobe vcan; sudo ip link add dev vcan0 type vcan; "
    "sudo ip link set vcan0 mtu 72; sudo ip link set up vcan0  "
    "(or: sudo apt-get install user-mode-linux kmod can-utils)"
)
# Environment passed into the UML guest: exact names and name prefixes. Everything else on the
# host (tokens, sockets, display, ...) stays out, because the init script is a file on disk.
ENV_PASS_NAMES = frozenset(
    {
        "CI",
        "GITHUB_ACTIONS",
        "USER",
        "LOGNAME",
        "LANG",
        "LANGUAGE",
        "TZ",
        "TERM",
        "COLUMNS",
        "NO_COLOR",
        "FORCE_COLOR",
        "PY_COLORS",
        "RUST_LOG",
        "PYTHONHASHSEED",
        "PYTHONWARNINGS",
        "PYTHONFAULTHANDLER",
        "PYTHONDEVMODE",
    }
)
ENV_PASS_PREFIXES = ("HIL_", "PYTEST_", "NUMBA_", "ZENOH_", "LC_")
EXIT_NO_TESTS = 5
EXIT_TIMEOUT = 124
EXIT_UML_CANNOT_BOOT = 125
"""run_uml: the guest died at boot with UML_FP_PANIC (UML cannot run on this host's CPU)."""
UML_FP_PANIC = "ptrace set fp regs failed"


def log(msg: str) -> None:
    """Print a status line of this script (on stderr, so command output stays clean)."""
    print(f"vcan_pytest: {msg}", file=sys.stderr, flush=True)


def is_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in {"true", "1", "yes", "on"}


def is_root() -> bool:
    return hasattr(os, "geteuid") and os.geteuid() == 0


# --------------------------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------------------------


def native_vcan_state(channel: str = VCAN_CHANNEL) -> str | None:
    """Return None when the host has no such interface, else "up" or "down"."""
    net = Path("/sys/class/net") / channel
    if not net.exists():
        return None
    try:
        flags = int((net / "flags").read_text().strip(), 16)
    except (OSError, ValueError):
        return "up"
    return "up" if flags & 0x1 else "down"


def find_uml_binary() -> str | None:
    found = shutil.which("linux.uml")
    if found:
        return found
    if os.access("/usr/bin/linux.uml", os.X_OK):
        return "/usr/bin/linux.uml"
    return None


def uml_module_trees() -> list[Path]:
    """Module trees (one per UML kernel version) that contain a vcan module."""
    if not UML_MODULES_ROOT.is_dir():
        return []
    trees = []
    for tree in sorted(UML_MODULES_ROOT.iterdir()):
        if tree.is_dir() and any(tree.rglob("vcan.ko*")):
            trees.append(tree)
    return trees


def uml_missing() -> list[str]:
    """What is missing to run the vcan tests under UML (empty list: ready)."""
    missing = []
    if find_uml_binary() is None:
        missing.append("linux.uml (package user-mode-linux)")
    if not uml_module_trees():
        missing.append(f"vcan module under {UML_MODULES_ROOT} (package user-mode-linux)")
    if shutil.which("insmod") is None and not Path("/usr/sbin/insmod").exists():
        missing.append("insmod (package kmod)")
    if shutil.which("ip") is None and not Path("/usr/sbin/ip").exists():
        missing.append("ip (package iproute2)")
    return missing


def apt_install() -> bool:
    """Install UML and friends with apt-get (root only). Returns True on success."""
    packages = list(APT_PACKAGES)
    if shutil.which("ip") is None and not Path("/usr/sbin/ip").exists():
        packages.append("iproute2")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    log(f"installing {' '.join(packages)} with apt-get (host has no vcan0 and no UML)")
    for cmd in (
        ["apt-get", "update", "-q"],
        ["apt-get", "install", "-y", "-q", "--no-install-recommends", *packages],
    ):
        result = subprocess.run(cmd, env=env, stdout=sys.stderr, check=False)
        if result.returncode != 0:
            log(f"`{shlex.join(cmd)}` failed with exit code {result.returncode}")
            return False
    return True


# --------------------------------------------------------------------------------------------
# Command and environment
# --------------------------------------------------------------------------------------------


def default_python() -> str:
    """The interpreter that runs pytest: the active venv, else the repo's .venv, else ours."""
    in_venv = sys.prefix != getattr(sys, "base_prefix", sys.prefix)
    if in_venv or os.environ.get("VIRTUAL_ENV"):
        return sys.executable
    repo_venv = REPO_ROOT / ".venv" / "bin" / "python"
    if repo_venv.exists():
        return str(repo_venv)
    return sys.executable


def venv_of(python: str) -> Path | None:
    """The virtual environment a python executable belongs to (without resolving symlinks)."""
    bindir = Path(python).absolute().parent
    if (bindir.parent / "pyvenv.cfg").exists():
        return bindir.parent
    return None


def build_guest_env(python: str, extra: list[str], in_uml: bool) -> dict[str, str]:
    """Environment for the command under UML (curated) or natively (host env plus markers)."""
    if in_uml:
        env = {
            k: v
            for k, v in os.environ.items()
            if k in ENV_PASS_NAMES or k.startswith(ENV_PASS_PREFIXES)
        }
    else:
        env = dict(os.environ)
    venv = venv_of(python)
    path_parts = [p for p in os.environ.get("PATH", "").split(os.pathsep) if p]
    for std in ("/usr/local/sbin", "/usr/local/bin", "/usr/sbin", "/usr/bin", "/sbin", "/bin"):
        if std not in path_parts:
            path_parts.append(std)
    if venv is not None:
        vbin = str(venv / "bin")
        path_parts = [vbin] + [p for p in path_parts if p != vbin]
        env["VIRTUAL_ENV"] = str(venv)
    env["PATH"] = os.pathsep.join(dict.fromkeys(path_parts))  # de-duplicated, order kept
    pythonpath = [str(REPO_ROOT)] + [
        p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and p != str(REPO_ROOT)
    ]
    env["PYTHONPATH"] = os.pathsep.join(pythonpath)
    env["HIL_VCAN_REQUIRED"] = "1"
    if in_uml:
        env["HOME"] = os.environ.get("HOME") or "/root"
        env.setdefault("LANG", "C.UTF-8")
        env["PYTHONUNBUFFERED"] = "1"
        env["PYTHONIOENCODING"] = "utf-8"
        env["TMPDIR"] = "/tmp"
        env["HIL_IN_UML"] = "1"
    for item in extra:
        key, sep, value = item.partition("=")
        if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
            raise SystemExit(f"vcan_pytest: --env expects NAME=VALUE, got {item!r}")
        env[key] = value
    return {k: v for k, v in env.items() if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k)}


# --------------------------------------------------------------------------------------------
# Native run
# --------------------------------------------------------------------------------------------


def run_native(cmd: list[str], env: dict[str, str]) -> int:
    state = native_vcan_state()
    if state == "down":
        log(f"warning: {VCAN_CHANNEL} exists but is down (sudo ip link set up {VCAN_CHANNEL})")
    log(f"native {VCAN_CHANNEL} found; running: {shlex.join(cmd)}")
    try:
        return subprocess.run(cmd, cwd=REPO_ROOT, env=env, check=False).returncode
    except FileNotFoundError as exc:
        log(f"cannot run {cmd[0]!r}: {exc}")
        return 127


# --------------------------------------------------------------------------------------------
# UML run
# --------------------------------------------------------------------------------------------

INIT_TEMPLATE_FILE = Path(__file__).with_name("uml_init.sh")
"""The guest's init script; ``@NAME@`` placeholders are filled in by :func:`write_init_script`."""


def write_init_script(
    workdir: Path,
    cmd: list[str],
    env: dict[str, str],
    inner_timeout: int | None,
    modules_root: Path = UML_MODULES_ROOT,
) -> Path:
    timeout_prefix = ""
    if inner_timeout is not None and shutil.which("timeout"):
        # Lets the guest record output and status before the host-side timeout fires.
        timeout_prefix = f"timeout -k 10 {inner_timeout} "
    values = {
        "WORKDIR": shlex.quote(str(workdir)),
        "MODULES": " ".join(CAN_MODULES),
        "MODROOT": shlex.quote(str(modules_root)),
        "CHANNEL": VCAN_CHANNEL,
        "CWD": shlex.quote(str(REPO_ROOT)),
        "TIMEOUT_PREFIX": timeout_prefix,
        "ENV": " ".join(shlex.quote(f"{k}={v}") for k, v in sorted(env.items())),
        "CMD": shlex.join(cmd),
    }
    script = re.sub(r"@([A-Z_]+)@", lambda m: values[m.group(1)], INIT_TEMPLATE_FILE.read_text())
    init = workdir / "init.sh"
    init.write_text(script)
    init.chmod(0o700)
    return init


def uml_memory_tmpdir(mem_mib: int, fallback: Path) -> str:
    """Where linux.uml creates its (sparse, unlinked) guest-RAM file: /dev/shm if big enough."""
    try:
        st = os.statvfs("/dev/shm")
        if st.f_bavail * st.f_frsize >= mem_mib * 1024 * 1024:
            return "/dev/shm"
    except OSError:
        pass
    return str(fallback)


def kill_group(proc: subprocess.Popen[bytes]) -> None:
    """Terminate the UML process group we started (UML runs guest processes as host children)."""

    def signal_group(sig: signal.Signals) -> bool:
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            return False
        return True

    if proc.poll() is None and signal_group(signal.SIGTERM):
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=5.0)
    # Also reaps any helper process the UML kernel process left behind in its group.
    signal_group(signal.SIGKILL)
    try:
        proc.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        log(f"warning: linux.uml (pid {proc.pid}) did not exit after SIGKILL")


class _Tail:
    """Copy bytes appended to a file to our stdout (hostfs writes through to the host file)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.pos = 0

    def pump(self) -> None:
        try:
            with self.path.open("rb") as fh:
                fh.seek(self.pos)
                data = fh.read()
        except FileNotFoundError:
            return
        if data:
            self.pos += len(data)
            sys.stdout.buffer.write(data)
            sys.stdout.buffer.flush()


def print_file_tail(path: Path, lines: int = 40) -> None:
    try:
        text = path.read_text(errors="replace").splitlines()
    except FileNotFoundError:
        log(f"({path.name} missing)")
        return
    for line in text[-lines:]:
        print(f"  | {line}", file=sys.stderr)


def run_uml(
    cmd: list[str],
    env: dict[str, str],
    timeout: float,
    mem_mib: int,
    keep: bool,
    kernel: tuple[str, Path] | None = None,
) -> int:
    """Boot UML (``kernel``: its binary and module root; default the distribution's) to run
    ``cmd`` beside a real vcan0; the command's exit status, or this script's own codes."""
    uml, modules_root = kernel or (find_uml_binary(), UML_MODULES_ROOT)
    if uml is None:
        log("linux.uml not found")
        return 1
    base = Path(tempfile.gettempdir())
    if str(base.resolve()).startswith(("/dev/shm", "/proc", "/sys", "/dev")):
        base = Path("/tmp")  # those are remounted inside the guest; /tmp is the host's /tmp
    workdir = Path(tempfile.mkdtemp(prefix="vcan-uml-", dir=base))
    # The guest-side timeout fires first so the guest can still record output and status.
    reserve = min(timeout / 2, max(15.0, timeout * 0.05))
    inner_timeout = max(int(timeout - reserve), 1)
    init = write_init_script(workdir, cmd, env, inner_timeout, modules_root)
    boot_log = workdir / "boot.log"
    uml_cmd = [
        uml,
        f"mem={mem_mib}M",
        "rootfstype=hostfs",
        "rootflags=/",
        "rw",
        f"init={init}",
        "con=null",
        "con0=fd:0,fd:1",
        # UML keeps its pid/mconsole files under uml_dir (default ~/.uml; without HOME it crashes).
        f"uml_dir={workdir}",
    ]
    uml_env = dict(os.environ)
    uml_env["HOME"] = os.environ.get("HOME") or str(workdir)
    uml_env["TMPDIR"] = uml_memory_tmpdir(mem_mib, workdir)
    log(f"booting user-mode Linux ({uml}, mem={mem_mib}M) to get a real {VCAN_CHANNEL}")
    log(f"guest runs: {shlex.join(cmd)}  (cwd {REPO_ROOT}, work dir {workdir})")
    tail = _Tail(workdir / "output.log")
    start = time.monotonic()
    ready_at: float | None = None
    timed_out = False
    interrupted = False
    with boot_log.open("wb") as boot_fh:
        proc = subprocess.Popen(
            uml_cmd,
            stdin=subprocess.DEVNULL,
            stdout=boot_fh,
            stderr=subprocess.STDOUT,
            env=uml_env,
            cwd=workdir,
            start_new_session=True,  # own process group: killable as a whole
        )
        previous_term = signal.getsignal(signal.SIGTERM)

        def on_term(signum: int, frame: object) -> None:
            raise KeyboardInterrupt

        signal.signal(signal.SIGTERM, on_term)
        try:
            while proc.poll() is None:
                if ready_at is None and (workdir / "ready").exists():
                    ready_at = time.monotonic()
                    log(f"guest ready ({VCAN_CHANNEL} up) after {ready_at - start:.1f} s")
                tail.pump()
                if time.monotonic() - start > timeout:
                    timed_out = True
                    break
                time.sleep(0.2)
        except KeyboardInterrupt:
            interrupted = True
        finally:
            kill_group(proc)
            signal.signal(signal.SIGTERM, previous_term)
    tail.pump()
    if interrupted:
        log("interrupted; stopped user-mode Linux")
        if not keep:
            shutil.rmtree(workdir, ignore_errors=True)
        return 130
    elapsed = time.monotonic() - start
    rc_file = workdir / "rc"
    failed_setup = workdir / "setup_failed"
    result: int
    if failed_setup.exists():
        log(f"guest could not set up {VCAN_CHANNEL}: {failed_setup.read_text().strip()}")
        print_file_tail(workdir / "setup.log")
        print_file_tail(boot_log, 15)
        result = 1
    elif rc_file.exists():
        result = int(rc_file.read_text().strip() or "1")
        log(f"guest command exited with {result}; boot + run took {elapsed:.1f} s")
        if result == EXIT_TIMEOUT and inner_timeout and elapsed >= inner_timeout:
            log(f"the command hit the guest-side timeout ({inner_timeout} s)")
    elif timed_out:
        log(f"timeout: user-mode Linux still running after {timeout:.0f} s; killed it")
        print_file_tail(workdir / "setup.log", 10)
        print_file_tail(boot_log, 15)
        result = EXIT_TIMEOUT
    else:
        log(
            f"user-mode Linux exited ({proc.returncode}) after {elapsed:.1f} s "
            "without recording the command's status; end of boot log:"
        )
        print_file_tail(workdir / "setup.log", 20)
        print_file_tail(boot_log, 30)
        result = 1
        with contextlib.suppress(OSError):
            if UML_FP_PANIC in boot_log.read_text(errors="replace"):
                result = EXIT_UML_CANNOT_BOOT
    if keep:
        log(f"kept work dir {workdir} (init.sh, boot.log, setup.log, output.log, rc)")
    else:
        shutil.rmtree(workdir, ignore_errors=True)
    return result


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
        help="run the command after `--` instead of pytest (e.g. --exec -- ip link show vcan0)",
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


def run_newer_uml(cmd: list[str], env: dict[str, str], args: argparse.Namespace) -> int:
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
    return run_uml(cmd, env, args.timeout, args.mem, args.keep, kernel)


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

    env = build_guest_env(python, args.env, in_uml=(mode == "uml"))
    if mode == "native":
        rc = run_native(cmd, env)
    else:
        rc = run_uml(cmd, env, args.timeout, args.mem, args.keep)

    if rc == EXIT_UML_CANNOT_BOOT:
        rc = run_newer_uml(cmd, env, args)
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
