"""``hil experiment``: a failed run's J stays out of every aggregate (Table I's averages, the
claims), and a CAN bus that cannot be opened is refused before any run."""

from __future__ import annotations

from pathlib import Path

from hal.strict_json import finite
from rt_controller.cli import main
from rt_controller.rig import experiment as ex
from rt_controller.rig.experiment_markdown import render_report
from rt_controller.rig.experiment_results import build_results
from rt_controller.rig.failures import RigProcessError

NOT_CLEAN = "run not clean: the DSP advanced 1 lockstep period(s) with the held torque"


def finished(out: Path, which: tuple[str, ...], failed: str, **kw) -> tuple[dict, dict]:
    """Planned runs of ``which``, all ended ok with J = 10, 11, ... except ``failed``, which
    has J = 100 (and a steady J) but failed as not clean; and the results built of them."""
    settings = ex.Settings(experiments=which, out=out, **kw)
    runs_by_exp, runs = ex.prepare(settings)
    for i, run in enumerate(runs.values()):
        run.status, run.summary, run.J_steady = "ok", {"J": 10.0 + i}, 1.0 + i
    bad = runs[failed]
    bad.status, bad.error, bad.summary["J"], bad.J_steady = "failed", NOT_CLEAN, 100.0, 50.0
    res = finite(build_results(settings, runs_by_exp, runs, "hil experiment"))
    return res, runs


def test_a_failed_runs_j_is_not_averaged_into_table1(tmp_path):
    """Seed 1 of T = 0.1 s failed with a J: the row averages its other run and says so."""
    res, _ = finished(tmp_path, ("table1",), "rhc-T0.1-seed1", reps=2)
    rows = {r["horizon_s"]: r for r in res["table1"]["rows"]}
    assert rows[0.1]["J"] == [12.0, None] and rows[0.1]["J_sorted"] == [12.0]
    assert (rows[0.1]["average"], rows[0.1]["average_count"]) == (12.0, 1)
    assert (rows[0.02]["average"], rows[0.02]["average_count"]) == (10.5, 2)
    assert rows[0.1]["J_steady"] == [3.0, None]
    lines = res["table1"]["markdown"].splitlines()
    assert lines[3] == "| T = 0.1 s | 12.000 | — | 12.000 (1 of 2) |"
    assert lines[2] == "| T = 0.02 s | 10.000 | 11.000 | 10.500 |"
    # no claim rests on a row that lost a run
    assert not [c for c in res["claims"] if c["claim"].startswith("Table I")]
    report = render_report(res)
    table = report[report.index("## Table I") : report.index("The paper's Table I")]
    assert "100.000" not in table and "12.000 (1 of 2)" in table
    assert "`rhc-T0.1-seed1`" in table  # named as left out of the averages
    assert "| `rhc-T0.1-seed1` |" in report and "| failed |" in report  # still in the Runs


def test_a_failed_runs_j_is_not_in_the_figures_tables_nor_their_claims(tmp_path):
    """fig4's T = 1.0 s run failed with the largest J: no claim is checked on it."""
    res, _ = finished(tmp_path, ("fig4",), "rhc-T1.0")
    assert res["fig4"]["J"] == {"0.02": 10.0, "0.1": 11.0, "1.0": None}
    assert res["fig4"]["J_steady"] == {"0.02": 1.0, "0.1": 2.0, "1.0": None}
    assert res["claims"] == []
    assert "| T = 1.0 s | 20 | — | — |" in render_report(res)


def test_a_bus_that_cannot_be_opened_is_refused_before_any_run(tmp_path, monkeypatch, capsys):
    """--can on an interface that does not exist (or a kernel without SocketCAN): the line
    its emulator would print, exit status 2, no run started, no output folder."""
    started = []
    monkeypatch.setattr(ex, "run_rig", lambda opts: started.append(opts.law))
    out = tmp_path / "exp"
    argv = ["experiment", "fig3", "--can", "socketcan:hilnosuch0", "--duration", "0.5"]
    assert main([*argv, "--out", str(out), "--fresh-processes"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hil experiment: error: cannot open CAN interface socketcan:hilnosuch0")
    assert len(err.strip().splitlines()) == 1, err
    assert started == [] and not out.exists()


def test_giving_up_names_the_experiment(tmp_path, monkeypatch, capsys):
    def broken(opts):
        raise RigProcessError("controller exited with status 3:\nboom")

    monkeypatch.setattr(ex, "run_rig", broken)
    argv = ["experiment", "fig3", "--duration", "1", "--out", str(tmp_path / "exp")]
    assert main([*argv, "--fresh-processes", "--jobs", "1"]) == 1
    err = capsys.readouterr().err
    assert "3 failures in a row: giving up on hil experiment fig3" in err, err
    assert "sweep" not in err
