"""Smoke test of the solver benchmark's JSON shape (timings are never asserted)."""

from __future__ import annotations

import json

from rt_controller.rig.bench_solver import bench_solver


def test_bench_solver_reports_the_documented_keys(cfg):
    out = bench_solver(cfg, updates=12, reference_updates=3, sweep=(5,))
    json.dumps(out)  # JSON-ready
    assert out["N"] == cfg.rhc.steps and out["kmax"] == cfg.rhc.kmax and out["updates"] == 12
    assert set(out["solve_us"]) == {"median", "p99", "max"}
    assert out["residual_median"] < 1e-3 and out["fallbacks"] == 0
    ref = out["numpy_reference"]
    assert ref["updates"] == 3 and ref["ratio"] > 1.0
    assert set(ref["solve_us"]) == {"median", "p99"}
    assert [s["N"] for s in out["sweep"]] == [5]
    assert set(out["machine"]["load"]) == {"1min", "5min", "15min"}
