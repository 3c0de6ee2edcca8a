"""A frozen camera is named: ``hil up`` (realtime) with the vision process stopped (SIGSTOP, then
SIGCONT) for a while warns of the camera outage with its start and length, and a freeze over
``controller.outage_max_share`` of the run makes the run not clean.

The freeze is held for a wall-clock time (the fault), but nothing asserts on wall-clock
windows: the stale stretch only has to be longer than ``controller.outage_warn_periods`` and,
for the long freeze, its share past ``controller.outage_max_share`` (about 60 % against 25 %).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from hal.config import RigConfig
from hal.zenoh_session import free_loopback_port
from tests.support import cycles_logged, start_hil_up
from tests.support.proc import child_running, reaped

pytestmark = pytest.mark.integration

WAIT_S = 120.0
CTL = RigConfig().controller


def report_of(log: str) -> dict:
    """``hil report LOG --json``."""
    out = subprocess.run(
        [sys.executable, "-m", "rt_controller.cli", "report", log, "--json"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return json.loads(out)


def freeze_vision(tmp_path, duration_s: float, freeze_s: float) -> tuple[int, dict, str]:
    """A realtime ``hil up --json`` whose vision process is stopped for ``freeze_s`` once the
    controller has logged 50 ticks: exit status, summary, stderr."""
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    with reaped(start_hil_up(ep, log, "--duration", f"{duration_s:g}", "--json")) as proc:
        deadline = time.monotonic() + WAIT_S
        while cycles_logged(log) < 50:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no ticks"
            time.sleep(0.05)
        vision = child_running(proc.pid, "vision")
        assert vision is not None
        os.kill(vision, signal.SIGSTOP)
        try:
            time.sleep(freeze_s)  # the fault: the camera gives nothing for this long
        finally:
            os.kill(vision, signal.SIGCONT)
        out, err = proc.communicate(timeout=WAIT_S)
    (line,) = [x for x in out.splitlines() if x.startswith("{")]
    return proc.returncode, json.loads(line), err


def test_a_two_second_camera_freeze_is_a_named_warning(tmp_path):
    _, summary, err = freeze_vision(tmp_path, duration_s=12, freeze_s=2)
    outages = summary["outages"]
    longest = outages["longest"]
    assert outages["count"] >= 1 and longest["ticks"] > CTL.outage_warn_periods, outages
    assert longest["start_tick"] >= 50 - 1
    named = [w for w in summary["warnings"] if w.startswith("camera outage from tick")]
    assert any(f"from tick {longest['start_tick']} " in w for w in named), summary["warnings"]
    assert f"from tick {longest['start_tick']} " in err  # said on stderr, as a warning
    assert "hil up: warning: camera outage" in err
    # not past the share: the outage alone does not make the run not clean
    assert outages["share"] <= CTL.outage_max_share, outages
    assert not [p for p in summary["problems"] if "stale or invalid" in p], summary["problems"]
    # hil report finds the same outages in the log's f_stale / f_valid columns
    assert report_of(summary["log"])["outages"] == outages


def test_a_longer_camera_freeze_makes_the_run_not_clean(tmp_path):
    rc, summary, err = freeze_vision(tmp_path, duration_s=8, freeze_s=5)
    outages = summary["outages"]
    assert outages["share"] > CTL.outage_max_share, outages
    assert rc == 1, err
    (problem,) = [p for p in summary["problems"] if "stale or invalid" in p]
    assert f"from tick {outages['longest']['start_tick']} " in problem
    assert "run not clean" in err and "controller.outage_max_share" in err
