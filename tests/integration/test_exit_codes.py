"""Exit codes tell the truth: a run that lost log records or tripped the DSP's watchdog exits
non-zero and says why in one line, from ``hil controller`` up through ``hil up``.

The faults are injected into the real daemons: the log is written to a tiny tmpfs that fills up,
and the controller is frozen (SIGSTOP) for longer than the DSP's watchdog allows.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from hal.zenoh_session import free_loopback_port
from rt_controller.runtime.counters import run_problems
from tests.support import start_hil_up
from tests.support.proc import processes_mentioning, running_controller

REPO = Path(__file__).resolve().parents[2]
WAIT_S = 180.0


def test_a_clean_summary_has_no_problems():
    clean = {"watchdog_trips": 0, "recorder": {"dropped": 0, "encode_errors": 0, "pending": 0}}
    assert run_problems(clean) == []


def test_each_problem_is_named():
    bad = {"watchdog_trips": 2, "recorder": {"dropped": 5, "encode_errors": 1, "pending": 3}}
    assert run_problems(bad) == [
        "8 log record(s) lost",
        "1 log record(s) could not be encoded",
        "2 DSP watchdog trip(s)",
    ]


def _finish(proc: subprocess.Popen, ep: str) -> tuple[int, dict, str]:
    try:
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    deadline = time.monotonic() + 30
    while processes_mentioning(ep) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not processes_mentioning(ep)
    lines = [ln for ln in out.splitlines() if ln.startswith("{")]
    return proc.returncode, json.loads(lines[-1]) if lines else {}, err


@pytest.mark.integration
def test_disk_full_for_the_log_fails_the_run(tiny_tmpfs):
    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    proc = start_hil_up(ep, tiny_tmpfs / "run.mcap", "--json", "--lockstep", "--duration", "10")
    rc, summary, err = _finish(proc, ep)
    assert rc == 1, err
    assert summary["recorder"]["dropped"] > 0
    last = err.strip().splitlines()[-1]
    assert last.startswith("hil up: run not clean:") and "log record(s) lost" in last, err


@pytest.mark.integration
def test_a_watchdog_trip_fails_the_run(tmp_path):
    """Freeze the controller for 0.5 s (the watchdog allows three 20 ms periods), once the arm
    has settled (the torque the DSP holds until the trip is then small).

    The velocity limits are raised out of the way: this test is about the watchdog, and a
    host busy enough to stall the loop in the IOC transient once put the drive in a
    velocity-limit fault first (no watchdog runs in FAULT; CI saw it)."""
    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    log = tmp_path / "run.mcap"
    rig = tmp_path / "rig.toml"
    rig.write_text("[dsp]\ndq_max = [80.0, 80.0]\n")
    proc = start_hil_up(ep, log, "--json", "--duration", "10", "--config", str(rig))
    pid = running_controller(ep, log, timeout_s=WAIT_S)  # running for 2 s: the transient is over
    os.kill(pid, signal.SIGSTOP)
    time.sleep(0.5)  # fault injection, not a timing assertion: any freeze > 60 ms trips it
    os.kill(pid, signal.SIGCONT)
    rc, summary, err = _finish(proc, ep)
    assert summary["watchdog_trips"] >= 1, err
    assert rc == 1 and "DSP watchdog trip(s)" in err.strip().splitlines()[-1], err


@pytest.mark.integration
def test_a_lockstep_period_the_dsp_skipped_fails_the_run(tmp_path):
    """Freeze the lockstep controller for 1.2 s mid-run: the DSP advances the period it waits
    on with the held torque after its 0.5 s reply timeout (more may follow), and the run, no
    longer the deterministic one, says so (it said nothing when no watchdog trip followed)."""
    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    log = tmp_path / "run.mcap"
    proc = start_hil_up(ep, log, "--json", "--lockstep", "--duration", "120")
    pid = running_controller(ep, log, timeout_s=WAIT_S)
    os.kill(pid, signal.SIGSTOP)
    time.sleep(1.2)  # fault injection: any freeze past the DSP's 0.5 s skips a period
    os.kill(pid, signal.SIGCONT)
    rc, summary, err = _finish(proc, ep)
    assert summary["dsp"]["skipped_periods"] >= 1, err
    assert rc == 1, err
    assert any("lockstep period(s) with the held torque" in p for p in summary["problems"]), err
