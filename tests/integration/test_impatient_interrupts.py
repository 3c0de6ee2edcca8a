"""``hil up`` told to stop twice (an impatient Ctrl-C Ctrl-C) still prints the run's summary,
and the summary names the signal the user sent, not the SIGTERM the rig passed on, with the
DSP's account of the stop as after a full run.

The real ``hil up --json`` runs (realtime). No wall-clock assertion: the waits poll.
"""

from __future__ import annotations

import json
import os
import signal
import time

import pytest

from hal.zenoh_session import free_loopback_port
from tests.support import cycles_logged, start_hil_up
from tests.support.proc import WAIT_S, child_running, reaped, wait_for

pytestmark = pytest.mark.integration


def _stopped_by(tmp_path, *signals: signal.Signals) -> tuple[int, str, str]:
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    with reaped(start_hil_up(ep, log, "--duration", "600", "--json")) as proc:
        wait_for(lambda: cycles_logged(log) >= 30, "the first ticks", proc)
        for sig in signals:
            os.kill(proc.pid, sig)
            time.sleep(0.1)  # a second signal in a row would coalesce with the first
        out, err = proc.communicate(timeout=WAIT_S)
    return proc.returncode, out, err


def test_two_quick_ctrl_c_still_print_the_summary(tmp_path):
    rc, out, err = _stopped_by(tmp_path, signal.SIGINT, signal.SIGINT)
    assert rc == 128 + signal.SIGINT, err
    assert "Traceback" not in err, err
    lines = [line for line in out.splitlines() if line.startswith("{")]
    assert len(lines) == 1, f"no JSON summary (exit {rc}):\n{out}\n{err}"
    summary = json.loads(lines[0])
    assert summary["end_reason"] == "stopped" and summary["ticks"] >= 30, summary
    assert summary["stop_signal"] == "SIGINT", summary


def test_a_hangup_is_named_in_the_summary(tmp_path):
    rc, out, err = _stopped_by(tmp_path, signal.SIGHUP)
    assert rc == 128 + signal.SIGHUP, err
    (line,) = [line for line in out.splitlines() if line.startswith("{")]
    summary = json.loads(line)
    assert (summary["end_reason"], summary["stop_signal"]) == ("stopped", "SIGHUP"), summary
    stopped = [w for w in summary["warnings"] if "stopped by" in w]  # before its 600 s
    assert len(stopped) == 1 and stopped[0].endswith("stopped by SIGHUP"), summary
    dsp = summary["dsp"]  # the DSP's own account: torque off in order, no trip
    assert dsp is not None and dsp["reported"] is True and dsp["watchdog_trips"] == 0, summary


def test_a_hangup_while_the_controller_starts_is_not_called_a_death(tmp_path):
    """The controller ended by the rig's own SIGTERM in its start-up: the summary says the
    user's signal stopped the run, not that the controller was killed."""
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    with reaped(start_hil_up(ep, log, "--duration", "600", "--json")) as proc:
        wait_for(lambda: child_running(proc.pid, "controller") is not None, "the controller", proc)
        os.kill(proc.pid, signal.SIGHUP)
        out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 128 + signal.SIGHUP, err
    (line,) = [line for line in out.splitlines() if line.startswith("{")]
    summary = json.loads(line)
    if summary["exit_codes"]["controller"] != -signal.SIGTERM:
        pytest.skip("the signal did not land in the controller's start-up")
    assert "interrupted by SIGHUP" in summary["end_reason"], summary
    for said in (summary["end_reason"], *summary["problems"]):
        assert "killed by SIGTERM" not in said, summary
