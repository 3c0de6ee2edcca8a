"""``hil experiment`` told to stop three times in a row (an impatient Ctrl-C Ctrl-C Ctrl-C) on
real rigs: status 130, the partial results written, no traceback, no process left behind.

No wall-clock assertion: the waits poll.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from tests.support.proc import WAIT_S, processes_mentioning, reaped, wait_for

pytestmark = pytest.mark.integration


def test_three_quick_ctrl_c_stop_the_experiment_without_a_traceback(tmp_path):
    """The third SIGINT came while the Dask cluster closed: a distributed ERROR and a
    CancelledError traceback on stderr after the 'interrupted' line."""
    out = tmp_path / "exp"
    argv = [sys.executable, "-m", "rt_controller.cli", "experiment", "fig3", "--duration", "3",
            "--jobs", "1", "--out", str(out)]  # fmt: skip
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    with reaped(proc):
        wait_for(lambda: (out / "logs" / "rhc-T0.02.mcap").exists(), "the first run", proc)
        for _ in range(3):
            os.killpg(proc.pid, signal.SIGINT)  # as the terminal sends Ctrl-C: to the group
            time.sleep(0.1)  # a second signal in a row would coalesce with the first
        _, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "Traceback" not in err and "ERROR" not in err, err
    assert f"hil experiment: interrupted by SIGINT: partial results in {out}" in err, err
    res = json.loads((out / "results.json").read_text())
    assert {r["status"] for r in res["runs"]} <= {"ok", "pending"}, res["runs"]
    assert processes_mentioning(str(out)) == []
