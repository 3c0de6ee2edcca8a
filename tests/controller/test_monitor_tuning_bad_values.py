"""A value Foxglove sends that the monitor cannot read as a number or a tick (a diagonal entry
or ``hil.at_tick`` typed as text) reaches the controller, which refuses it with the reason:
counted, logged and said in ``hil.last_outcome``, never an empty answer with nothing said.
Over a real foxglove-sdk server and WebSocket client, the link played in-process."""

from __future__ import annotations

import pytest

from tests.support.param_link import tuning_monitor


@pytest.fixture
def rig():
    with tuning_monitor() as pair:
        yield pair


def test_a_diagonal_typed_as_text_is_refused_by_the_controller(rig):
    link, client = rig
    out = client.set_parameters({"gains.K_1": "abc"}, timeout=30)
    assert out["gains.K"] == [[0.01, 0.0], [0.0, 0.01]]  # unchanged
    assert (
        out["hil.last_outcome"].startswith("refused at tick")
        and "gains.K" in out["hil.last_outcome"]
    )
    assert link.service.counters.as_dict() == {"accepted": 0, "refused": 1, "unauthenticated": 0}


def test_a_tick_typed_as_text_is_refused_not_applied(rig):
    link, client = rig
    out = client.set_parameters({"hil.at_tick": "abc", "gains.kp": 0.3}, timeout=30)
    assert out["gains.kp"] == 0.13 and "at_tick" in out["hil.last_outcome"]
    assert out["hil.last_outcome"].startswith("refused at tick")
    assert link.service.cfg.gains.kp == 0.13 and link.service.counters.refused == 1
    after = client.set_parameters({"gains.kp": 0.3}, timeout=30)  # the bad tick was consumed
    assert after["gains.kp"] == 0.3 and link.service.param_set == 1
