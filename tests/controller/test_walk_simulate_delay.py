"""``hil simulate`` with a delay as long as the run: the law would only ever see the first
sample, so the figures (J, f_final, max_abs_dq of the seen state) describe no closed loop."""

from __future__ import annotations

import json

import pytest

from rt_controller.cli import main


@pytest.mark.parametrize("flag", ["--state-delay", "--feature-delay"])
def test_a_delay_covering_the_whole_run_is_refused_in_one_line(flag, capsys):
    # 0.1 s at 50 Hz: 5 ticks; with a delay of 4 periods every tick sees sample 0
    assert main(["simulate", "--duration", "0.1", "--rate", "50", flag, "4", "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    (line,) = err.strip().splitlines()
    assert line.startswith(f"hil simulate: error: {flag} 4 ")
    assert "first sample" in line


def test_a_delay_shorter_than_the_run_still_runs(capsys):
    argv = ["simulate", "--duration", "0.1", "--rate", "50", "--state-delay", "3", "--json", "-q"]
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out)["ticks"] == 5
