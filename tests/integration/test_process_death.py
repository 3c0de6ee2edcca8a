"""A process of the rig that dies mid-run still leaves ``hil up`` a full summary and exit 1.

Each test starts the real ``hil up --json`` (realtime, as a user runs it), waits until the
controller has logged some ticks, SIGKILLs one of its three children and checks the one JSON
object on stdout: which process ended how and at which tick, the DSP's watchdog account, the
log's path and what it holds, and the problems. No wall-clock assertion: the waits poll.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from hal.config import load_config
from hal.zenoh_session import free_loopback_port
from rt_controller.config_rules import config_toml
from rt_controller.rig.failures import RigProcessDied
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import run_rig_plan
from tests.support import cycles_logged, killed_once_ticking, start_hil_up
from tests.support.proc import WAIT_S, child_running, processes_mentioning, reaped, wait_for

pytestmark = pytest.mark.integration

TICKS_BEFORE_KILL = 50


def kill_mid_run(tmp_path: Path, victim: str, *extra: str) -> tuple[int, dict, str, Path, int]:
    """``hil up --json`` with ``victim`` SIGKILLed after :data:`TICKS_BEFORE_KILL` ticks: exit
    status, the summary printed, stderr, the log path and the ticks logged before the kill."""
    ep, log = f"tcp/127.0.0.1:{free_loopback_port()}", tmp_path / "run.mcap"
    with reaped(start_hil_up(ep, log, "--duration", "600", "--json", *extra)) as proc:
        wait_for(lambda: cycles_logged(log) >= TICKS_BEFORE_KILL, "the first ticks", proc)
        seen = cycles_logged(log)
        pid = child_running(proc.pid, victim)
        assert pid is not None, f"no {victim} child"
        os.kill(pid, signal.SIGKILL)
        out, err = proc.communicate(timeout=WAIT_S)
    deadline = time.monotonic() + WAIT_S
    while processes_mentioning(ep) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not processes_mentioning(ep), "a process of the rig outlived hil up"
    lines = [line for line in out.splitlines() if line.startswith("{")]
    assert len(lines) == 1, f"no JSON summary (exit {proc.returncode}):\n{out}\n{err}"
    return proc.returncode, json.loads(lines[0]), err, log, seen


def check_common(rc: int, summary: dict, err: str, log: Path, victim: str, seen: int) -> None:
    assert rc == 1, err  # not clean; 2 is for bad usage only
    assert "Traceback" not in err, err
    ended = summary["ended_by"]
    assert ended["process"] == victim and ended["signal"] == "SIGKILL", summary
    assert ended["exit_code"] is None
    assert isinstance(ended["tick"], int) and ended["tick"] >= seen - 1, summary
    assert ended["time_s"] > 0
    assert victim in summary["end_reason"] and "SIGKILL" in summary["end_reason"]
    assert f"tick {ended['tick']}" in summary["end_reason"]
    assert summary["log"] == str(log)
    contents = summary["log_contents"]
    assert contents["finished"] is True, contents  # the recorder finished it
    assert contents["cycles"] >= seen and contents["cycles"] == summary["ticks"], summary
    assert any(victim in p and "SIGKILL" in p for p in summary["problems"]), summary
    assert summary["J"] is not None and summary["planned_ticks"] == 600 * summary["rate_hz"]
    assert "run not clean" in err


def test_a_killed_controller_leaves_a_summary_and_the_dsp_trip(tmp_path):
    rc, summary, err, log, seen = kill_mid_run(tmp_path, "controller")
    check_common(rc, summary, err, log, "controller", seen)
    # the controller's own last tick is the log's last
    assert summary["ended_by"]["tick"] == summary["log_contents"]["last_tick"]
    dsp = summary["dsp"]
    assert dsp["reported"] is True and dsp["watchdog_trips"] >= 1, dsp
    assert dsp["fault_reason"] == "watchdog" and dsp["drive_state"] == "fault", dsp
    # torque off no sooner than the watchdog time after the last command
    assert dsp["torque_off_after_ms"] >= dsp["watchdog_period_ms"], dsp
    assert dsp["torque_off_s"] >= dsp["last_command_s"], dsp


def test_a_killed_controller_faults_every_cia402_drive(tmp_path):
    """The cia402 profile: with the controller gone, SYNC stops; every drive takes its torque
    away in FAULT with an EMCY, no sooner than its SYNC-loss limit, and the summary says so."""
    rc, summary, err, log, seen = kill_mid_run(tmp_path, "controller", "--profile", "cia402")
    check_common(rc, summary, err, log, "controller", seen)
    cfg = load_config(None)
    limit_ms = cfg.cia402.sync_loss_periods * cfg.rates.control_period_ns / 1e6
    dsp = summary["dsp"]
    assert dsp["profile"] == "cia402" and dsp["drive_state"] == "fault", dsp
    nodes = {str(cfg.cia402.node_id_1), str(cfg.cia402.node_id_2)}
    assert set(dsp["drives"]) == nodes and dsp["watchdog_trips"] == len(nodes), dsp
    for node, drive in dsp["drives"].items():
        off = drive["torque_off"]
        assert drive["state"] == "FAULT" and off["emcy"] in ("0x8700", "0x8130"), dsp
        assert off["emcy"] in dsp["emcys"][node], dsp  # the EMCY went on the bus
        if off["emcy"] == "0x8700":  # SYNC loss: never before its limit
            assert off["after_last_sync_ms"] >= limit_ms, dsp


def test_a_killed_emulator_leaves_a_summary(tmp_path):
    rc, summary, err, log, seen = kill_mid_run(tmp_path, "emulator")
    check_common(rc, summary, err, log, "emulator", seen)
    assert summary["dsp"]["reported"] is False  # the DSP died: nobody to say


def test_a_killed_vision_process_leaves_a_summary(tmp_path):
    rc, summary, err, log, seen = kill_mid_run(tmp_path, "vision")
    check_common(rc, summary, err, log, "vision", seen)
    dsp = summary["dsp"]  # the controller stopped in order: torque off, no trip
    assert dsp["reported"] is True and dsp["watchdog_trips"] == 0, dsp


@pytest.mark.parametrize("victim", ["controller", "vision"])
def test_a_plan_run_cut_short_by_a_death_has_its_summary(tmp_path, victim):
    """``hil experiment``'s lockstep batches: the run a death cut short is reported with the
    same summary (its log's counters when the controller died), not only as an error."""
    cfg = load_config(None).with_overrides({"controller.clock": "lockstep"})
    config = tmp_path / "rig.toml"
    config.write_text(config_toml(cfg), encoding="utf-8")
    logs = {name: tmp_path / f"{name}.mcap" for name in ("first", "second")}
    doc = [
        {"name": n, "config": str(config), "law": "ioc", "duration_s": 600.0, "log": str(log)}
        for n, log in logs.items()
    ]
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"runs": doc}), encoding="utf-8")
    opts = RigOptions(config=str(config), duration_s=1200.0, lockstep=True, plan=plan)
    with killed_once_ticking(logs["first"], victim, TICKS_BEFORE_KILL):
        summaries, error = run_rig_plan(opts, 2)
    assert isinstance(error, RigProcessDied) and error.end.name == victim, error
    (cut,) = summaries
    assert cut["run"] == "first" and cut["ended_by"]["process"] == victim, cut
    assert cut["ended_by"]["signal"] == "SIGKILL" and cut["log"] == str(logs["first"])
    assert cut["log_contents"]["cycles"] >= TICKS_BEFORE_KILL and cut["log_contents"]["finished"]
    assert any(victim in p for p in cut["problems"]), cut["problems"]
    assert cut["planned_ticks"] == 600 * 50
    if victim == "controller":
        dsp = cut["dsp"]
        assert dsp["watchdog_trips"] >= 1 and dsp["fault_reason"] == "watchdog", dsp
        assert dsp["torque_off_after_ms"] >= dsp["watchdog_period_ms"], dsp
