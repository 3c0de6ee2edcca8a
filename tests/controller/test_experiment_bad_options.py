"""``hil experiment`` with a bad option: one line, status 2, and no output folder left behind
(every option, the config and the ``--scheduler`` are checked before the folder is made)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rt_controller.cli import main


@pytest.mark.parametrize(
    ("options", "said"),
    [
        (["--scheduler", "bogus"], "--scheduler bogus: cannot connect"),
        (["--noise", "0.5"], "--noise: camera.noise_px = 0.5 is the analytic camera's"),
        (["--config", "missing.toml"], "cannot read config file missing.toml"),
        (["--config", "bad.toml"], "bad.toml: camera.width_px: -640 is out of range"),
    ],
)
def test_a_bad_option_leaves_no_output_folder(tmp_path, monkeypatch, capsys, options, said):
    monkeypatch.chdir(tmp_path)
    Path("bad.toml").write_text("[camera]\nwidth_px = -640\n")
    for out in ([], ["--out", "given"]):  # the default experiments/<timestamp>, and --out
        assert main(["experiment", "fig3", "--duration", "0.2", *options, *out]) == 2
        err = capsys.readouterr().err
        assert f"hil experiment: error: {said}" in err, err
        assert len(err.strip().splitlines()) == 1, err
        assert not Path("experiments").exists() and not Path("given").exists()


def test_the_j_table_does_not_call_a_run_that_never_ran_failed(capsys):
    """After a Ctrl-C the runs not run have no J; the table says so without a verdict (the
    report's status column tells failed from not run)."""
    from rt_controller.commands.experiment import print_tables

    print_tables({"fig3": {"J": {"ioc": 23.9, "rhc": None}}, "report": "report.md"})
    out = capsys.readouterr().out
    assert "23.9000" in out and "failed" not in out and "—" in out


def test_an_out_holding_an_experiment_is_refused_unless_force(tmp_path, monkeypatch, capsys):
    """A second ``hil experiment --out DIR`` replaced the first one's logs without a word."""
    monkeypatch.chdir(tmp_path)
    logs = Path("today", "logs")
    logs.mkdir(parents=True)
    (logs / "ioc.mcap").write_bytes(b"a run's log")
    argv = ["experiment", "fig3", "--duration", "0.2", "--out", "today", "--config", "none.toml"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "hil experiment: error: --out today: holds an experiment already (logs)" in err, err
    assert "--force" in err and (logs / "ioc.mcap").read_bytes() == b"a run's log"
    assert main([*argv, "--force"]) == 2  # on to the next check: the missing config
    assert "cannot read config file none.toml" in capsys.readouterr().err
    Path("empty").mkdir()  # a folder made beforehand, still empty: that is no experiment
    assert main([*argv[:-4], "--out", "empty", "--config", "none.toml"]) == 2
    assert "cannot read config file none.toml" in capsys.readouterr().err
