"""The pieces of a summary after a process died (``rig/ending.py``) and the table ``hil up``
prints (only the counters that are not zero), on fixed inputs."""

from __future__ import annotations

import json
import signal

from rt_controller.commands.up import nonzero, table_view
from rt_controller.rig.ending import (
    ProcessEnd,
    contents_words,
    dsp_report,
    dsp_words,
    log_contents,
    log_path_said,
    summary_after,
)
from rt_controller.runtime.counters import run_problems

STATS = {
    "watchdog_trips": 1,
    "last_trip_latency_ms": 60.8,
    "last_command_sim_s": 1.659,
    "last_trip_sim_s": 1.72,
    "watchdog_period_ms": 60.0,
    "drive_state": "fault",
    "fault_reason": "watchdog",
    "last_fault": "watchdog at physics step 1720 (t = 1.720 s): torque off 60.8 ms after ...",
}


def test_how_a_process_ended_in_words():
    killed = ProcessEnd("controller", -signal.SIGKILL, 0)
    assert killed.how == "killed by SIGKILL" and killed.signal_name == "SIGKILL"
    failed = ProcessEnd("vision", 3, 0)
    assert failed.how == "exited with status 3" and failed.signal_name is None


def test_the_log_path_the_controller_announced():
    err = "hil controller: law ioc at 50 Hz (realtime), logging to logs/run-1-ioc.mcap\nmore"
    assert str(log_path_said(err)) == "logs/run-1-ioc.mcap"
    assert log_path_said("hil controller: error: no features") is None


def test_the_dsp_report_is_the_last_whole_json_line():
    out = json.dumps(STATS) + "\n" + '{"watchdog_trips": 7, "cut'  # a line cut by a kill
    dsp = dsp_report(out)
    assert dsp["reported"] and dsp["watchdog_trips"] == 1
    assert dsp["torque_off_after_ms"] == 60.8 and dsp["torque_off_s"] == 1.72
    assert "torque off 60.8 ms after the last command" in dsp_words(dsp)
    assert dsp_report("")["reported"] is False
    assert dsp_words(dsp_report("")) == "the emulator printed no counters"


def test_lockstep_periods_the_dsp_advanced_unanswered_make_the_run_not_clean():
    """A lockstep run is the deterministic one only if the DSP had every period's command
    before its reply timeout; a period it advanced with the held torque (a host too slow)
    changes J silently unless the run says so."""
    out = json.dumps({**STATS, "watchdog_trips": 0, "skipped_periods": 2, "skipped_by_run": [0, 2]})
    dsp = dsp_report(out + "\n")
    assert dsp["skipped_periods"] == 2 and dsp["skipped_by_run"] == [0, 2]
    lockstep = {"clock": "lockstep", "dsp": dsp}
    assert run_problems(lockstep) == [
        "the DSP advanced 2 lockstep period(s) with the held torque (no command within "
        "dsp.lockstep_reply_timeout_s): not the deterministic run"
    ]
    assert run_problems({**lockstep, "dsp": {**dsp, "skipped_periods": 0}}) == []
    # realtime has no such periods, and an emulator that printed nothing is said elsewhere
    assert run_problems({"clock": "realtime", "dsp": dsp}) == []
    assert run_problems({"clock": "lockstep", "dsp": dsp_report("")}) == []


def test_a_log_that_is_not_there_is_said_so(tmp_path):
    contents = log_contents(tmp_path / "none.mcap")
    assert "error" in contents and contents_words(contents) == contents["error"]
    assert "error" in log_contents(None)


def test_a_death_before_any_log_still_gives_the_summary(tmp_path):
    base = {"clock": "realtime", "rate_hz": 50.0, "ticks": None, "planned_ticks": 500}
    end = ProcessEnd("emulator", 2, 0)
    out = summary_after(end, None, tmp_path / "none.mcap", {"reported": False}, base)
    assert out["end_reason"] == "emulator exited with status 2 before its first tick"
    assert out["ended_by"] == {
        "process": "emulator",
        "signal": None,
        "exit_code": 2,
        "tick": None,
        "time_s": None,
    }
    assert out["problems"][0] == f"the run ended after 0 of 500 ticks: {out['end_reason']}"
    assert any("the log cannot be read" in p for p in out["problems"])


def test_the_controllers_own_end_reason_is_kept():
    summary = {"ticks": 40, "planned_ticks": 500, "end_reason": "the DSP fell silent"}
    out = summary_after(ProcessEnd("emulator", -9, 0), summary, None, {"reported": False}, {})
    assert out["end_reason"].endswith("; the controller: the DSP fell silent")
    assert out["problems"][0].startswith("the run ended after 40 of 500 ticks: emulator killed")


def test_the_table_shows_only_counters_that_are_not_zero():
    rejections = {
        "can_rx": {"accepted": 10, "crc": 0, "counter": 2},
        "features": {"accepted": 0, "stale": 0},
        "dsp_rejected_frames": 0,
    }
    assert nonzero(rejections) == {"can_rx.accepted": 10, "can_rx.counter": 2}
    table = table_view(
        {"rejections": rejections, "recorder": {"written": 5, "dropped": 0, "pending": 0}}
    )
    assert table["rejections"] == "can_rx.counter 2"
    assert table["input_counts"] == "can_rx.accepted 10"
    assert table["recorder"].startswith("written 5 (the topics listed")
    assert table_view({"recorder": {"dropped": 0}})["recorder"] == "none"


def test_a_dead_controller_s_summary_counts_the_trip_the_dsp_reports(tmp_path):
    """The controller killed: its last record counted no trip, but the DSP tripped its
    watchdog after the death (the safe stop). The table must not say ``watchdog_trips 0``
    and ``dsp_faults none`` beside ``dsp: 1 watchdog trip(s) ...; drive fault``."""
    base = {"clock": "lockstep", "rate_hz": 50.0, "planned_ticks": 500, "watchdog_trips": 0}
    dsp = dsp_report(json.dumps(STATS) + "\n")
    killed = ProcessEnd("controller", -signal.SIGKILL, 0)
    out = summary_after(killed, None, tmp_path / "none.mcap", dsp, base)
    assert out["watchdog_trips"] == 1 and out["dsp_faults"] == {"watchdog": 1}
    assert "1 DSP watchdog trip(s)" in out["problems"]
    table = table_view(out)
    assert table["watchdog_trips"] == 1 and table["dsp_faults"] == "watchdog 1"
    quiet = dsp_report(json.dumps({**STATS, "watchdog_trips": 0, "drive_state": "enabled"}))
    out = summary_after(killed, None, tmp_path / "none.mcap", quiet, base)
    assert out["watchdog_trips"] == 0 and not out.get("dsp_faults")
