"""``hil bench loop``'s lockstep profile: where a period's wall time goes, from cycle records."""

from __future__ import annotations

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
        "period": 1000.0,
        "period_p99": 1000.0,
        "features_wait": 300.0,
        "solve": 100.0,
        "write": 50.0,
        "dsp_and_can": 550.0,
    }
    assert prof["features_wait"] + prof["solve"] + prof["write"] + prof[
        "dsp_and_can"
    ] == pytest.approx(prof["period"])


def test_lockstep_period_profile_of_a_single_tick_is_empty() -> None:
    one = {k: np.zeros(1) for k in ("t_ns", "read_us", "solve_us", "write_us", "cycle_us")}
    assert lockstep_period_profile(one) == {}
