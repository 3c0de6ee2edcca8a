"""``hil emulator --lockstep`` stopped during its start-up on a cold kernel cache: no start-up
step begins a compile after the stop (the camera's and the physics' compiles take seconds each
on a loaded host; both ran whatever the stop said, the stop took up to 8 s)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from hal.bus import isolated_spec
from tests.support import REPO, free_endpoint, hil_command
from tests.support.proc import WAIT_S

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _catches_sigterm(pid: int) -> bool:
    """Whether ``pid`` has a handler for SIGTERM (its stop handlers are in place)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    return False


def test_a_stop_during_start_up_compiles_nothing_more(tmp_path):
    cache = tmp_path / "numba"  # cold: every kernel the start-up calls is compiled
    args = ["emulator", "--lockstep", "--can", isolated_spec("udp_multicast")]
    proc = subprocess.Popen(
        [*hil_command(), *args, "--zenoh-endpoint", free_endpoint()],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        cwd=REPO,
        env={**os.environ, "NUMBA_CACHE_DIR": str(cache)},
    )
    try:
        deadline = time.monotonic() + WAIT_S
        while not _catches_sigterm(proc.pid):
            assert proc.poll() is None and time.monotonic() < deadline, "no stop handler"
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGTERM)
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, err
    assert "simulated in" in out, out  # its summary, as after any stop
    compiled = sorted(p.name for p in cache.rglob("*.nbi"))
    steps = {name.split(".")[0] for name in compiled}  # camera_exposure (renderer), arm (physics)
    # the stop came right after the handlers were in place: at most a compile under way (on a
    # slow host) may finish, no later step starts one
    assert len(steps) <= 1, f"compiled after the stop: {compiled}\n{err}"
