"""``hil experiment``'s report: a Table I row's spread (max - min) is over at least two runs
that ended ok; a row with one such run has no spread ("—"), not 0, in the run-order table and
in the note comparing the repetitions' spread with the paper's."""

from __future__ import annotations

from pathlib import Path

from hal.strict_json import finite
from rt_controller.rig import experiment as ex
from rt_controller.rig.experiment_markdown import render_report
from rt_controller.rig.experiment_results import build_results


def table1(out: Path, reps: int, failed: tuple[str, ...]) -> dict:
    """The results of a Table I sweep whose runs all ended ok with J = 10, 11, ... except
    ``failed``, which ended as failed (with a J that must enter nothing)."""
    settings = ex.Settings(experiments=("table1",), out=out, reps=reps)
    runs_by_exp, runs = ex.prepare(settings)
    for i, run in enumerate(runs.values()):
        run.status, run.summary, run.J_steady = "ok", {"J": 10.0 + i}, 1.0 + i
    for name in failed:
        runs[name].status, runs[name].error = "failed", "run not clean"
    return finite(build_results(settings, runs_by_exp, runs, "hil experiment"))


def run_order_rows(report: str) -> dict[str, str]:
    """The run-order table's spread cell per horizon (``"0.1"`` -> ``"—"``)."""
    start = report.index("The same values in run order")
    lines = report[start:].split("\n\n")[1].splitlines()[2:]
    return {
        line.split(" s |")[0].removeprefix("| T = "): line.split(" | ")[-1][:-2] for line in lines
    }


def test_a_row_with_one_ok_run_has_no_spread(tmp_path):
    """T = 0.1 s: seed 1 failed, seed 0 (J = 12) is the row's only run: no spread."""
    res = table1(tmp_path, 2, ("rhc-T0.1-seed1",))
    report = render_report(res)
    assert run_order_rows(report) == {"0.02": "1.0000", "0.1": "—", "1.0": "1.0000"}
    note = report[report.index("**Repetitions.**") :].split("\n")[0]
    assert "T = 0.1 s: 0.00 %" not in note and "T = 0.02 s: 9.52 %" in note, note
    row = {r["horizon_s"]: r for r in res["table1"]["rows"]}[0.1]
    assert not {"spread", "min", "max"} & set(row)  # results.json carries no spread to null


def test_a_spread_over_fewer_runs_than_the_row_says_how_many(tmp_path):
    """T = 1.0 s: one of three failed: the spread of the other two says (2 of 3), as the
    average does; a row with none ok still shows "—"."""
    failed = ("rhc-T1.0-seed2", *(f"rhc-T0.1-seed{i}" for i in range(3)))
    report = render_report(table1(tmp_path, 3, failed))
    assert run_order_rows(report) == {"0.02": "2.0000", "0.1": "—", "1.0": "1.0000 (2 of 3)"}
