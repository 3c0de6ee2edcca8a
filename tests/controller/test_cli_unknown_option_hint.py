"""An option the command does not have: the error names what it calls that option where it
has one. The clock is ``--clock lockstep`` on ``hil controller`` and ``hil vision`` but
``--lockstep`` on ``hil emulator`` and ``hil up``, and a near miss is a typo."""

from __future__ import annotations

import pytest

from rt_controller.cli import main


def error_of(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize(
    ("argv", "hint"),
    [
        (["controller", "--lockstep"], "--clock lockstep"),
        (["vision", "--lockstep"], "--clock lockstep"),
        (["emulator", "--clock", "lockstep"], "--lockstep"),
        (["up", "--clock=lockstep"], "--lockstep"),
        (["simulate", "--horizn", "1"], "--horizon"),
        (["up", "--durations", "3", "--lockstp"], "--duration, --lockstep"),
    ],
)
def test_another_command_s_spelling_or_a_typo_is_named(argv, hint, capsys):
    line = error_of(argv, capsys)
    assert line.endswith(f"(did you mean {hint}?)"), line
    assert f"unrecognized arguments: {' '.join(argv[1:])}" in line, line


def test_an_option_like_no_other_gets_argparse_s_words_alone(capsys):
    line = error_of(["controller", "--foo"], capsys)
    assert line == "hil controller: error: unrecognized arguments: --foo", line
