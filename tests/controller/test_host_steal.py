"""The hypervisor's steal, read from ``/proc/stat``, and the warning a disturbed realtime run
carries: a clean run (exit 0) whose J is not the lockstep experiment's says so."""

from __future__ import annotations

import pytest

from rt_controller.commands.output import verdict
from rt_controller.runtime.counters import run_warnings
from rt_controller.runtime.host_steal import (
    DISTURBED_STEAL_PERCENT,
    PROC_STAT,
    cpu_ticks,
    steal_percent,
)

STAT = "cpu  100 5 50 800 10 0 3 32 0 0\ncpu0 50 2 25 400 5 0 1 16 0 0\nintr 1\n"


def test_cpu_ticks_reads_steal_and_the_total_of_all_cpus(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text(STAT, encoding="ascii")
    assert cpu_ticks(stat) == (32, 100 + 5 + 50 + 800 + 10 + 0 + 3 + 32)


@pytest.mark.parametrize(
    "text", ["", "cpu 1 2 3\n", "intr 1 2 3 4 5 6 7 8 9\n", "cpu a b c d e f g h\n"]
)
def test_cpu_ticks_is_none_where_there_is_no_linux_stat(tmp_path, text):
    stat = tmp_path / "stat"
    stat.write_text(text, encoding="ascii")
    assert cpu_ticks(stat) is None
    assert cpu_ticks(tmp_path / "missing") is None


def test_steal_percent_is_the_share_of_the_time_between_two_readings():
    assert steal_percent((10, 1000), (60, 1200)) == pytest.approx(25.0)
    assert steal_percent(None, (60, 1200)) is None
    assert steal_percent((10, 1000), None) is None
    assert steal_percent((10, 1000), (10, 1000)) is None  # no time passed


def test_this_host_reports_a_steal_between_zero_and_all():
    if not PROC_STAT.exists():
        pytest.skip("no /proc/stat")
    before = cpu_ticks()
    sum(range(200_000))
    share = steal_percent(before, cpu_ticks())
    assert share is None or 0.0 <= share <= 100.0


def disturbed(**over):
    return {
        "clock": "realtime",
        "host_steal_percent": DISTURBED_STEAL_PERCENT,
        "late_states": 7,
        **over,
    }


def test_a_realtime_run_on_a_stolen_host_is_clean_but_warns_that_its_j_is_not_lockstep(capsys):
    summary = {**disturbed(), "problems": []}
    summary["warnings"] = run_warnings(summary)
    assert len(summary["warnings"]) == 1
    assert "10 %" in summary["warnings"][0] and "7 tick(s)" in summary["warnings"][0]
    assert verdict(summary, "hil up") == 0  # still clean
    err = capsys.readouterr().err
    assert "hil up: warning: the hypervisor took 10 %" in err and "--lockstep" in err


@pytest.mark.parametrize(
    "summary",
    [
        disturbed(host_steal_percent=DISTURBED_STEAL_PERCENT - 0.1),
        disturbed(host_steal_percent=None),
        disturbed(clock="lockstep", host_steal_percent=None),
        disturbed(clock="lockstep", host_steal_percent=50.0),
    ],
)
def test_no_warning_below_the_threshold_without_a_reading_or_in_lockstep(summary):
    assert run_warnings(summary) == []


def test_problems_still_make_a_warned_run_not_clean(capsys):
    summary = {**disturbed(), "problems": ["2 DSP watchdog trip(s)"]}
    summary["warnings"] = run_warnings(summary)
    assert verdict(summary, "hil controller") == 1
    err = capsys.readouterr().err
    assert "hil controller: warning:" in err and "run not clean: 2 DSP watchdog trip(s)" in err
