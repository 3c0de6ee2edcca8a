"""A request the controller fails on (a fault of its own, not of the request) is counted and
said once on the controller's side, and ``hil param``'s client says it may have failed there,
through the public seam: :meth:`ParameterServer.attach` on a zenoh session and
:func:`request` on another."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import pytest

from hal.config import RigConfig
from rt_controller.calibration.link import ParameterLinkError, ParameterServer, request
from rt_controller.calibration.parameters import ParameterService

KEY = bytes(range(32))


def _payload(data: bytes) -> SimpleNamespace:
    return SimpleNamespace(to_bytes=lambda: data)


class Query:
    """zenoh's query as the queryable sees it: its answers, and dropped (ended) once."""

    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr, self.payload = key, _payload(payload)
        self.answers: list[bytes] = []

    def reply(self, _key: str, data: bytes) -> None:
        self.answers.append(data)

    def drop(self) -> None:
        pass


class InProcessZenoh:
    """zenoh's session for both sides: ``get`` runs the declared queryable at once."""

    def __init__(self) -> None:
        self.session = self
        self.queryable = None

    def declare_queryable(self, _key: str, handler) -> object:
        self.queryable = handler
        return object()

    def get(self, key: str, payload: bytes, timeout: float) -> list[SimpleNamespace]:
        query = Query(key, payload)
        self.queryable(query)
        return [SimpleNamespace(ok=SimpleNamespace(payload=_payload(a))) for a in query.answers]


def test_the_in_process_session_carries_an_answer():
    zenoh = InProcessZenoh()
    ParameterServer(ParameterService(RigConfig()), KEY).attach(zenoh)
    assert request(zenoh, KEY, "get")["values"]["gains.kp"] == 0.13


def test_a_request_the_controller_fails_on_is_counted_and_said_once(caplog):
    zenoh = InProcessZenoh()
    broken = ParameterService(None)  # type: ignore[arg-type]  # no configuration to read
    server = ParameterServer(broken, KEY)
    server.attach(zenoh)
    with caplog.at_level(logging.ERROR, logger="rt_controller.calibration"):
        for _ in range(3):
            with pytest.raises(ParameterLinkError, match="failed on it"):
                request(zenoh, KEY, "get")
    assert server.failed == 3
    said = [r for r in caplog.records if r.name.startswith("rt_controller.calibration")]
    assert len(said) == 1 and "fault of the controller's own" in said[0].getMessage()
    assert "(it got no answer)" in said[0].getMessage()
    counts = {"accepted": 0, "refused": 0, "unauthenticated": 0, "failed": 3}
    assert broken.counters.as_dict() == counts  # what /diagnostics reports
