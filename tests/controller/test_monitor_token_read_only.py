"""``hil.token`` set on a plain loopback monitor without ``--allow-tuning``: the answer says no
token is needed, and does not claim the client "may change the rig" (every set is refused
there; only the mark is offered)."""

from __future__ import annotations

from hal.config import RigConfig
from hal.zenoh_session import free_loopback_port
from rt_controller.monitor.bridge import MonitorBridge
from rt_controller.monitor.tuning import TuningFrontEnd
from tests.support.foxglove_ws import FoxgloveClient
from tests.support.param_link import KEY, LoopbackLink


def _answer(allow_tuning: bool) -> str:
    link = LoopbackLink()
    tuning = TuningFrontEnd(link, KEY, allow_tuning=allow_tuning)
    port = free_loopback_port()
    bridge = MonitorBridge(RigConfig(), link, port=port, tuning=tuning)
    client = FoxgloveClient.open(f"ws://127.0.0.1:{port}")
    try:
        return client.set_parameters({"hil.token": "abc"}, timeout=30)["hil.last_outcome"]
    finally:
        client.close()
        bridge.close()


def test_the_token_answer_of_a_read_only_monitor_says_it_is_read_only() -> None:
    line = _answer(allow_tuning=False)
    assert line.startswith("no access token is needed"), line
    assert "may change the rig" not in line and "--allow-tuning" in line, line


def test_the_token_answer_of_a_tuning_monitor_says_who_may_change_the_rig() -> None:
    line = _answer(allow_tuning=True)
    assert line.startswith("no access token is needed") and "may change the rig" in line, line
