"""hil report / hil info on a log whose parameter-change and operator-event records are not
whole (the recorder takes any JSON object: a hand-made or older log): what is missing is shown
empty, never a traceback."""

from __future__ import annotations

import json

import pytest

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.runtime.recorder import CycleRecorder

T0 = 10**9


def _log(path):
    rec = CycleRecorder(path, RigConfig())
    for k in range(5):
        rec.record_cycle({"tick": k, "t_ns": T0 + k * 20_000_000, "sim_time_s": k * 0.02,
                          "cycle_us": 100.0})  # fmt: skip
    t = T0 + 40_000_000
    rec.record_parameters({"tick": 2, "t_ns": t, "accepted": True, "changes": [{"key": "k"}]})
    rec.record_parameters({"tick": None, "t_ns": t, "accepted": False, "changes": "x"})
    rec.record_parameters({"tick": 3, "t_ns": t, "accepted": True, "changes": [7, None]})
    rec.record_event({"tick": "2", "t_ns": t, "action": None, "accepted": True, "source": None})
    rec.close()
    return path


@pytest.mark.parametrize("extra", [[], ["--json"], ["--plot", "FIGS"]])
def test_report_of_odd_change_records(tmp_path, capsys, extra):
    log = _log(tmp_path / "run.mcap")
    extra = [str(tmp_path / "figs") if a == "FIGS" else a for a in extra]
    assert main(["report", "-q", *extra, str(log)]) == 0
    out, err = capsys.readouterr()
    assert "Traceback" not in err and err == ""
    if "--json" in extra:
        rep = json.loads(out)
        assert [c["tick"] for c in rep["parameter_changes"]] == [2, None, 3]
        assert rep["parameter_changes"][0]["changes"] == "k ? -> ?"


def test_info_of_odd_change_records(tmp_path, capsys):
    log = _log(tmp_path / "run.mcap")
    assert main(["info", "--json", str(log)]) == 0
    assert json.loads(capsys.readouterr().out)["ticks"] == 5
