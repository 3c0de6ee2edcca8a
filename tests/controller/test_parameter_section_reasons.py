"""Every key of the configuration that is not online-tunable is refused with a reason: a key of
a section without a reason of its own (vision, cia402, hardware) once raised KeyError in the
control thread and stopped the controller (``hil param set hardware.profile=cia402``)."""

from __future__ import annotations

import json

import pytest

from hal.config import RigConfig
from rt_controller.calibration.parameters import TUNABLE, ParameterService, Request, refusal


def _fixed_keys() -> list[str]:
    return [
        f"{section}.{name}"
        for section, body in RigConfig().to_dict().items()
        for name in body
        if f"{section}.{name}" not in TUNABLE
    ]


@pytest.mark.parametrize("key", _fixed_keys())
def test_every_fixed_key_has_a_reason(key: str) -> None:
    why = refusal(key)
    assert why is not None and why.startswith(f"{key} is not online-tunable: ")


def test_a_set_of_a_hardware_key_is_refused_not_raised() -> None:
    service = ParameterService(RigConfig())
    service.submit(Request({"hardware.profile": "cia402"}, source="test"))
    cfg, outcomes = service.due(0)
    assert cfg is None
    [out] = outcomes
    assert not out.accepted and out.reason.startswith("hardware.profile is not online-tunable")
    assert service.counters.refused == 1


@pytest.mark.parametrize("key", ["robot.__class__", "gains.__dict__", "gains.with_overrides"])
def test_an_attribute_that_is_no_config_key_is_refused_and_logged(key: str) -> None:
    """``hil param set robot.__class__=1`` once put the class into the record as the old value,
    and the controller died writing it (TypeError: not JSON serializable)."""
    service = ParameterService(RigConfig())
    service.submit(Request({key: 1}, source="test"))
    _, [out] = service.due(0)
    assert not out.accepted and out.reason == f"unknown config key {key!r}"
    assert out.changes == [{"key": key, "old": None, "new": 1}]
    json.dumps(out.record())
