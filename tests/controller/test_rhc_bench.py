"""Smoke test of the solver benchmark's JSON shape (timings are never asserted)."""

from __future__ import annotations

import json
import math

from rt_controller.rig.bench_solver import bench_solver
from tests.support.bench_reference import bench_reference


def test_bench_solver_reports_the_documented_keys(cfg):
    out = bench_solver(cfg, updates=12, sweep=(5,))
    json.dumps(out)  # JSON-ready
    assert out["N"] == cfg.rhc.steps and out["kmax"] == cfg.rhc.kmax and out["updates"] == 12
    assert set(out["solve_us"]) == {"median", "p99", "max"}
    assert out["residual_median"] < 1e-3 and out["fallbacks"] == 0
    assert "numpy_reference" not in out  # the test oracle is timed test-side
    assert [s["N"] for s in out["sweep"]] == [5]
    assert set(out["machine"]["load"]) == {"1min", "5min", "15min"}


def test_bench_profile_counts_one_solve_per_tick(cfg):
    """kmax + 3 evaluations of F per continuation tick: F, its prediction, kmax products, the
    residual at the applied solution (more only on the rare ticks that release a bound)."""
    out = bench_solver(cfg, updates=20, sweep=())
    prof = out["profile"]
    assert prof["fevals_per_tick"] == cfg.rhc.kmax + 3
    assert out["fevals_median"] == cfg.rhc.kmax + 3
    assert prof["replayed_ticks"] > 0
    for key in ("sweep_us", "update_us", "kernel_us", "sweeps_us", "gmres_us", "wrapper_us"):
        assert math.isfinite(prof[key])
    assert prof["sweep_us"] > 0 and prof["kernel_us"] > 0


def test_bench_paced_replays_recorded_ticks_one_per_control_period(cfg):
    """``paced``: the recorded continuation ticks, one per control period with the core idle
    in between (the figure the live daemon's ``law_us`` is compared with); the configured N
    only, not the sweep."""
    out = bench_solver(cfg, updates=30, sweep=(5,))
    paced = out["paced"]
    assert paced["period_s"] == 1.0 / cfg.rates.control_hz
    assert paced["ticks"] == out["profile"]["replayed_ticks"] > 0
    assert set(paced["solve_us"]) == {"median", "p99", "max"}
    assert all(math.isfinite(v) and v > 0 for v in paced["solve_us"].values())
    assert "paced" not in out["sweep"][0]


def test_bench_decide_reports_the_compiled_call_and_its_entry_floor(cfg):
    """``decide``: the compiled per-tick rule of each law timed closed loop, warm and paced,
    with the entry floor (an empty Python call, a no-op compiled call with the rule's arguments)
    paced the same way, its code size and its working set."""
    out = bench_solver(cfg, updates=24, sweep=())
    for law in ("rhc", "ioc"):
        d = out["decide"][law]
        for key in ("closed_loop_us", "warm_us", "paced_us"):
            assert all(math.isfinite(v) and v > 0 for v in d[key].values())
        floor = d["paced_floor_us"]
        assert floor["period_s"] == d["paced_us"]["period_s"] == 1.0 / cfg.rates.control_hz
        for key in ("python_call", "compiled_entry"):
            assert set(floor[key]) == {"median", "p99", "max"} and floor[key]["median"] > 0
        ws = d["working_set_bytes"]
        assert ws["total"] == sum(v for k, v in ws.items() if k != "total") > 0


def test_the_reference_benchmark_times_both_solvers(cfg):
    out = bench_reference(cfg, updates=6, reference_updates=3)
    json.dumps(out)
    assert out["compiled"]["updates"] == 6 and out["numpy_reference"]["updates"] == 3
    assert out["ratio"] > 0.0 and math.isfinite(out["ratio"])
