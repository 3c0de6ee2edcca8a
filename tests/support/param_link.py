"""The signed parameter link of ``hil monitor`` played in-process, for tests of the Foxglove
front-end: ``session.session.get`` of zenoh answered by a real
:class:`~rt_controller.calibration.link.ParameterServer` whose queue is taken at tick
:data:`TICK` (actions are done there, as the loop does)."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

from hal.config import RigConfig
from rt_controller.calibration.link import ParameterServer
from rt_controller.calibration.parameters import ParameterService

KEY = bytes(range(32))
TICK = 10


class LoopbackLink:
    """``session.session.get`` of zenoh, answered by a ParameterServer whose queue is taken at
    tick :data:`TICK` (actions are done there, as the loop does)."""

    def __init__(self) -> None:
        self.service = ParameterService(RigConfig())
        self.server = ParameterServer(self.service, KEY)
        self.session = self
        self.lock = threading.Lock()

    def get(self, _key, payload, timeout):
        got: list = []
        with self.lock:
            self.server.handle(payload, got.append)
            if not got:
                self.service.due(TICK)
                for act in self.service.actions.due(TICK):
                    act.finish(TICK, accepted=act.refusal is None, reason=act.refusal)
        ok = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: got[0]))
        return [SimpleNamespace(ok=ok)] if got and got[0] is not None else []


@contextlib.contextmanager
def tuning_monitor(allow_tuning: bool = True) -> Iterator[tuple[LoopbackLink, Any]]:
    """A real ``hil monitor`` bridge (tuning allowed unless ``allow_tuning`` is False) on a
    free loopback port, over a :class:`LoopbackLink`, and an independent Foxglove WebSocket
    client connected to it."""
    from hal.zenoh_session import free_loopback_port
    from rt_controller.monitor.bridge import MonitorBridge
    from rt_controller.monitor.tuning import TuningFrontEnd
    from tests.support.foxglove_ws import FoxgloveClient

    link = LoopbackLink()
    tuning = TuningFrontEnd(link, KEY, allow_tuning=allow_tuning)
    port = free_loopback_port()
    bridge = MonitorBridge(RigConfig(), link, port=port, tuning=tuning)
    client = FoxgloveClient.open(f"ws://127.0.0.1:{port}")
    try:
        yield link, client
    finally:
        client.close()
        bridge.close()
