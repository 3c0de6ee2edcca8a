"""``hil export`` off its happy path: odd ``--out`` spellings."""

from __future__ import annotations

from pathlib import Path

import pytest

from hal.config import RigConfig
from rt_controller.cli import main
from tests.controller.test_replay import record_run


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    return record_run(tmp_path_factory.mktemp("walk-export") / "run.mcap", RigConfig(), 30)


@pytest.mark.parametrize("fmt", ["csv", "mat"])
def test_an_out_with_a_trailing_slash_is_a_folder(log, tmp_path, capsys, fmt):
    """``--out x.csv/`` says folder: the tables go in it, not a refusal telling to give a
    folder or a name ending in .csv (which it is both)."""
    folder = tmp_path / f"x.{fmt}"
    assert main(["export", str(log), "--format", fmt, "--out", f"{folder}/"]) == 0, (
        capsys.readouterr().err
    )
    assert folder.is_dir() and any(folder.iterdir())


def test_canopen_of_a_log_without_that_topic_says_why_it_is_empty(log, tmp_path, capsys):
    """``--topics canopen`` on a dsp-profile log writes an empty table: a note says the log
    has no /hal/canopen messages (only a cia402 run records them), not a bare "0 rows"."""
    assert (
        main(["export", str(log), "--format", "csv", "--topics", "canopen", "--out", str(tmp_path)])
        == 0
    )
    out = capsys.readouterr().out
    assert "canopen: 0 rows" in out and "note:" in out and "/hal/canopen" in out, out


def test_export_of_a_lossy_recovered_copy_says_what_it_lost(log, tmp_path, capsys):
    """The copy `hil recover` made of a cut log holds only the ticks before the cut: the
    export notes it (as it notes a cut log's own damage), not a clean-looking table."""
    from rt_controller.logtools.recover import recover

    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    copy = tmp_path / "copy.mcap"
    recover(cut, copy)
    argv = ["export", str(copy), "--format", "csv", "--topics", "cycle", "--out", str(tmp_path)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "note:" in out and "hil recover" in out and str(cut) in out, out


@pytest.mark.parametrize(
    ("name", "argv"),
    [
        ("run.mat", ["--format", "mat"]),  # the default LOGSTEM.mat beside it is the log
        ("run.csv", ["--format", "csv", "--topics", "cycle", "--out", "{log}"]),
    ],
)
def test_export_never_overwrites_its_log(log, tmp_path, capsys, name, argv):
    src = tmp_path / name
    src.write_bytes(log.read_bytes())
    argv = [a.replace("{log}", str(src)) for a in argv]
    assert main(["export", str(src), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(src) in err and "the log" in err, err
    assert src.read_bytes() == log.read_bytes()
