"""The controller's final ``/diagnostics`` record says how its run ended (``planned_ticks``,
``end_reason``), so ``hil info`` of the log alone tells a run stopped after 30 of 30000 ticks
from a whole one, with the figures.

The real ``hil up`` runs (realtime); its controller is stopped by a SIGTERM the rig did not send
once the log holds its first ticks. No wall-clock assertion: the waits poll.
"""

from __future__ import annotations

import json
import os
import signal

import pytest

from hal.zenoh_session import free_loopback_port
from tests.support import cycles_logged, run_hil, start_hil_up
from tests.support.proc import WAIT_S, child_running, reaped, wait_for

pytestmark = pytest.mark.integration

TICKS_FIRST = 30


def test_info_of_a_run_stopped_early_says_after_how_many_of_the_planned_ticks(tmp_path):
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    proc = start_hil_up(ep, log, "--duration", "600", "--json")
    with reaped(proc):
        wait_for(lambda: cycles_logged(log) >= TICKS_FIRST, "the first ticks", proc)
        controller = child_running(proc.pid, "controller")
        assert controller is not None, "no controller child"
        os.kill(controller, signal.SIGTERM)
        proc.communicate(timeout=WAIT_S)
    out = run_hil(["info", str(log), "--json"], timeout_s=WAIT_S)
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    planned, ran = info["planned_ticks"], info["ticks_run"]
    assert info["end_reason"] == "stopped" and planned == 600 * float(info["run"]["rate_hz"])
    assert TICKS_FIRST <= ran < planned
    assert info["stop_signal"] == "SIGTERM"
    assert f"the run ended after {ran} of {planned} ticks: stopped by SIGTERM" in info["warnings"]
