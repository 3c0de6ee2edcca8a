"""The ``hil`` console script as a user runs it."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rt_controller.cli import main

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


@pytest.mark.parametrize("option", [["--rate", "0"], ["--duration", "-1"]])
def test_bad_options(option, capsys):
    assert main(["simulate", *option]) == 2
    assert "must be positive" in capsys.readouterr().err


def test_help_for_every_subcommand():
    p = run("--help")
    assert p.returncode == 0
    from rt_controller.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for name in sub.choices:
        h = run(name, "--help")
        assert h.returncode == 0, (name, h.stderr)
        assert "usage: hil" in h.stdout
