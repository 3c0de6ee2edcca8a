"""``hil bench soak`` end to end, briefly: the JSON's structure and its agreement with the log
it kept. Timings and sizes are figures, never asserted."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from rt_controller.logtools.reader import read_log

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ROLES = {"controller", "emulator", "vision", "recorder"}


def test_a_short_soak_reports_every_series(tmp_path: Path) -> None:
    hil = Path(sys.executable).parent / "hil"
    argv = ["bench", "soak", "--duration", "5", "--sample", "1", "--warmup", "1"]
    done = subprocess.run(
        [str(hil), *argv, "--keep", str(tmp_path), "--json", "-q"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode in (0, 1), done.stderr  # 1: a run not clean on a loaded host
    assert "Traceback" not in done.stderr
    out = json.loads(done.stdout)
    assert out["duration_s"] == 5.0 and out["sample_s"] == 1.0 and out["law"] == "rhc"
    assert ROLES <= set(out["rss_mb"]) == set(out["rss_growth"]) == set(out["peak_rss_mb"])
    for role, series in out["rss_mb"].items():
        times = [t for t, _ in series]
        assert times == sorted(times) and all(mb > 0 for _, mb in series), role
        assert out["peak_rss_mb"][role] == max(mb for _, mb in series)
        assert set(out["rss_growth"][role]) == {"from_mb", "to_mb", "growth_mb", "slope_mb_per_h"}
    log = Path(out["log"])
    assert log.parent == tmp_path and out["log_bytes"] == log.stat().st_size
    assert out["log_size"][-1][1] == out["log_bytes"]
    loaded = read_log(log, raw=False)
    assert not loaded.truncated
    assert out["ticks"] == loaded.cycles["tick"].size > 0
    assert isinstance(out["deadline_misses"], int) and out["deadline_misses"] >= 0
    backlog = out["recorder_backlog"]
    assert backlog, "no periodic /diagnostics record"
    assert [b[0] for b in backlog] == sorted(b[0] for b in backlog)
    assert all(isinstance(p, int) and p >= 0 for _, p, _ in backlog)
    assert out["recorder_backlog_max"] == max(p for _, p, _ in backlog)
    assert out["recorder"]["dropped"] >= 0 and isinstance(out["problems"], list)
