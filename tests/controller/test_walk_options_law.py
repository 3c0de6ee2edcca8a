"""The RHC-only options (``--horizon``, ``--steps``, ``--kmax``, ``--zeta``) under a law in force
(``--law``, else the config's ``controller.law``) that is not rhc: ``hil simulate``, whose law
never changes, refuses them (one line, status 2: they would change nothing); ``hil controller``
and ``hil up`` keep them for a switch to rhc while the run runs (``hil param set
controller.law=rhc``) and say so on stderr; ``hil controller --plan`` refuses them (each run's
config is run as it is). With rhc they set the config."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from rt_controller.cli import main
from rt_controller.commands.common import config_from_args
from rt_controller.errors import ControllerConfigError
from tests.support import error_line

RHC_ONLY = [("--horizon", "0.2"), ("--steps", "12"), ("--kmax", "3"), ("--zeta", "40")]


@pytest.fixture
def nothing_runs(monkeypatch: pytest.MonkeyPatch) -> list[object]:
    """The simulation, the daemon and the rig are not started: each records what it was given
    and ends the command with a usage error instead."""
    started: list[object] = []

    def start(*args: object, **_: object) -> None:
        started.append(args)
        raise ControllerConfigError("not started in this test")

    import rt_controller.control.simulate
    import rt_controller.rig.processes
    import rt_controller.runtime.daemon

    monkeypatch.setattr(rt_controller.runtime.daemon, "ControllerDaemon", start)
    monkeypatch.setattr(rt_controller.rig.processes, "run_rig", start)
    monkeypatch.setattr(rt_controller.control.simulate, "run_closed_loop", start)
    return started


@pytest.mark.parametrize(("option", "value"), RHC_ONLY)
def test_simulate_refuses_an_rhc_option_under_another_law(
    option: str, value: str, nothing_runs: list[object], capsys: pytest.CaptureFixture[str]
) -> None:
    line = error_line(["simulate", "--duration", "1", "--law", "pbc", option, value], capsys)
    assert line.endswith(f"error: {option}: only for the rhc law (the law in force is pbc)")
    assert not nothing_runs


def test_simulate_counts_the_law_of_the_config(
    tmp_path: Path, nothing_runs: list[object], capsys: pytest.CaptureFixture[str]
) -> None:
    conf = tmp_path / "ioc.toml"
    conf.write_text('[controller]\nlaw = "ioc"\n', encoding="utf-8")
    line = error_line(["simulate", "--config", str(conf), "--horizon", "0.2"], capsys)
    assert line.endswith("error: --horizon: only for the rhc law (the law in force is ioc)")
    assert not nothing_runs


@pytest.mark.parametrize(
    "command",
    [["controller", "--no-rt", "--duration", "1"], ["up", "--duration", "1"]],
    ids=["controller", "up"],
)
def test_a_switchable_run_keeps_the_rhc_options_and_says_so(
    command: list[str], nothing_runs: list[object], capsys: pytest.CaptureFixture[str]
) -> None:
    code = main([*command, "--law", "pbc", "--horizon", "0.2", "--kmax", "3"])
    err = capsys.readouterr().err
    assert code == 2 and nothing_runs, err  # reached the run (which the fixture stops)
    prog = f"hil {command[0]}"
    assert (
        f"{prog}: note: --horizon, --kmax only take effect once the law is switched to rhc "
        "(the law in force is pbc; hil param set controller.law=rhc)"
    ) in err


def test_the_rhc_options_still_set_the_config_of_rhc(tmp_path: Path) -> None:
    conf = tmp_path / "rhc.toml"
    conf.write_text('[controller]\nlaw = "rhc"\n', encoding="utf-8")
    opts = {"horizon": 0.2, "steps": 12, "kmax": 3, "zeta": 40.0}
    for args in (
        argparse.Namespace(law="rhc", **opts),
        argparse.Namespace(config=str(conf), **opts),
    ):
        rhc = config_from_args(args).rhc
        assert (rhc.horizon, rhc.steps, rhc.kmax, rhc.zeta) == (0.2, 12, 3, 40.0)


@pytest.mark.parametrize("option", ["--rate", "--horizon", "--steps", "--kmax", "--zeta"])
def test_a_plan_refuses_the_options_its_runs_configs_give(
    option: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = tmp_path / "plan.json"
    plan.write_text('{"runs": []}', encoding="utf-8")
    argv = ["controller", "--no-rt", "--plan", str(plan), option, "20"]
    line = error_line(argv, capsys)
    assert line.endswith(f"error: --plan runs each run's config as it is: drop {option}")
