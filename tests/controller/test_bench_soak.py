"""``hil bench soak``'s figures from its series: RSS growth after the warm-up and the recorder's
backlog from the controller's ``/diagnostics`` records."""

from __future__ import annotations

import pytest

from rt_controller.rig.bench_soak import recorder_backlog, rss_growth


def test_rss_growth_starts_after_the_warmup_and_fits_the_slope() -> None:
    # 100 MB during the warm-up (compile), then 200 MB growing 1 MB per 10 s
    series = [(float(t), 100.0) for t in range(0, 60, 10)]
    series += [(float(t), 200.0 + (t - 60) / 10) for t in range(60, 181, 10)]
    g = rss_growth(series, warmup_s=60.0)
    assert g["from_mb"] == 200.0 and g["to_mb"] == 212.0
    assert g["growth_mb"] == pytest.approx(12.0)
    assert g["slope_mb_per_h"] == pytest.approx(360.0)


def test_rss_growth_needs_two_samples_after_the_warmup() -> None:
    g = rss_growth([(0.0, 1.0), (30.0, 2.0), (61.0, 3.0)], warmup_s=60.0)
    assert g == {"from_mb": None, "to_mb": None, "growth_mb": None, "slope_mb_per_h": None}


def _diag(t_s: float, backlog: int, final: bool = False, dropped: int = 0) -> dict:
    recorder = {"written": 1, "dropped": dropped, "pending": 0, "backlog_bytes": backlog}
    return {
        "t_ns": int(t_s * 1e9),
        "final": final,
        "status": [
            {"name": "controller", "values": {"ticks": 1}},
            {"name": "recorder", "values": recorder},
        ],
    }


def test_recorder_backlog_takes_the_periodic_records_on_the_soak_axis() -> None:
    diags = [_diag(101.0, 5), _diag(102.0, 9, dropped=2), _diag(103.0, 0, final=True)]
    diags.append({"t_ns": 1, "final": False, "status": []})  # no recorder status: skipped
    assert recorder_backlog(diags, t0_s=100.0) == [[1.0, 5, 0], [2.0, 9, 2]]
