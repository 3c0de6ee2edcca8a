"""A replayed request stays refused after the controller's memory of nonces has moved on: a key
holder's burst of more than ``seen_max`` requests in the freshness window must not reopen the
oldest ones to a replay (captured on zenoh by anyone on the host), through the public seams
:class:`ParameterServer` (its ``handle``, ``wall_ns`` and ``seen_max``) and :func:`seal`."""

from __future__ import annotations

from hal.config import RigConfig
from rt_controller.calibration.link import REQUEST_LABEL, ParameterServer, seal
from rt_controller.calibration.parameters import ParameterService

KEY = bytes(range(32))
NOW = 1_800_000_000_000_000_000


def _set(nonce: str, t_ns: int, kp: float) -> bytes:
    body = {"op": "set", "nonce": nonce, "t_unix_ns": t_ns, "source": "test"}
    body.update(changes={"gains.kp": kp}, at_tick=None)
    return seal(body, KEY, REQUEST_LABEL)


def test_a_request_pushed_out_of_memory_cannot_be_replayed() -> None:
    service = ParameterService(RigConfig())
    server = ParameterServer(service, KEY, wall_ns=lambda: NOW, seen_max=2)
    first = _set("n1", NOW - 3_000_000_000, 0.2)
    answered: list[bytes | None] = []
    for payload in (first, _set("n2", NOW - 2_000_000_000, 0.3), _set("n3", NOW - 1, 0.4)):
        server.handle(payload, answered.append)
    service.due(0)
    assert service.cfg.gains.kp == 0.4 and service.counters.accepted == 3
    server.handle(first, answered.append)  # the replay, still inside the 30 s window
    service.due(1)
    assert service.cfg.gains.kp == 0.4 and service.counters.accepted == 3
    assert service.counters.unauthenticated == 1 and answered[-1] is None
    server.handle(_set("n4", NOW, 0.5), answered.append)  # new requests still go through
    service.due(2)
    assert service.cfg.gains.kp == 0.5 and service.counters.accepted == 4
