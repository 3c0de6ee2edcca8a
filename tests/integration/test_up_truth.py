"""``hil up`` tells the truth: its summary says what was run, Ctrl-C still prints it, a hang
and a lockstep run that ended short are "not clean" (exit 1) with their reason, the shared
options (``--rate``, ``--horizon``, ``--steps``) reach every process, and a monitor port that
cannot be opened stops the command before any process starts.

Faults are injected by signals (SIGSTOP on the emulator, SIGINT to ``hil up``); nothing here
asserts a wall-clock timing.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import time

import pytest

from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import Rig
from rt_controller.runtime.counters import run_problems
from tests.support import cycles_logged, free_endpoint, run_hil, start_hil_up, wait_until

pytestmark = pytest.mark.integration


def test_up_takes_rate_horizon_and_steps_and_says_what_it_ran(tmp_path):
    rhc = ["--law", "rhc", "--rate", "100", "--steps", "8", "--horizon", "0.08"]
    log = ["--log", str(tmp_path / "r.mcap")]
    out = run_hil(["up", "--lockstep", *rhc, "--duration", "1", "--json", *log], timeout_s=240)
    assert out.returncode == 0, out.stderr
    s = json.loads(out.stdout)
    assert (s["clock"], s["rate_hz"], s["law"], s["horizon_s"], s["steps"]) == (
        "lockstep",
        100.0,
        "rhc",
        0.08,
        8,
    )
    assert s["duration_s"] == 1.0 and s["ticks"] == s["planned_ticks"] == 100
    assert s["end_reason"] == "duration" and s["can"].startswith("udp_multicast")
    # f measured from the emulated camera's pixels (camera.model = "image", the default): the
    # default lens and sensor noise leave 0.015 px at q(0) (measured, lockstep, bit-exact per
    # seed); the analytic camera gave -120, -160 to 1e-13
    assert s["f_first"] == pytest.approx([-120.0, -160.0], abs=0.05)
    assert s["jump_seen_s"] is None  # the jump comes at 3 s, after this run


def test_a_config_s_lockstep_clock_is_the_rig_s_without_the_flag(tmp_path):
    """The config an experiment writes (controller.clock = "lockstep") given to ``hil up``
    without --lockstep: the emulator took lockstep from it and the controller was told
    realtime, so the rig waited 20 s for features and exited 2."""
    cfg = tmp_path / "rig.toml"
    cfg.write_text('[controller]\nclock = "lockstep"\nlaw = "ioc"\n', encoding="utf-8")
    log = ["--log", str(tmp_path / "r.mcap")]
    out = run_hil(["up", "--config", str(cfg), "--duration", "1", "--json", *log], 240)
    assert out.returncode == 0, out.stderr
    s = json.loads(out.stdout)
    assert (s["clock"], s["ticks"], s["problems"]) == ("lockstep", 50, []), s


def test_a_bad_rate_is_refused_before_the_rig_starts():
    out = run_hil(["up", "--rate", "-5"], timeout_s=60)
    assert out.returncode == 2
    assert out.stderr.startswith("hil up: error:") and "--rate" in out.stderr


def test_a_monitor_port_in_use_fails_before_the_rig_starts():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        port = sock.getsockname()[1]
        out = run_hil(["up", "--monitor-port", str(port), "--duration", "1"], timeout_s=60)
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip() == (
        f"hil up: error: --monitor: cannot listen on 127.0.0.1:{port}: Address already in use "
        "(another rig's live view?); choose another with --monitor-port PORT (0 = any)"
    )
    assert out.stdout == ""


def test_a_hang_is_a_run_not_clean_with_its_reason():
    out = run_hil(["up", "--wall-timeout", "0.1", "--json"], timeout_s=120)
    assert out.returncode == 1, out.stderr
    summary = json.loads(out.stdout)
    assert "wall-clock budget of 0.1 s (--wall-timeout)" in summary["problems"][0]
    assert summary["planned_ticks"] == 500 and "exit_codes" in summary, summary
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("hil up: run not clean: hung: controller still running"), out.stderr


def test_ctrl_c_still_prints_the_summary_and_the_log(tmp_path):
    ep, log = free_endpoint(), tmp_path / "run.mcap"
    proc = start_hil_up(ep, log, "--duration", "600", "--lockstep", "--json")
    try:
        assert wait_until(lambda: cycles_logged(log) >= 20, timeout_s=120)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:  # pragma: no cover - only on a hang
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, err
    summary = json.loads(out)
    assert summary["log"] == str(log) and summary["ticks"] >= 20
    assert summary["end_reason"] == "stopped" and summary["problems"] == []


def test_a_lockstep_run_outlives_a_stalled_emulator(tmp_path):
    """The emulator stops for longer than the old 2 s Sync timeout (SIGSTOP, as a host that
    deschedules it would): the controller waits for it and the run gets all its ticks. On the
    old main it ended short and called itself clean."""
    log = tmp_path / "stall.mcap"
    opts = RigOptions(lockstep=True, duration_s=4.0, log=log, law="pbc")
    with Rig(opts) as rig:
        rig.start()
        emulator = next(c for c in rig.children if c.name == "emulator")
        assert wait_until(lambda: cycles_logged(log) >= 30, timeout_s=120)
        os.kill(emulator.proc.pid, signal.SIGSTOP)
        time.sleep(3.0)  # the stall, longer than the old timeout
        os.kill(emulator.proc.pid, signal.SIGCONT)
        summary = rig.wait_controller()
    assert summary["ticks"] == summary["planned_ticks"] == 200, summary
    assert summary["problems"] == [], summary["problems"]


def test_a_lockstep_run_that_ended_short_is_not_clean():
    short = {"ticks": 211, "planned_ticks": 400, "end_reason": "no Sync from the DSP for 30 s"}
    assert run_problems(short) == [
        "the run ended after 211 of 400 ticks: no Sync from the DSP for 30 s"
    ]
    assert run_problems({**short, "end_reason": "stopped"}) == []
    assert run_problems({"ticks": 400, "planned_ticks": 400, "end_reason": "duration"}) == []


def test_set_keys_reach_every_process_of_the_rig(tmp_path):
    """``--set``: the controller's clock and rate, and the vision process's camera model (the
    analytic camera gives f(0) to 1e-9; the image pipeline is 0.015 px off, measured)."""
    sets = ["controller.clock=lockstep", "rates.control_hz=25", "camera.model=analytic"]
    argv = ["up", "--law", "ioc", "--duration", "1", "--json", "--log", str(tmp_path / "r.mcap")]
    out = run_hil([*argv, *(a for s in sets for a in ("--set", s))], timeout_s=240)
    assert out.returncode == 0, out.stderr
    s = json.loads(out.stdout)
    assert (s["clock"], s["rate_hz"], s["ticks"], s["problems"]) == ("lockstep", 25.0, 25, [])
    assert s["f_first"] == pytest.approx([-120.0, -160.0], abs=1e-9)
