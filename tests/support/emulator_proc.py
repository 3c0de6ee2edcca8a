"""The ``hil emulator`` as a child process, for the emulator process tests
(``tests/emulator/test_emulator_process.py``, ``tests/emulator/test_emulator_lockstep_candump.py``).

``TRANSPORTS`` are the CAN transports they run on (the ``can_spec`` fixture of
``tests/emulator/conftest.py``): ``socketcan`` on vcan0, marked ``vcan`` (run with
``scripts/vcan_pytest.py``, natively or inside user-mode Linux), and ``udp_multicast`` on an
isolated port, marked ``integration``. Under user-mode Linux (``HIL_IN_UML=1``) every timeout is
10x longer: it bounds a wait, it is not a timing claim.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import IO, Any

import pytest

from hal.joint_client import JointClient
from tests import support
from tests.support import REPO
from tests.support.joint import read_until
from tests.support.vcan import requires_vcan

IN_UML = os.environ.get("HIL_IN_UML", "") == "1"
SLOW = 10.0 if IN_UML else 1.0
START_TIMEOUT_S = 30.0 * SLOW
"""Python + numba + python-can start-up of the emulator process."""
RECV_TIMEOUT_S = 5.0 * SLOW
STOP_TIMEOUT_S = 60.0 * SLOW
"""Generous: a loaded 2-core host (load average > 10 seen) can take many seconds to run the
emulator's last periods and exit; only a hang should hit this."""
TEST_TIMEOUT_S = 600 if IN_UML else 120
"""The pytest-timeout of each emulator process test."""

TRANSPORTS = [
    pytest.param("socketcan", id="socketcan", marks=[pytest.mark.vcan, requires_vcan]),
    pytest.param("udp_multicast", id="udp_multicast", marks=[pytest.mark.integration]),
]


def _pump(stream: IO[str], sink: queue.Queue[str], lines: list[str]) -> None:
    for line in iter(stream.readline, ""):
        line = line.rstrip("\n")
        lines.append(line)
        sink.put(line)


class Proc:
    """A child process whose stdout/stderr lines are collected by reader threads."""

    def __init__(self, argv: list[str]) -> None:
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
        env["PYTHONUNBUFFERED"] = "1"
        self.popen = subprocess.Popen(
            argv,
            cwd=REPO,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.out: list[str] = []
        self.err: list[str] = []
        self.out_q: queue.Queue[str] = queue.Queue()
        self.err_q: queue.Queue[str] = queue.Queue()
        self.readers = [
            threading.Thread(target=_pump, args=(s, q, ls), name=f"reader-{n}", daemon=True)
            for n, s, q, ls in (
                ("out", self.popen.stdout, self.out_q, self.out),
                ("err", self.popen.stderr, self.err_q, self.err),
            )
        ]
        for t in self.readers:
            t.start()

    @property
    def pid(self) -> int:
        return self.popen.pid

    def wait_line(self, q: queue.Queue[str], pred: Callable[[str], bool], timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                pytest.fail(f"no expected line within {timeout:g} s; stderr: {self.err[-20:]}")
            try:
                line = q.get(timeout=min(remaining, 0.2))
            except queue.Empty:
                if self.popen.poll() is not None and q.empty():
                    time.sleep(0.2)  # let the readers drain the pipes
                    if q.empty():
                        pytest.fail(
                            f"process exited ({self.popen.returncode}) before the expected "
                            f"line; stdout: {self.out[-20:]}; stderr: {self.err[-20:]}"
                        )
                continue
            if pred(line):
                return line

    def signal(self, sig: int) -> int:
        """Send ``sig`` and wait for the exit status."""
        self.popen.send_signal(sig)
        return self.popen.wait(timeout=STOP_TIMEOUT_S)

    def close(self) -> None:
        """Terminate (then kill) if still running, wait, join the readers. Idempotent."""
        p = self.popen
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=STOP_TIMEOUT_S)
        for t in self.readers:
            t.join(timeout=STOP_TIMEOUT_S)
        for s in (p.stdout, p.stderr):
            if s is not None:
                s.close()


@contextlib.contextmanager
def emulator(spec: str, *extra: str) -> Iterator[Proc]:
    """``hil emulator --can SPEC --json ...`` as a child process, ready to serve."""
    argv = [sys.executable, "-m", "rt_controller.cli", "emulator", "--can", spec, "--json"]
    proc = Proc([*argv, *extra])
    try:
        line = proc.wait_line(proc.err_q, lambda s: "serving the arm on" in s, START_TIMEOUT_S)
        print(f"\n{line}")
        yield proc
    finally:
        proc.close()


def stop_emulator(proc: Proc, sig: int = signal.SIGTERM) -> dict[str, Any]:
    """Signal the emulator, check it exits 0 without a traceback; its JSON summary."""
    rc = proc.signal(sig)
    proc.close()
    assert rc == 0, f"exit status {rc}; stderr: {proc.err}"
    assert not any("Traceback" in line for line in proc.err), proc.err
    summary = json.loads(proc.out[-1])
    return summary


def wait_until(
    cond: Callable[[], bool],
    what: str,
    timeout: float = RECV_TIMEOUT_S,
    reading: JointClient | None = None,
) -> float:
    """Poll ``cond`` every millisecond, reading the bus of the client ``reading`` meanwhile (a
    client has no thread of its own; the one ``streaming`` of test_emulator_process.py runs
    reads it while it runs); the monotonic time at which ``cond`` became true."""
    if reading is not None:
        ok = read_until(reading, cond, timeout)
    else:
        ok = support.wait_until(cond, timeout, poll_s=0.001)
    if not ok:
        pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
    return time.monotonic()
