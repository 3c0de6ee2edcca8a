"""Finding processes a test started: by a token in their command line (e.g. a zenoh endpoint),
as children of a process, and whether one still runs."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

WAIT_S = 120.0
"""Generous bound for a step that normally takes seconds: a hang fails, slowness does not."""


def wait_for(
    cond: Callable[[], bool], what: str, proc: subprocess.Popen | None = None, poll_s: float = 0.05
) -> None:
    """Poll ``cond`` until true; fail the test when ``proc`` (``hil up``) exits first, with its
    output, or after :data:`WAIT_S`."""
    deadline = time.monotonic() + WAIT_S
    while not cond():
        if proc is not None and proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"hil up exited ({proc.returncode}) before {what}:\n{out}\n{err}")
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(poll_s)


def processes_mentioning(token: str) -> list[str]:
    """Live processes (not zombies) whose command line contains ``token``."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (proc / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if token in cmdline and state != "Z":
            found.append(f"{proc.name}: {cmdline.strip()}")
    return found


def running_controller(token: str, log: Path, cycles: int = 100, timeout_s: float = 180.0) -> int:
    """The pid of the rig's controller whose command line holds ``token`` (its zenoh
    endpoint), once its ``log`` holds ``cycles`` cycles (or ``timeout_s`` passed)."""
    import time

    from tests.support import cycles_logged

    deadline = time.monotonic() + timeout_s
    controller: list[str] = []
    while not controller and time.monotonic() < deadline:
        controller = [p for p in processes_mentioning(token) if " controller " in p]
        time.sleep(0.05)
    assert controller, "the controller never started"
    while time.monotonic() < deadline and cycles_logged(log) < cycles:
        time.sleep(0.05)
    return int(controller[0].split(":")[0])


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (exists and is not a zombie)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def children_of(pid: int) -> list[int]:
    """The child processes of ``pid`` (every thread's), zombies included."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*/children"):
        try:
            out += [int(p) for p in task.read_text().split()]
        except OSError:
            continue
    return out


def child_running(parent: int, command: str) -> int | None:
    """The pid of ``parent``'s child whose command line runs ``hil COMMAND`` (``command`` among
    its first four arguments, e.g. ``python -m rt_controller.cli vision``); None: no such child."""
    for pid in children_of(parent):
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if command.encode() in argv[:4]:
            return pid
    return None


@contextlib.contextmanager
def reaped(proc: subprocess.Popen) -> Iterator[subprocess.Popen]:
    """``proc`` (started in a session of its own), killed with its whole group and reaped if it
    still runs when the block ends (a test that failed or timed out leaves nothing behind)."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()


def stop_all(procs: list[subprocess.Popen], timeout_s: float = 20.0) -> None:
    """SIGTERM to each of ``procs`` still running (last started first), then wait for each;
    one that outlives ``timeout_s`` is killed. Every one is reaped."""
    for proc in reversed(procs):
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def folder_of_a_killed_run(prefix: str, where: Path | None = None) -> Path:
    """A private folder (:mod:`rt_controller.rig.scratch`) as a killed run leaves it: made by
    a process that then ended without removing it (``os._exit``, as SIGKILL would)."""
    code = (
        "import os, sys; from pathlib import Path; "
        "from rt_controller.rig.scratch import make_private_folder; "
        "w = sys.argv[2] or None; "
        "print(make_private_folder(sys.argv[1], Path(w) if w else None), flush=True); os._exit(9)"
    )
    args = [sys.executable, "-c", code, prefix, str(where or "")]
    done = subprocess.run(args, capture_output=True, text=True, timeout=WAIT_S, check=False)
    assert done.returncode == 9, done.stderr
    folder = Path(done.stdout.strip())
    assert folder.is_dir()
    return folder
