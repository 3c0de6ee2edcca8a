"""What the host offers for the vcan tests (a native ``vcan0``, user-mode Linux, apt-get) and
the command's environment, natively or inside the UML guest. Part of ``vcan_pytest.py``."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
VCAN_CHANNEL = "vcan0"
UML_MODULES_ROOT = Path("/usr/lib/uml/modules")
# Loaded in this order (dependencies first); located by file name under the module tree.
# can-bcm: python-can sends periodic frames (canopen's heartbeat producer) by the kernel's
# broadcast manager.
CAN_MODULES = ("can", "can-raw", "can-bcm", "can-dev", "vcan")
APT_PACKAGES = ("user-mode-linux", "kmod", "can-utils")
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
