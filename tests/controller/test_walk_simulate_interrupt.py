"""``hil simulate`` stopped by Ctrl-C or SIGTERM: exit 130 (143) with one line saying no result
was printed, not a silent exit after its progress line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from tests.support.proc import WAIT_S


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_mid_simulate_says_so_in_one_line(sig):
    cmd = [sys.executable, "-m", "rt_controller.cli", "simulate", "--duration", "100000"]
    env = {**os.environ, "HIL_PROGRESS_AFTER_S": "0"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stderr is not None
        while "running" not in (line := proc.stderr.readline()):
            assert line, "hil simulate exited before its run"
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=WAIT_S)
        assert proc.returncode == 128 + sig and out == ""
        assert err.strip().splitlines() == [f"hil simulate: interrupted by {sig.name}; no result"]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
