"""Ctrl-C (or SIGTERM) while ``hil param`` or ``hil monitor`` still waits for the rig's zenoh
hub (no rig yet) ends it in one line with the shell's status for that signal (128 + its
number), as a Ctrl-C while ``hil param`` waits for the answer does: not exit 2, which says the
arguments were wrong.

The stand-in "hub" is a plain loopback TCP listener: the tool's connection attempt proves it
is waiting (its signal handlers are in place) before the signal is sent. No wall-clock
assertion: the waits poll.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess

import pytest

from tests.support import REPO, hil_command
from tests.support.proc import WAIT_S, reaped

pytestmark = pytest.mark.integration


def _interrupted_while_waiting(args: list[str], sig: signal.Signals, tmp_path) -> tuple[int, str]:
    key = tmp_path / "rig.key"
    subprocess.run([*hil_command(), "keygen", str(key)], check=True, capture_output=True)
    with socket.socket() as lsn:
        lsn.bind(("127.0.0.1", 0))
        lsn.listen(8)
        lsn.settimeout(WAIT_S)
        endpoint = f"tcp/127.0.0.1:{lsn.getsockname()[1]}"
        cmd = [*hil_command(), *args, "--key-file", str(key), "--zenoh-endpoint", endpoint]
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            start_new_session=True, cwd=REPO,
        )  # fmt: skip
        with reaped(proc):
            conn, _ = lsn.accept()  # it tries the hub: it waits for it now
            conn.close()
            os.kill(proc.pid, sig)
            _out, err = proc.communicate(timeout=WAIT_S)
    return proc.returncode, err


@pytest.mark.parametrize(
    "args",
    [["param", "get"], ["param", "set", "gains.kp=0.2"], ["monitor", "--port", "0"]],
    ids=["param-get", "param-set", "monitor"],
)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_while_waiting_for_the_hub_is_an_interruption(args, sig, tmp_path):
    rc, err = _interrupted_while_waiting(args, sig, tmp_path)
    assert rc == 128 + sig, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"hil {args[0]}: interrupted by {sig.name}"), err
    assert "Traceback" not in err and "error" not in lines[0], err


def test_a_monitor_gives_up_on_a_missing_hub_within_its_duration(tmp_path):
    """``hil monitor --duration 1`` with no rig: the wait for the hub is bounded by the 1 s it
    was asked to run (not the default 10 s), with the one-line "no hub" error (exit 2)."""
    key = tmp_path / "rig.key"
    subprocess.run([*hil_command(), "keygen", str(key)], check=True, capture_output=True)
    with socket.socket() as lsn:  # a port nobody else takes meanwhile; it speaks no zenoh
        lsn.bind(("127.0.0.1", 0))
        lsn.listen(8)
        endpoint = f"tcp/127.0.0.1:{lsn.getsockname()[1]}"
        cmd = [*hil_command(), "monitor", "--port", "0", "--duration", "1"]
        cmd += ["--key-file", str(key), "--zenoh-endpoint", endpoint]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=WAIT_S, cwd=REPO)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"hil monitor: error: zenoh: no hub at {endpoint} after 1 s (start the emulator, "
        "`hil emulator`, or check --zenoh-endpoint)"
    ], done.stderr
