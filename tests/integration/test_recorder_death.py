"""The controller's recorder process killed mid-run: a lockstep run ends at once ("log lost"),
since it exists for its log; it never runs on unlogged to its duration."""

from __future__ import annotations

import json
import os
import signal
import subprocess

import pytest

from hal.zenoh_session import free_loopback_port
from tests.support import cycles_logged, start_hil_up
from tests.support.proc import WAIT_S, child_running, children_of, reaped, wait_for

pytestmark = pytest.mark.integration

DURATION_S = "3000"
"""Simulated seconds: run on unlogged, the run would take many minutes of wall time."""


def test_a_lockstep_run_ends_when_its_recorder_dies(tmp_path):
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    proc = start_hil_up(ep, log, "--lockstep", "--duration", DURATION_S, "--json")
    with reaped(proc):
        wait_for(lambda: cycles_logged(log) >= 30, "the first ticks", proc)
        controller = child_running(proc.pid, "controller")
        assert controller is not None, "no controller child"
        recorders = children_of(controller)
        assert len(recorders) == 1, recorders  # the recorder is the controller's one child
        os.kill(recorders[0], signal.SIGKILL)
        try:
            out, err = proc.communicate(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the run went on for {WAIT_S} s without its recorder")
    summaries = [json.loads(ln) for ln in out.splitlines() if ln.startswith("{")]
    assert len(summaries) == 1, err
    summary = summaries[0]
    assert proc.returncode == 1, err
    assert summary["end_reason"].startswith("log lost: the recorder process"), summary
    assert summary["ticks"] < summary["planned_ticks"], summary
    assert "Traceback" not in err, err
