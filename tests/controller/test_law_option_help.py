"""The law options' help names the config key each one overrides and says the config's value is
the default (a --config file sets it), not a bare number that a file may have changed."""

from __future__ import annotations

import pytest

from rt_controller.cli import main

KEYS = {
    "--rate": "rates.control_hz",
    "--horizon": "rhc.horizon",
    "--steps": "rhc.steps",
    "--kmax": "rhc.kmax",
    "--zeta": "rhc.zeta",
}


@pytest.mark.parametrize("command", ["simulate", "controller", "up"])
def test_each_law_option_names_its_key(command: str, capsys) -> None:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for option, key in KEYS.items():
        at = text.index(f"{option} ", text.index("options:"))
        assert f"({key}; default: the config's, embedded " in text[at : at + 200], option
