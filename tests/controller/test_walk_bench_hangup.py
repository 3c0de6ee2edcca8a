"""``hil bench`` when its terminal goes away (SIGHUP): it unwinds as on Ctrl-C, says so in one
line, exits 129 and removes its temporary folder (the runs' MCAP logs)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

from tests.support.proc import WAIT_S, wait_for


def test_sighup_mid_bench_removes_the_temporary_folder_and_says_so(tmp_path):
    cmd = [sys.executable, "-m", "rt_controller.cli", "bench", "loop", "--rates", "50"]
    cmd += ["--duration", "60", "--host-probe", "0", "--lockstep-duration", "0"]
    env = {**os.environ, "TMPDIR": str(tmp_path), "HIL_PROGRESS_AFTER_S": "0"}
    proc = subprocess.Popen(  # SIGHUP as a terminal's, even under a nohup'd test run
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL),
    )
    try:
        wait_for(lambda: any(tmp_path.glob("hil-bench-*/loop-50.mcap")), "the run's log", proc)
        proc.send_signal(signal.SIGHUP)
        out, err = proc.communicate(timeout=WAIT_S)
        assert proc.returncode == 128 + signal.SIGHUP and out == ""
        assert err.strip().splitlines()[-1] == "hil bench loop: interrupted by SIGHUP; no figures"
        assert not [p.name for p in tmp_path.iterdir() if p.name.startswith("hil-bench-")]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
