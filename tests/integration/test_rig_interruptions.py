"""``hil up`` says what happened however its run is cut: by a signal to the controller that the
rig did not send, by a Ctrl-C while it handles a death or while the controller still starts,
and by the wall-clock budget running out on a frozen controller. Each prints one summary
(JSON here) with the run's ticks, log and exit codes, and an exit status that is not 0.

The real ``hil up --json`` runs (realtime), as a user starts it. No wall-clock assertion: the
waits poll, and where a signal can land in one of two windows, both are accepted as long as
the summary says what happened.
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
from tests.support import cycles_logged, start_hil_up
from tests.support.proc import WAIT_S, child_running, reaped, wait_for

pytestmark = pytest.mark.integration

TICKS_FIRST = 30


def _summary(out: str, err: str, rc: int) -> dict:
    lines = [line for line in out.splitlines() if line.startswith("{")]
    assert len(lines) == 1, f"no JSON summary (exit {rc}):\n{out}\n{err}"
    assert "Traceback" not in err, err
    return json.loads(lines[0])


def _rig(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen, Path]:
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    return start_hil_up(ep, log, "--duration", "600", "--json", *extra), log


def _ticking_controller(proc: subprocess.Popen, log: Path) -> int:
    wait_for(lambda: cycles_logged(log) >= TICKS_FIRST, "the first ticks", proc)
    pid = child_running(proc.pid, "controller")
    assert pid is not None, "no controller child"
    return pid


def test_a_controller_stopped_by_a_signal_the_rig_did_not_send_fails_the_run(tmp_path):
    """A SIGTERM from elsewhere (``kill``, a shutdown) ends the controller's run in order, with
    its summary; but it is not the run that was asked for: not clean, and said."""
    proc, log = _rig(tmp_path)
    with reaped(proc):
        os.kill(_ticking_controller(proc, log), signal.SIGTERM)
        out, err = proc.communicate(timeout=WAIT_S)
    summary = _summary(out, err, proc.returncode)
    assert proc.returncode == 1, err
    assert summary["end_reason"] == "stopped", summary
    assert summary["ticks"] < summary["planned_ticks"] == 600 * summary["rate_hz"]
    said = "the controller was stopped by a signal the rig did not send, after "
    assert any(p.startswith(said) for p in summary["problems"]), summary["problems"]


def test_a_ctrl_c_right_after_a_death_still_says_the_death(tmp_path):
    """Ctrl-C while ``hil up`` waits for the DSP's trip after the controller died (or just
    before it noticed the death): the summary names the death all the same. In lockstep the
    wait is long (the DSP counts a missing period after 0.5 s of wall time)."""
    proc, log = _rig(tmp_path, "--lockstep")
    with reaped(proc):
        os.kill(_ticking_controller(proc, log), signal.SIGKILL)
        time.sleep(0.5)
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=WAIT_S)
    summary = _summary(out, err, proc.returncode)
    assert proc.returncode in (1, 128 + signal.SIGINT), err  # 1: the signal came too late
    assert "controller killed by SIGKILL" in summary["end_reason"], summary
    assert summary["log"] == str(log) and summary["log_contents"]["cycles"] >= TICKS_FIRST
    assert summary["exit_codes"]["controller"] == -signal.SIGKILL, summary


def test_a_ctrl_c_while_the_controller_starts_has_a_summary(tmp_path):
    """Stopped before the first tick: still one summary, with no tick, the planned ticks and
    why it ended (the controller stopped in start-up, or ended by the signal itself)."""
    proc, _ = _rig(tmp_path)
    with reaped(proc):
        wait_for(lambda: child_running(proc.pid, "controller") is not None, "the controller", proc)
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=WAIT_S)
    summary = _summary(out, err, proc.returncode)
    assert proc.returncode == 128 + signal.SIGINT, err
    assert summary["planned_ticks"] == 600 * summary["rate_hz"], summary
    ended = summary["end_reason"]
    if summary.get("ticks"):  # the start-up was quicker than the signal: a run stopped
        assert ended == "stopped", summary
    else:  # stopped in start-up, ended by the signal itself, or not yet among the rig's children
        said = ("before its first tick", "before the controller started")
        assert ended == "stopped" or any(s in ended for s in said), summary
    assert "exit_codes" in summary, summary


def test_a_frozen_controller_is_called_hung_with_the_run_s_summary(tmp_path):
    """A controller frozen (SIGSTOP) until the wall-clock budget runs out: killed with its
    stacks, and the summary has the ticks, the log, the exit codes and the DSP's account, with
    the hang first among the problems."""
    proc, log = _rig(tmp_path, "--wall-timeout", "60")  # start-up fits in it
    with reaped(proc):
        os.kill(_ticking_controller(proc, log), signal.SIGSTOP)
        out, err = proc.communicate(timeout=WAIT_S)
    summary = _summary(out, err, proc.returncode)
    assert proc.returncode == 1, err
    problems = summary["problems"]
    assert problems[0].startswith("hung: controller still running after its wall-clock"), problems
    assert any(p.startswith("controller killed by SIGKILL when stopped") for p in problems)
    assert summary["exit_codes"]["controller"] == -signal.SIGKILL, summary
    assert summary["log"] == str(log) and summary["ticks"] >= TICKS_FIRST, summary
    assert summary["dsp"]["reported"] is True, summary
