"""A signed request whose ``at_tick`` is no tick (a Foxglove service body passes it through as
sent: a string, a list, NaN, a fraction, a boolean) is refused with the reason, counted and
answered, never applied at some other tick and never a failure of the controller, through the
public seams: :meth:`ParameterServer.attach` on a zenoh session and :func:`request`."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

from hal.config import RigConfig
from rt_controller.calibration.link import ParameterServer, request
from rt_controller.calibration.parameters import ParameterService

KEY = bytes(range(32))
TICK = 10
BAD_TICKS = ["abc", [1], {"t": 1}, float("nan"), float("inf"), 1.5, True, -(2**70)]


class Query:
    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr = key
        self.payload = SimpleNamespace(to_bytes=lambda: payload)
        self.answers: list[bytes] = []

    def reply(self, _key: str, data: bytes) -> None:
        self.answers.append(data)

    def drop(self) -> None:
        pass


class Rig:
    """zenoh for both sides; the loop's tick boundary :data:`TICK` follows each request."""

    def __init__(self) -> None:
        self.session, self.queryable = self, None
        self.service = ParameterService(RigConfig())
        self.server = ParameterServer(self.service, KEY)
        self.server.attach(self)
        self.events: list[Any] = []

    def declare_queryable(self, _key: str, handler: Any) -> object:
        self.queryable = handler
        return object()

    def get(self, key: str, payload: bytes, timeout: float) -> list[SimpleNamespace]:
        query = Query(key, payload)
        self.queryable(query)
        self.service.due(TICK)
        for act in self.service.actions.due(TICK):
            reason = self.service.actions.refusal(act, TICK)
            self.events.append(act.finish(TICK, accepted=reason is None, reason=reason))
        wrap = [
            SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda a=a: a)) for a in query.answers
        ]
        return [SimpleNamespace(ok=w) for w in wrap]


@pytest.mark.parametrize("at_tick", BAD_TICKS, ids=repr)
def test_a_set_for_no_tick_is_refused_and_counted(at_tick: Any) -> None:
    rig = Rig()
    out = request(rig, KEY, "set", changes={"gains.kp": 0.2}, at_tick=at_tick, timeout_s=1)
    o = out["outcome"]
    assert not o["accepted"] and "at_tick" in o["reason"] and "\n" not in o["reason"]
    assert rig.service.cfg.gains.kp == RigConfig().gains.kp and rig.server.failed == 0
    assert rig.service.counters.as_dict() == {"accepted": 0, "refused": 1, "unauthenticated": 0}


@pytest.mark.parametrize("at_tick", BAD_TICKS, ids=repr)
def test_an_action_for_no_tick_is_refused(at_tick: Any) -> None:
    rig = Rig()
    out = request(rig, KEY, "action", action="disarm", at_tick=at_tick, timeout_s=1)
    e = out["event"]
    assert not e["accepted"] and "at_tick" in e["reason"] and rig.server.failed == 0


@pytest.mark.parametrize("at_tick", [None, 3, 7.0])
def test_a_tick_reached_or_none_is_taken(at_tick: Any) -> None:
    rig = Rig()
    out = request(rig, KEY, "set", changes={"gains.kp": 0.2}, at_tick=at_tick, timeout_s=1)
    assert out["outcome"]["accepted"] and out["outcome"]["tick"] == TICK
    assert out["outcome"]["at_tick"] == (None if at_tick is None else int(at_tick))


def test_a_huge_tick_is_named_as_it_was_sent() -> None:
    """1e300 is an integer-valued float: refused as out of range, named ``1e+300``, not written
    out as its 301 digits (cut at the reason's length)."""
    out = request(Rig(), KEY, "set", changes={"gains.kp": 0.2}, at_tick=1e300, timeout_s=1)
    assert out["outcome"]["reason"] == "at_tick: expected a tick (an integer), got 1e+300"
