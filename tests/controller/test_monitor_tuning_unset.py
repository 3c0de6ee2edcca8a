"""A Foxglove set without a value (the protocol's "unset", which Foxglove's Parameters panel
sends when a value is cleared) is refused by ``hil monitor`` with a line that says what to do,
never passed on as Python's ``None`` ("expected a number, got None"); the values stay."""

from __future__ import annotations

import json
import time

import pytest

from tests.support.param_link import tuning_monitor


@pytest.fixture
def rig():
    with tuning_monitor() as pair:
        yield pair


def _set_raw(client, params: list[dict], rid: str, timeout: float = 30.0) -> dict:
    """``setParameters`` as sent (a parameter may lack ``value``): the answer's values."""
    client.ws.send(json.dumps({"op": "setParameters", "parameters": params, "id": rid}))
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        frame = client.ws.recv(timeout=deadline - time.monotonic())
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg.get("op") == "parameterValues" and msg.get("id") == rid:
                return {p["name"]: p.get("value") for p in msg["parameters"]}
    raise AssertionError("no answer from the Foxglove server")


@pytest.mark.parametrize("name", ["gains.kp", "gains.K_1", "controller.law"])
def test_a_set_without_a_value_is_refused_with_what_to_do(rig, name):
    link, client = rig
    out = _set_raw(client, [{"name": name}], "u1")
    line = out["hil.last_outcome"]
    assert line.startswith("refused here:") and name in line and "None" not in line
    assert "value" in line
    assert link.service.param_set == 0 and link.service.cfg.gains.kp == 0.13
    after = _set_raw(client, [{"name": "gains.kp", "value": 0.3}], "u2")
    assert after["gains.kp"] == 0.3 and link.service.param_set == 1
