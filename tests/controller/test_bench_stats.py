"""The benches' figures go through the one percentile helper (``rt_controller.sample_stats``):
statistics of the finite samples, NaN when there are none, never an exception, and the same
JSON keys as ever."""

from __future__ import annotations

import math

import numpy as np

from rt_controller.rig.bench_loop import lockstep_period_profile
from rt_controller.rig.bench_tuning import tuning_figures


def test_a_period_profile_ignores_samples_that_are_not_finite() -> None:
    nan = float("nan")
    cycles = {
        "t_ns": np.array([0, 1_000_000, 2_000_000, 3_000_000], dtype=np.int64),
        "read_us": np.array([300.0, nan, 300.0, 300.0]),
        "solve_us": np.array([100.0, 100.0, np.inf, 100.0]),
        "write_us": np.full(4, 50.0),
        "cycle_us": np.array([450.0, nan, 450.0, 450.0]),
    }
    assert lockstep_period_profile(cycles) == {
        "period_median": 1000.0,
        "period_p99": 1000.0,
        "features_wait": 300.0,
        "solve": 100.0,
        "write": 50.0,
        "dsp_and_can": 550.0,
    }


def test_tuning_figures_of_requests_and_a_law_switch() -> None:
    ticks = np.arange(10)
    solve = np.array([10.0] * 10)
    solve[[4, 7]] = (90.0, 80.0)
    out = tuning_figures([10_000_000, 20_000_000, 30_000_000], [4, 7], ticks, solve, 0.02)
    assert out["requests"] == 3
    assert set(out["request_to_effect_ms"]) == {"median", "p99", "max"}
    assert out["request_to_effect_ms"]["median"] == 20.0
    assert out["request_to_effect_ms"]["max"] == 30.0
    assert out["request_to_effect_periods"]["median"] == 1.0
    assert out["within_two_periods"] is True
    assert out["law_switch"] == {
        "ticks": [4, 7],
        "decide_us_at_switch": [90.0, 80.0],
        "decide_us_ordinary": {"median": 10.0, "p99": 10.0},
    }


def test_tuning_figures_without_requests_are_nan_not_an_error() -> None:
    """A run whose every request failed still gives its figures (NaN, not within two periods)."""
    out = tuning_figures([], [], np.arange(3), np.array([10.0, float("nan"), 12.0]), 0.02)
    assert out["requests"] == 0
    assert all(math.isnan(v) for v in out["request_to_effect_ms"].values())
    assert out["within_two_periods"] is False
    assert out["law_switch"]["decide_us_ordinary"] == {"median": 11.0, "p99": 11.98}
