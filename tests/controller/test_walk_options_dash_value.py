"""A value that begins with ``-`` (``hil vision --dropout -1:2``): argparse takes it for an
option and says the value is missing; the error says how to give it."""

from __future__ import annotations

import pytest

from rt_controller.cli import main


def error_of(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


def test_a_value_that_looks_like_an_option_is_told_how_to_give_it(capsys):
    line = error_of(["vision", "--dropout", "-1:2"], capsys)
    assert line.endswith("(a value that begins with '-' is written --dropout=VALUE)"), line


def test_a_value_left_out_gets_no_such_hint(capsys):
    line = error_of(["replay", "run.mcap", "--tol"], capsys)
    assert line == "hil replay: error: argument --tol: expected one argument", line
