"""``hil experiment`` off the happy path: a --duration of no tick, a run that reports no
finite J, a stop signal while the results are written, and --json when interrupted.

The rigs are fakes (``run_rig`` replaced): no process is started.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

from rt_controller.cli import main
from rt_controller.rig import experiment as ex
from rt_controller.rig import experiment_report as report

NO_LOG = {"log_contents": {"error": "a fake run writes no log"}}


def argv(out: Path, *extra: str) -> list[str]:
    return ["experiment", "fig3", "--out", str(out), "--fresh-processes", "--jobs", "1", *extra]


def test_a_duration_shorter_than_one_control_period_is_refused(tmp_path, monkeypatch, capsys):
    """``--duration 0.001`` ran three rigs of no tick, then a traceback (a division by J = 0 in
    the claims); ``hil up`` refuses it: so does the experiment, before any run or folder."""
    started: list[str] = []
    monkeypatch.setattr(ex, "run_rig", lambda opts: started.append(opts.law) or {})
    out = tmp_path / "exp"
    assert main(argv(out, "--duration", "0.001")) == 2
    err = capsys.readouterr().err
    assert err.startswith("hil experiment: error: --duration 0.001 s is shorter than one"), err
    assert len(err.strip().splitlines()) == 1, err
    assert started == [] and not out.exists()


def test_a_run_without_a_finite_j_fails_and_is_said(tmp_path, monkeypatch, capsys):
    """A run whose summary has no finite J was 'ok' and its line a TypeError traceback."""
    monkeypatch.setattr(ex, "run_rig", lambda opts: {"J": float("nan"), "problems": [], **NO_LOG})
    out = tmp_path / "exp"
    assert main(argv(out, "--duration", "1", "--json")) == 1
    captured = capsys.readouterr()
    assert "run ioc (IOC) failed: the controller reported no finite J" in captured.err
    res = json.loads(captured.out)
    assert [r["status"] for r in res["runs"]] == ["failed"] * 3


def test_a_stop_signal_while_the_results_are_written_keeps_them(tmp_path, monkeypatch, capsys):
    """A Ctrl-C while the figures were drawn (after every run) cut the write-up short: no
    results.json, no report.md, status 130 without a word. The write-up now ends first."""
    fake = {"J": 1.0, "problems": ["a fake run"], **NO_LOG}  # failed: no figure drawn of it
    monkeypatch.setattr(ex, "run_rig", lambda opts: fake)
    draw = report.write_figures

    def interrupted_while_drawing(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return draw(*args, **kwargs)

    monkeypatch.setattr(report, "write_figures", interrupted_while_drawing)
    out = tmp_path / "exp"
    assert main(argv(out, "--duration", "1")) == 128 + signal.SIGINT
    err = capsys.readouterr().err
    assert f"hil experiment: interrupted by SIGINT: partial results in {out}" in err, err
    res = json.loads((out / "results.json").read_text())
    assert [r["error"] for r in res["runs"]] == ["run not clean: a fake run"] * 3
    assert (out / "report.md").is_file()


def test_json_when_interrupted_prints_the_partial_results(tmp_path, monkeypatch, capsys):
    """``--json`` printed nothing on stdout when the experiment was stopped by a signal (a
    reader got no JSON); it prints the partial results, as ``hil up --json`` its summary."""
    from rt_controller.rig.failures import RigCancelled

    def stopped(opts):
        os.kill(os.getpid(), signal.SIGTERM)  # the user stops the experiment
        if not opts.cancel.wait(30):
            raise AssertionError("never cancelled")
        raise RigCancelled("cancelled")

    monkeypatch.setattr(ex, "run_rig", stopped)
    out = tmp_path / "exp"
    assert main(argv(out, "--duration", "1", "--json")) == 128 + signal.SIGTERM
    captured = capsys.readouterr()
    res = json.loads(captured.out)
    assert [r["status"] for r in res["runs"]] == ["pending"] * 3
    assert res == json.loads((out / "results.json").read_text())
    assert "interrupted by SIGTERM" in captured.err


def test_reps_for_an_experiment_without_repetitions_is_refused(tmp_path, monkeypatch, capsys):
    """``fig4 --reps 10`` ran fig4 once, the --reps dropped without a word."""
    started: list[str] = []
    monkeypatch.setattr(ex, "run_rig", lambda opts: started.append(opts.law) or {})
    out = tmp_path / "exp"
    for which in ("fig3", "fig4"):
        argv = ["experiment", which, "--reps", "10", "--duration", "1", "--out", str(out)]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err == f"hil experiment: error: --reps: {which} has no repetitions (table1 has)\n"
    assert started == [] and not out.exists()


def test_a_full_disk_leaves_no_half_results_file(tmp_path, monkeypatch, capsys):
    """The disk filling up while results.json was written left half a JSON file in place of
    the one there (``--force``); now no half file is left (``--force`` removed the earlier one
    before the runs) and the error names it."""
    import errno

    fake = {"J": 1.0, "problems": ["a fake run"], **NO_LOG}
    monkeypatch.setattr(ex, "run_rig", lambda opts: fake)
    out = tmp_path / "exp"
    out.mkdir()
    (out / "results.json").write_text('{"an": "earlier experiment"}\n')
    write_text = Path.write_text

    def full_disk(self: Path, data: str, *args, **kwargs) -> int:
        if "results.json" in self.name:
            write_text(self, data[:100], *args, **kwargs)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return write_text(self, data, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full_disk)
    assert main([*argv(out, "--duration", "1"), "--force"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"hil experiment: error: {out / 'results.json'}: No space left on device"
    assert not (out / "results.json").exists()  # --force removed the earlier one; no half
    assert [p.name for p in out.iterdir() if p.name.endswith(".partial")] == []


def test_a_stopped_plan_keeps_the_runs_that_ended_before(tmp_path, monkeypatch):
    """Ctrl-C during a plan (runs sharing one set of processes) recorded every run of it as
    not run, also those that had ended: a table1 stopped in its last run lost all its J. The
    plan's runner hands the summaries of the ended runs with :class:`RigCancelled`."""
    from rt_controller.rig.failures import RigCancelled

    def stopped(opts, n):
        first = json.loads(opts.plan.read_text())["runs"][0]["name"]
        exc = RigCancelled("cancelled")
        exc.summaries = [{"run": first, "J": 2.0, "wall_s": 0.5, "problems": []}]
        raise exc

    monkeypatch.setattr(ex, "run_rig_plan", stopped)
    monkeypatch.setattr(ex, "steady_cost", lambda log: None)
    st = ex.Settings(experiments=("fig4",), out=tmp_path, jobs=1)
    _, runs = ex.prepare(st)
    batch = ex.execute_batch(list(runs.values()), st)
    assert [r.status for r in batch] == ["ok", "pending", "pending"]
    assert batch[0].J == 2.0 and batch[0].wall_s is not None
    assert all(r.error is None and r.J is None for r in batch[1:])
