"""Camera outages: stretches of ticks on stale or invalid features, found tick by tick
(``RunCounters.outages``) and from a log's columns (``find_outages``), named as warnings and
judged against ``controller.outage_max_share``."""

from __future__ import annotations

import numpy as np
import pytest

from hal.config import RigConfig, load_config
from hal.errors import HalConfigError
from rt_controller.runtime.counters import (
    OUTAGES_LISTED,
    OutageTracker,
    find_outages,
    run_problems,
    run_warnings,
)

PERIOD = 0.02


def tracked(flags: list[bool], warn: int = 5, share: float = 0.25) -> dict:
    """The outages block of ticks 0.. at 50 Hz with these flags, fed tick by tick."""
    tracker = OutageTracker(warn, share)
    for k, bad in enumerate(flags):
        tracker.note(k, k * PERIOD, bad)
    return tracker.as_dict(PERIOD)


def test_a_stretch_longer_than_the_threshold_is_an_outage_with_its_start_and_length():
    flags = [False] * 10 + [True] * 6 + [False] * 4 + [True] * 5 + [False] * 3
    out = tracked(flags)
    assert out["count"] == 1  # 6 > 5 is an outage; 5 is not
    (o,) = out["listed"]
    assert o["start_tick"] == 10 and o["ticks"] == 6
    assert o["start_s"] == pytest.approx(0.2) and o["s"] == pytest.approx(0.12)
    assert out["longest"] == o and out["longest_ticks"] == 6
    assert out["ticks_on_stale_or_invalid"] == 11
    assert out["share"] == pytest.approx(11 / 28)


def test_a_stretch_running_at_the_end_counts():
    out = tracked([False] * 3 + [True] * 8)
    assert out["count"] == 1 and out["listed"][0]["start_tick"] == 3
    assert out["listed"][0]["ticks"] == 8


def test_the_longest_is_marked_among_several():
    flags = [True] * 7 + [False] + [True] * 12 + [False] + [True] * 9 + [False]
    out = tracked(flags)
    assert out["count"] == 3 and out["longest"]["start_tick"] == 8
    warnings = run_warnings({"clock": "lockstep", "outages": out})
    assert len(warnings) == 3
    assert [("(the longest)" in w) for w in warnings] == [False, True, False]
    assert "from tick 8 (t = 0.160 s): 12 ticks (0.24 s)" in warnings[1]


def test_no_bad_tick_no_outage_no_warning():
    out = tracked([False] * 50)
    assert out["count"] == 0 and out["longest"] is None and out["share"] == 0.0
    assert run_warnings({"clock": "realtime", "outages": out}) == []
    assert run_problems({"ticks": 50, "outages": out}) == []


def test_only_so_many_are_named_the_rest_counted():
    flags = ([True] * 6 + [False]) * (OUTAGES_LISTED + 3)
    out = tracked(flags, share=1.0)
    assert out["count"] == OUTAGES_LISTED + 3 and len(out["listed"]) == OUTAGES_LISTED
    warnings = run_warnings({"clock": "realtime", "outages": out})
    assert len(warnings) == OUTAGES_LISTED + 1 and "3 more camera outage(s)" in warnings[-1]


def test_past_the_share_the_run_is_not_clean():
    flags = [False] * 70 + [True] * 30
    clean = tracked(flags, share=0.3)
    assert run_problems({"ticks": 100, "outages": clean}) == []  # 30 % is not past 30 %
    dirty = tracked(flags, share=0.29)
    (problem,) = run_problems({"ticks": 100, "outages": dirty})
    assert "30 tick(s) (30% of the run)" in problem and "from tick 70" in problem


def test_the_log_columns_give_the_same_block_as_the_loop():
    rng = np.random.default_rng(7)
    bad = rng.random(400) < 0.1
    bad[100:140] = True
    ticks = np.arange(400)
    offline = find_outages(ticks, ticks * PERIOD, bad, 5, 0.25, PERIOD)
    assert offline == tracked(list(bad))
    assert offline["longest"]["start_tick"] <= 100 and offline["longest_ticks"] >= 40


def test_the_thresholds_are_config_keys():
    cfg = RigConfig()
    tracker = OutageTracker.from_config(cfg.controller)
    assert (tracker.warn_periods, tracker.max_share) == (5, 0.25)
    with pytest.raises(HalConfigError, match=r"controller\.outage_max_share"):
        cfg.with_overrides({"controller.outage_max_share": 1.5})
    with pytest.raises(HalConfigError, match=r"controller\.outage_warn_periods"):
        cfg.with_overrides({"controller.outage_warn_periods": -1})
    assert load_config(None).controller.outage_warn_periods == 5
