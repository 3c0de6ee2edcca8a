"""Shared fixtures. The autouse ``no_leaks`` fixture fails any test that leaves a CAN bus, a
zenoh session, a thread or a child process behind."""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from hal.config import RigConfig, load_config
from tests.support.proc import alive, children_of

LEAK_GRACE_S = 3.0


def _session_rig_key() -> None:
    """One rig key for the whole test session (``$HIL_KEY_FILE``): processes a test starts by
    hand (``hil emulator``, ``hil vision``, ``hil controller``) and the clients it opens in this
    process share it; ``hil up`` / ``Rig`` still make a fresh key per run."""
    import atexit
    import shutil

    from hal.secoc import KEY_ENV, write_key_file
    from rt_controller.rig.scratch import make_private_folder

    if not os.environ.get(KEY_ENV):  # (a killed session's folder goes at the next one's start)
        folder = make_private_folder("hil-test-key-")
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        os.environ[KEY_ENV] = str(write_key_file(folder / "rig.key"))


_session_rig_key()


def _sigint_delivered() -> None:
    """A suite started as a shell's background job (``pytest ... &``) inherits SIGINT ignored,
    and so would every process a test starts: a test that sends Ctrl-C to a child would wait
    for a signal the child ignores. The session gives SIGINT back its default handler."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


_sigint_delivered()


def _child_pids() -> set[int]:
    return {p for p in children_of(os.getpid()) if alive(p)}


def _open_buses() -> list[str]:
    can = sys.modules.get("can")
    if can is None:
        return []
    gc.collect()
    found = []
    for obj in gc.get_objects():
        try:
            if isinstance(obj, can.BusABC) and not getattr(obj, "_is_shutdown", True):
                found.append(f"{type(obj).__name__}({getattr(obj, 'channel_info', '?')})")
        except (ReferenceError, RuntimeError):  # canopen's unassigned-network placeholder raises
            continue
    return found


PROCESS_POOLS = ("Dask-Offload",)
"""Threads of library pools that start on first use and live as long as the process (Dask's
offload pool, used by an in-process cluster such as ``hil experiment``'s): not leaks."""


def _foreign(t: threading.Thread) -> bool:
    """A native thread (the foxglove SDK's, zenoh's) that called into Python once: ``threading``
    registers it as a dummy for good and cannot join it, so it is not ours to leak."""
    return isinstance(t, threading._DummyThread)


def _leaks(threads_before: set[threading.Thread], children_before: set[int]) -> list[str]:
    from hal.resources import open_resources

    out = [f"open resource: {label}" for label in open_resources()]
    out += [f"open python-can bus: {b}" for b in _open_buses()]
    out += [
        f"thread still running: {t.name}"
        for t in threading.enumerate()
        if t not in threads_before
        and t.is_alive()
        and not t.name.startswith(PROCESS_POOLS)
        and not _foreign(t)
    ]
    out += [f"child process still running: pid {p}" for p in _child_pids() - children_before]
    return out


@pytest.fixture(autouse=True)
def no_leaks():
    """Fail the test if it leaked a bus, session, thread or process (after a short grace)."""
    threads_before = set(threading.enumerate())
    children_before = _child_pids()
    yield
    deadline = time.monotonic() + LEAK_GRACE_S
    leaks = _leaks(threads_before, children_before)
    while leaks and time.monotonic() < deadline:
        time.sleep(0.05)
        leaks = _leaks(threads_before, children_before)
    if leaks:
        pytest.fail("test leaked: " + "; ".join(leaks), pytrace=False)


@pytest.fixture
def endpoint() -> str:
    """A zenoh endpoint on a free loopback port."""
    from tests.support import free_endpoint

    return free_endpoint()


@pytest.fixture
def cfg() -> RigConfig:
    """The embedded default configuration (the paper's numbers)."""
    return load_config()


@pytest.fixture
def tiny_tmpfs(tmp_path):
    """A 192 KiB tmpfs: a 10 s run's log does not fit."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=192k", "tmpfs", str(mnt)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip()}): disk-full test skipped")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)
