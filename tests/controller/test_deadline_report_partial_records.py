"""hil report / hil info on a log whose cycle records do not all carry every field (an older
writer, a hand-made or edited log): a field a record lacks is unknown for that tick, not a
deadline miss or a stale tick, and never a traceback."""

from __future__ import annotations

import json

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.runtime.recorder import CycleRecorder


def _log(path, drop: dict[int, tuple[str, ...]]):
    rec = CycleRecorder(path, RigConfig())
    for k in range(10):
        r = {
            "tick": k, "t_ns": 10**9 + k * 20_000_000, "sim_time_s": k * 0.02,
            "cycle_us": 100.0, "lateness_us": 1.0, "deadline_miss": k == 7,
            "missed_periods": 1 if k == 7 else 0, "f_stale": False, "f_valid": True,
        }  # fmt: skip
        for key in drop.get(k, ()):
            del r[key]
        rec.record_cycle(r)
    rec.close()
    return path


def test_a_record_without_missed_periods_on_a_miss_is_reported(tmp_path, capsys):
    log = _log(tmp_path / "a.mcap", {7: ("missed_periods",), 3: ("missed_periods",)})
    assert main(["report", "-q", "--json", str(log)]) == 0
    out, err = capsys.readouterr()
    rep = json.loads(out)
    assert rep["deadline_misses"] == 1
    assert rep["misses"][0]["tick"] == 7 and rep["misses"][0]["missed_periods"] is None
    assert rep["missed_periods"] == 0  # the records that say
    assert "Traceback" not in err


def test_info_of_such_a_log_is_no_traceback(tmp_path, capsys):
    log = _log(tmp_path / "a.mcap", {3: ("missed_periods",)})
    assert main(["info", "--json", str(log)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["deadline_misses"] == 1 and info["missed_periods"] == 1


def test_a_record_without_the_flags_is_no_miss_and_no_stale_tick(tmp_path, capsys):
    log = _log(tmp_path / "b.mcap", {2: ("deadline_miss", "f_stale", "f_valid")})
    assert main(["report", "-q", "--json", str(log)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["deadline_misses"] == 1
    assert [m["tick"] for m in rep["misses"]] == [7]
    assert rep["outages"]["ticks_on_stale_or_invalid"] == 0


def _odd_log(path, more):
    """Five hand-edited cycle records: text for tick 1's cycle time and miss flag, and
    ``more(k)``'s fields."""
    rec = CycleRecorder(path, RigConfig())
    for k in range(5):
        rec.record_cycle(
            {"tick": k, "t_ns": 10**9 + k * 20_000_000, "sim_time_s": k * 0.02,
             "cycle_us": "slow" if k == 1 else 100.0,
             "deadline_miss": "yes" if k == 1 else k == 3, **more(k)}
        )  # fmt: skip
    rec.close()
    return path


def test_values_of_the_wrong_type_are_unknown_not_a_traceback(tmp_path, capsys):
    """Text where a number or flag belongs (a hand-edited log) is an unknown value."""
    path = _odd_log(
        tmp_path / "c.mcap",
        lambda k: {"lateness_us": 1.0, "missed_periods": "x" if k == 2 else 0,
                   "f_valid": "no" if k == 4 else True},
    )  # fmt: skip
    assert main(["report", "-q", "--json", str(path)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert [m["tick"] for m in rep["misses"]] == [3]
    assert rep["missed_periods"] == 0
    assert rep["cycle_us"]["max"] == 100.0
    assert main(["info", str(path)]) == 0


def test_plots_of_values_of_the_wrong_type_are_drawn_with_gaps(tmp_path, capsys):
    path = _odd_log(
        tmp_path / "d.mcap",
        lambda k: {"lateness_us": "late" if k == 0 else 1.0, "solve_us": "a" if k == 2 else 3.0,
                   "residual": "r" if k == 2 else 0.0},
    )  # fmt: skip
    figs = tmp_path / "figs"
    assert main(["report", "-q", "--plot", str(figs), str(path)]) == 0
    names = {p.name for p in figs.glob("*.png")}
    assert {"d_cycle_time.png", "d_solve_time.png", "d_lateness_hist.png"} <= names
