"""``hil bench loop``'s lockstep profile: where a period's wall time goes, from cycle records."""

from __future__ import annotations

import os

import numpy as np
import pytest

from rt_controller.rig.bench_loop import lockstep_period_profile


def test_lockstep_period_profile_splits_each_period_exactly() -> None:
    # four ticks 1000 us apart; each cycle waited 300 us for features, solved 100, wrote 50
    cycles = {
        "t_ns": np.array([0, 1_000_000, 2_000_000, 3_000_000], dtype=np.int64),
        "read_us": np.full(4, 300.0),
        "solve_us": np.full(4, 100.0),
        "write_us": np.full(4, 50.0),
        "cycle_us": np.full(4, 450.0),
    }
    prof = lockstep_period_profile(cycles)
    assert prof == {
        "period_median": 1000.0,
        "period_p99": 1000.0,
        "features_wait": 300.0,
        "solve": 100.0,
        "write": 50.0,
        "dsp_and_can": 550.0,
    }
    assert prof["features_wait"] + prof["solve"] + prof["write"] + prof[
        "dsp_and_can"
    ] == pytest.approx(prof["period_median"])


def test_lockstep_period_profile_of_a_single_tick_is_empty() -> None:
    one = {k: np.zeros(1) for k in ("t_ns", "read_us", "solve_us", "write_us", "cycle_us")}
    assert lockstep_period_profile(one) == {}


def test_a_run_that_was_not_clean_fails_the_bench_but_its_figures_are_printed(
    monkeypatch, capsys
) -> None:
    import json

    from rt_controller.cli import main
    from rt_controller.rig import bench_loop as bl

    def fake(cfg, **kw):
        runs = [
            {"rate_hz": 50.0, "problems": []},
            {"rate_hz": 500.0, "problems": ["1 DSP watchdog trip(s)"]},
        ]
        return {"rates": runs, "lockstep": None}

    monkeypatch.setattr(bl, "bench_loop", fake)
    assert main(["bench", "loop", "--rates", "50,500", "--lockstep-duration", "0"]) == 1
    out = capsys.readouterr()
    assert [r["rate_hz"] for r in json.loads(out.out)["rates"]] == [50.0, 500.0]
    assert "run not clean at 500 Hz: 1 DSP watchdog trip(s)" in out.err
    assert "50 Hz" not in out.err


@pytest.mark.integration
def test_kept_logs_are_the_runs_logs(tmp_path) -> None:
    """``--keep DIR``: each rate's MCAP log and config stay there, and the record names it.
    (A real-time run on a loaded host may fault, so its cleanliness is not asserted: the
    record's ``problems`` must only agree with what the log says.)"""
    from rt_controller.logtools.reader import read_log
    from rt_controller.rig.bench_loop import bench_loop

    out = bench_loop(
        rates=(50.0,), duration=1.0, law="ioc", lockstep_duration=0, keep=tmp_path, host_probe_s=0.2
    )
    probes = out["host"]["probes"]  # the host's floor, measured first
    assert len(probes) == len(os.sched_getaffinity(0)) and all(p["wakeups"] > 0 for p in probes)
    (run,) = out["rates"]
    log = read_log(run["log"])
    assert run["log"] == str(tmp_path / "loop-50.mcap") and (tmp_path / "rig-50.toml").is_file()
    assert log.n_cycles == run["ticks"] > 0
    drive_modes = {"fault", "disarmed", "no_status", "dsp_restarted"}
    held = sum(1 for law in log.cycles["law"] if law in drive_modes)
    assert held == sum(run["drive_ticks"].values())
    if held or run["dsp_faults"] or run["watchdog_trips"]:
        assert run["problems"]  # a run that faulted is never reported clean
    ran = [i for i, law in enumerate(log.cycles["law"]) if law == "ioc"]
    ages = sorted(float(log.cycles["predict_ms"][i]) for i in ran)
    assert run["predict_ms"]["max"] == ages[-1]  # the compensated ages, over the law's ticks
    assert run["f_predict_ms"]["max"] == max(float(log.cycles["f_predict_ms"][i]) for i in ran)


def test_compare_puts_both_profiles_figures_of_one_rate_side_by_side() -> None:
    from rt_controller.rig.bench_loop import compare

    stats = {"min": 1.0, "median": 2.0, "p99": 3.0, "max": 4.0}
    run = {"rate_hz": 50.0, "lateness_us": stats, "cycle_us": stats, "e2e_us": None}
    timing = {
        "sync": {"period_error_us": {**stats, "median": 5.0}},
        "sync_to_tpdo_us": stats,
        "pdo_round_trip_us": stats,
        "torque_to_effect_us": {**stats, "p99": 9.0},
    }
    row = compare(
        {**run, "deadline_misses": 0, "problems": []},
        {**run, "deadline_misses": 1, "problems": ["x"], "canopen": timing},
    )
    assert row["rate_hz"] == 50.0
    assert row["dsp"] == {
        "lateness_us": {"median": 2.0, "p99": 3.0},
        "cycle_us": {"median": 2.0, "p99": 3.0},
        "e2e_us": None,
        "deadline_misses": 0,
        "clean": True,
    }
    c = row["cia402"]
    assert c["clean"] is False and c["deadline_misses"] == 1
    assert c["sync_period_error_us"] == {"median": 5.0, "p99": 3.0}
    assert c["torque_to_effect_us"] == {"median": 2.0, "p99": 9.0}
