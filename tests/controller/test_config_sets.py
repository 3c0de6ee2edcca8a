"""``--set KEY=VALUE``: any config key from the command line, by the rules of the named options.

The commands that run the rig (``hil up``, ``controller``, ``simulate``, ``bench``, ``cia402
check``, ``experiment``: tests/controller/test_experiment_sets.py) and ``hil replay`` take it;
``rt_controller.config_rules.apply_overrides`` is the one path, so ``--set
rates.control_hz=100`` moves the physics rate as ``--rate 100`` does.
"""

from __future__ import annotations

import json

import pytest

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.config_rules import apply_overrides, parse_sets
from rt_controller.errors import ControllerConfigError
from tests.support import error_line


def test_a_set_key_follows_the_rules_of_its_named_option():
    """A control rate the physics rate is no multiple of: --rate and --set move it alike."""
    by_option = apply_overrides(RigConfig(), rate=300.0)
    by_set = apply_overrides(RigConfig(), sets={"rates.control_hz": 300.0})
    assert by_set == by_option
    assert by_set.rates.physics_hz % 300.0 == 0 and by_set.rates.physics_hz != 1000.0


def test_a_set_of_a_key_without_an_option_is_applied_and_validated():
    cfg = apply_overrides(RigConfig(), sets=parse_sets(["camera.model=analytic", "gains.kp=0.3"]))
    assert (cfg.camera.model, cfg.gains.kp) == ("analytic", 0.3)
    with pytest.raises(Exception, match=r"camera.model \(--set\): must be image or analytic"):
        apply_overrides(RigConfig(), sets={"camera.model": "bogus"}, from_command_line=True)


def test_simulate_runs_on_the_set_keys(capsys):
    argv = ["simulate", "--duration", "0.2", "--json", "-q"]
    assert main([*argv, "--set", "rates.control_hz=100", "--set", "controller.law=pbc"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert (s["rate"], s["ticks"], s["law"]) == (100.0, 20, "pbc")


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--rate", "100", "--set", "rates.control_hz=50"], "--rate and --set rates.control_hz"),
        (["--set", "rates.control_hz=-1"], "rates.control_hz (--set): must be a positive"),
        (["--set", "rates.control_hz"], "--set expects KEY=VALUE"),
        (["--set", "gains.kp=1", "--set", "gains.kp=2"], "--set: gains.kp given twice"),
        (["--set", "rates=1"], "unknown config key 'rates' (a key is section.name"),
        (["--set", "rates.nosuch=1"], "unknown key rates.nosuch"),
    ],
)
def test_a_bad_set_is_one_error_line(argv, said, capsys):
    err = error_line(["simulate", "--duration", "0.1", *argv], capsys)
    assert said in err, err


def test_up_refuses_a_set_of_what_it_picks_for_its_rig(capsys):
    """The rig's port and key are hil up's (a free port, a fresh key): their options say so."""
    for key, option in [
        ("transport.zenoh_endpoint", "--zenoh-endpoint"),
        ("transport.key_file", "--key-file"),
    ]:
        err = error_line(["up", "--set", f"{key}=x"], capsys)
        assert err == f"hil up: error: --set {key}: hil up sets it for its rig; use {option}"


def test_parse_sets_reads_json_else_a_string():
    assert parse_sets(["a.b=[1, 2]", "c.d=true", "e.f=ioc", "g.h="]) == {
        "a.b": [1, 2],
        "c.d": True,
        "e.f": "ioc",
        "g.h": "",
    }
    with pytest.raises(ControllerConfigError, match="given twice"):
        parse_sets(["a.b=1", " a.b=2"])
