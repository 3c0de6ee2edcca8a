"""hil info's text: the duration line names its time axis once, without a nested unit
("4.000 s (plant time)", not "4.000 s (plant time (s))")."""

from __future__ import annotations

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.runtime.recorder import CycleRecorder


def test_the_duration_line_reads_plainly(tmp_path, capsys):
    log = tmp_path / "run.mcap"
    rec = CycleRecorder(log, RigConfig())
    for k in range(5):
        rec.record_cycle({"tick": k, "t_ns": 10**9 + k * 20_000_000, "sim_time_s": k * 0.02})
    rec.close()
    assert main(["info", str(log)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("duration:")]
    assert lines and lines[0].split(None, 1)[1] == "0.100 s (plant time)"
