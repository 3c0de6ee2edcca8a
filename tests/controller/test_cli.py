"""The ``hil`` console script as a user runs it."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from rt_controller.cli import COMMAND_MODULES, build_parser, main

HIL = [sys.executable, "-m", "rt_controller.cli"]


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*HIL, *args], capture_output=True, text=True, timeout=120)


def test_simulate_json_summary():
    p = run("simulate", "--law", "ioc", "--json", "--duration", "2")
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    for key in ("law", "rate", "duration", "ticks", "J", "V0", "f_final", "max_abs_tau"):
        assert key in s
    assert s["law"] == "ioc" and s["ticks"] == 100 and s["rate"] == 50.0


def test_simulate_table_output(capsys):
    assert main(["simulate", "--law", "pbc", "--duration", "0.5", "--no-disturbance"]) == 0
    out = capsys.readouterr().out
    assert "max_abs_tau" in out and "pbc" in out


def test_bad_config_is_one_clear_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[gains]\nkp = -1\n")
    assert main(["simulate", "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "gains.kp: must be positive" in err
    assert "Traceback" not in err


def test_bad_config_backed_option(capsys):
    assert main(["simulate", "--rate", "0"]) == 2
    assert "rates.control_hz (--rate): must be a positive number" in capsys.readouterr().err


def test_bad_option_refused_while_parsing(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--duration", "-1"])
    assert exc.value.code == 2
    assert "argument --duration: duration in seconds must be in (0," in capsys.readouterr().err


def test_help_for_every_subcommand():
    p = run("--help")
    assert p.returncode == 0
    assert COMMAND_MODULES  # each module registers the subcommand of its name
    for name in COMMAND_MODULES:
        assert re.search(rf"(?m)^ +{name}(\s|$)", p.stdout), name  # in the top-level help
        h = run(name, "--help")
        assert h.returncode == 0, (name, h.stderr)
        assert "usage: hil" in h.stdout


HEAVY = ("numpy", "zenoh", "numba", "matplotlib", "can", "cantools", "mcap")

HELP_PROBE = """
import contextlib, io, json, sys
from rt_controller.cli import COMMAND_MODULES, build_parser, main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        main(sys.argv[1:])
    except SystemExit as exc:
        code = exc.code
heavy = [m for m in {heavy!r} if m in sys.modules]
print(json.dumps({{"code": code, "heavy": heavy, "chars": len(out.getvalue())}}))
"""


@pytest.mark.parametrize("argv", [("--help",)] + [(c, "--help") for c in COMMAND_MODULES])
def test_help_imports_no_heavy_library(argv):
    """``hil --help`` and ``hil COMMAND --help`` build their parsers without numpy, zenoh,
    numba, matplotlib, python-can, cantools or mcap (a fresh interpreter per case)."""
    probe = HELP_PROBE.format(heavy=HEAVY)
    p = subprocess.run(
        [sys.executable, "-c", probe, *argv], capture_output=True, text=True, timeout=120
    )
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["code"] == 0 and got["chars"] > 100
    assert got["heavy"] == []


def test_rig_wall_budget_scales_with_simulated_time_in_lockstep():
    """A lockstep run is simulated time: on a slow host (user-mode Linux, about 10x slower) it
    must not be called hung after its simulated duration; an explicit budget wins."""
    from rt_controller.rig.options import LOCKSTEP_SLOWEST, STARTUP_MARGIN_S, RigOptions

    assert RigOptions(duration_s=6.0).wall_budget_s() == 6.0 + STARTUP_MARGIN_S
    lockstep = RigOptions(duration_s=6.0, lockstep=True)
    assert lockstep.wall_budget_s() == LOCKSTEP_SLOWEST * 6.0 + STARTUP_MARGIN_S
    assert LOCKSTEP_SLOWEST >= 10.0  # at least user-mode Linux's slowdown
    assert RigOptions(duration_s=6.0, lockstep=True, wall_timeout_s=7.5).wall_budget_s() == 7.5


def test_up_refuses_a_bad_wall_timeout(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["up", "--wall-timeout", "-3"])
    assert exc.value.code == 2
    assert "--wall-timeout" in capsys.readouterr().err


def test_a_rig_child_exits_at_once_with_its_output_and_status(tmp_path):
    """``python -m rt_controller.cli`` (how the rig starts its children) skips the
    interpreter's teardown: the summary printed to a pipe still arrives whole, and the exit
    status is the command's, for success and for a refused command line."""
    ok = run("simulate", "--duration", "0.2", "--json")
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["ticks"] == 10
    bad = run("controller", "--plan", str(tmp_path / "none.json"), "--no-rt")
    assert bad.returncode == 2 and "cannot read" in bad.stderr


@pytest.mark.parametrize(
    ("argv", "command", "unknown"),
    [
        (["experiment", "fig3", "--nope"], "hil experiment", "--nope"),
        (["vision", "--can", "virtual"], "hil vision", "--can virtual"),
        (["bench", "host", "--nope"], "hil bench host", "--nope"),
    ],
)
def test_an_unknown_option_is_reported_with_its_command_s_usage(argv, command, unknown, capsys):
    """Not with the top-level ``usage: hil [-h] ...``, which lists every command but not the
    options of the one that was given."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.startswith(f"usage: {command} "), err
    assert f"{command}: error: unrecognized arguments: {unknown}" in err, err


@pytest.mark.parametrize(
    ("argv", "items", "at_tick", "as_json"),
    [
        (["param", "set", "--at-tick", "5", "gains.kp=0.3"], ["gains.kp=0.3"], 5, False),
        (["param", "get", "--json", "gains.kp", "gains.kd"], ["gains.kp", "gains.kd"], None, True),
        (["param", "mark", "--at-tick", "5", "hello"], ["hello"], 5, False),
    ],
)
def test_options_between_a_commands_positionals(argv, items, at_tick, as_json):
    """argparse alone gave ``items`` nothing once an option followed the action, and the
    items were "unrecognized arguments" (exit 2)."""
    args = build_parser().parse_args(argv)
    assert (args.items, args.at_tick, args.json) == (items, at_tick, as_json)
