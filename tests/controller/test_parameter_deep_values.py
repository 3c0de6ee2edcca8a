"""A value nested hundreds of lists deep (``hil param set rhc.u_max=[[[[...]]]]``) is refused
with its reason: it once raised RecursionError in the control thread and stopped the
controller (depth 500), and at depth 990 ``hil param`` itself died with a traceback."""

from __future__ import annotations

import json

import pytest

from hal.config import RigConfig
from rt_controller.calibration.parameters import ParameterService, Request
from rt_controller.cli import main


def _nested(depth: int) -> list:
    value: list = []
    for _ in range(depth - 1):
        value = [value]
    return value


@pytest.mark.parametrize("depth", [500, 5000])
def test_a_deeply_nested_value_is_refused_and_logged(depth: int) -> None:
    service = ParameterService(RigConfig())
    service.submit(Request({"rhc.u_max": _nested(depth)}, source="test"))
    cfg, [out] = service.due(0)
    assert cfg is None and not out.accepted
    assert out.reason.startswith("rhc.u_max: ") and "nested" in out.reason, out.reason
    assert service.counters.refused == 1
    json.dumps(out.record())


def test_a_shallow_wrong_shape_is_still_judged_by_the_rules() -> None:
    service = ParameterService(RigConfig())
    service.submit(Request({"rhc.u_max": [[1.0], [2.0]]}, source="test"))
    _, [out] = service.due(0)
    assert not out.accepted and out.reason.startswith("rhc.u_max") and "nested" not in out.reason


def test_hil_param_set_with_a_deeply_nested_value_is_one_line(capsys) -> None:
    text = "[" * 990 + "]" * 990
    assert main(["param", "set", f"rhc.u_max={text}", "--timeout", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err and "rhc.u_max" in err, err


def test_hil_replay_set_with_a_deeply_nested_value_is_one_line(capsys, tmp_path) -> None:
    text = "[" * 990 + "]" * 990
    log = tmp_path / "absent.mcap"  # the --set is judged before the log is read
    assert main(["replay", str(log), "--set", f"rhc.u_max={text}"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert "--set: rhc.u_max: lists nested too deep" in err, err
