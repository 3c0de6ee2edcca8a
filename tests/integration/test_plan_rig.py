"""``hil controller --plan`` on the real daemons: runs after a scenario reset are the runs fresh
processes give, also after a run that faulted the DSP; every run keeps its own log and counters.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from hal.config import load_config
from hal.zenoh_session import free_loopback_port
from rt_controller.config_rules import config_toml
from rt_controller.logtools.reader import read_log
from rt_controller.rig.failures import RigCancelled
from rt_controller.rig.options import RigOptions
from rt_controller.rig.processes import run_rig, run_rig_plan
from tests.support.proc import running_controller

pytestmark = [pytest.mark.integration, pytest.mark.slow]

DURATION_S = 2.0


def _config(tmp_path: Path, name: str, **overrides: object) -> Path:
    cfg = load_config(None).with_overrides({"controller.clock": "lockstep", **overrides})
    path = tmp_path / f"{name}.toml"
    path.write_text(config_toml(cfg), encoding="utf-8")
    return path


def test_a_run_after_a_faulted_one_is_the_run_fresh_processes_give(tmp_path):
    """Plan: IOC with a gain that drives the arm past the DSP's velocity limit (the DSP
    faults), then RHC with another camera noise seed and IOC with the first seed again, with
    the paper's gains. The faulted run is reported not clean; the reset clears the fault and
    names the next run's seed, and the next runs equal fresh runs bit for bit."""
    runs = [
        ("wild", _config(tmp_path, "wild", **{"gains.kp": 40.0}), "ioc"),
        ("rhc", _config(tmp_path, "rhc", **{"camera.seed": 3}), "rhc"),
        ("ioc", _config(tmp_path, "ioc"), "ioc"),
    ]
    plan = tmp_path / "plan.json"
    doc = [
        {"name": n, "config": str(c), "law": law, "duration_s": DURATION_S, "log": f"{n}.mcap"}
        for n, c, law in runs
    ]
    for entry in doc:
        entry["log"] = str(tmp_path / "plan" / entry["log"])
    plan.write_text(json.dumps({"runs": doc}), encoding="utf-8")
    opts = RigOptions(config=str(runs[0][1]), duration_s=3 * DURATION_S, lockstep=True, plan=plan)
    summaries, error = run_rig_plan(opts, len(runs))
    assert error is None
    assert [s["run"] for s in summaries] == ["wild", "rhc", "ioc"]
    wild, rhc, ioc = summaries
    assert wild["dsp_faults"] == {"velocity_limit": 1} and wild["problems"]
    assert rhc["problems"] == [] and ioc["problems"] == [], (rhc["problems"], ioc["problems"])
    for summary in (rhc, ioc):
        assert summary["ticks"] == DURATION_S * 50 and summary["dsp_faults"] == {}
    for (name, config, law), summary in zip(runs[1:], (rhc, ioc), strict=True):
        log = tmp_path / f"fresh-{name}.mcap"
        fresh = run_rig(
            RigOptions(config=str(config), law=law, duration_s=DURATION_S, lockstep=True, log=log)
        )
        assert fresh["J"] == summary["J"] and fresh["f_final"] == summary["f_final"]
        # each run counts its own frames (three per tick: two state frames and a Sync), not
        # those of the runs before it on the same links
        accepted = summary["rejections"]["can_rx"]["accepted"]
        before = wild["rejections"]["can_rx"]["accepted"]
        assert (
            3 * summary["ticks"]
            <= accepted
            < fresh["rejections"]["can_rx"]["accepted"] + (before // 2)
        )
        a = read_log(log, raw=False).cycles
        b = read_log(Path(summary["log"]), raw=False).cycles
        for col in ("q", "dq", "f", "tau", "cost"):
            assert a[col].tobytes() == b[col].tobytes(), (name, col)


def test_a_period_the_dsp_skipped_in_a_plan_fails_that_run(tmp_path):
    """Freeze the controller for 1.2 s in the first run of a two-run plan: the DSP advances
    the period it waits on with the held torque. That run, and only that one, is reported
    not the deterministic one (the DSP counts skipped periods by run)."""
    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    config = _config(tmp_path, "ioc")
    doc = [
        {"name": n, "config": str(config), "law": "ioc", "duration_s": d,
         "log": str(tmp_path / f"{n}.mcap")}
        for n, d in (("frozen", 60.0), ("next", DURATION_S))
    ]  # fmt: skip
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"runs": doc}), encoding="utf-8")
    froze = threading.Event()

    def freeze() -> None:
        pid = running_controller(ep, Path(doc[0]["log"]))
        os.kill(pid, signal.SIGSTOP)
        time.sleep(1.2)  # fault injection: any freeze past the DSP's 0.5 s skips a period
        os.kill(pid, signal.SIGCONT)
        froze.set()

    injector = threading.Thread(target=freeze, daemon=True)
    injector.start()
    opts = RigOptions(
        config=str(config), duration_s=120.0, lockstep=True, plan=plan, zenoh_endpoint=ep
    )
    summaries, error = run_rig_plan(opts, 2)
    injector.join(5)
    assert froze.is_set() and error is None
    assert [s["run"] for s in summaries] == ["frozen", "next"]
    frozen, clean = summaries
    assert any("lockstep period(s)" in p for p in frozen["problems"]), frozen["problems"]
    assert clean["problems"] == [], clean["problems"]


def test_a_cancelled_plan_hands_over_the_runs_that_ended(tmp_path):
    """Cancel a two-run plan in its second run (``hil experiment``'s Ctrl-C): the first run's
    summary goes with :class:`RigCancelled`, so its result is kept, not called not run."""
    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    config = _config(tmp_path, "ioc")
    doc = [
        {"name": n, "config": str(config), "law": "ioc", "duration_s": d,
         "log": str(tmp_path / f"{n}.mcap")}
        for n, d in (("first", DURATION_S), ("second", 60.0))
    ]  # fmt: skip
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"runs": doc}), encoding="utf-8")
    cancel = threading.Event()

    def cancel_in_the_second_run() -> None:
        running_controller(ep, Path(doc[1]["log"]), cycles=20)
        cancel.set()

    threading.Thread(target=cancel_in_the_second_run, daemon=True).start()
    opts = RigOptions(config=str(config), duration_s=120.0, lockstep=True, plan=plan,
                      zenoh_endpoint=ep, cancel=cancel)  # fmt: skip
    with pytest.raises(RigCancelled) as cancelled:
        run_rig_plan(opts, 2)
    assert [s["run"] for s in cancelled.value.summaries] == ["first"]
    (first,) = cancelled.value.summaries
    assert first["problems"] == [] and first["ticks"] == DURATION_S * 50, first
