"""The monitor as a calibration front-end (rt_controller/monitor/tuning.py): Foxglove's
Parameters (get, set, subscribe) and the operator services over a real foxglove-sdk server and
an independent WebSocket client, the link to the controller played in-process by the real
ParameterServer (requests signed and verified as on zenoh; the "loop" takes them at tick 10)."""

from __future__ import annotations

import time
from types import SimpleNamespace

import pytest

from hal.config import RigConfig
from hal.zenoh_session import free_loopback_port
from rt_controller.monitor.bridge import MonitorBridge
from rt_controller.monitor.tuning import ADVERTISED, TuningFrontEnd
from rt_controller.runtime.recorder import CYCLE_TOPIC, DIAGNOSTICS_TOPIC
from tests.support.foxglove_ws import FoxgloveClient
from tests.support.param_link import KEY, TICK, LoopbackLink


class SlowTickLink(LoopbackLink):
    """The loop reaches tick :data:`TICK` ``delay_s`` after a request (None: never), and zenoh's
    ``get`` waits for the answer up to its ``timeout``, as a lockstep run with ticks to go."""

    def __init__(self, delay_s: float | None) -> None:
        super().__init__()
        self.delay_s = delay_s

    def get(self, _key, payload, timeout):
        got: list = []
        self.server.handle(payload, got.append)
        start = time.monotonic()
        while not got and time.monotonic() - start < timeout:
            if self.delay_s is not None and time.monotonic() - start >= self.delay_s:
                self.service.due(TICK)
            time.sleep(0.01)
        ok = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: got[0]))
        return [SimpleNamespace(ok=ok)] if got and got[0] is not None else []


@pytest.fixture
def serve():
    bridges = []

    def start(allow_tuning: bool, link: LoopbackLink | None = None, **kw):
        link = link or LoopbackLink()
        tuning = TuningFrontEnd(link, KEY, allow_tuning=allow_tuning, **kw)
        port = free_loopback_port()
        bridge = MonitorBridge(RigConfig(), link, port=port, tuning=tuning)
        bridges.append(bridge)
        client = FoxgloveClient.open(f"ws://127.0.0.1:{port}")
        return link, client, tuning

    yield start
    for b in bridges:
        b.close()


def test_parameters_are_advertised_and_a_set_lands_at_its_tick(serve):
    link, client, tuning = serve(allow_tuning=True)
    values = client.get_parameters([])
    assert set(ADVERTISED) <= set(values)
    assert values["gains.kp"] == 0.13 and values["gains.K_1"] == 0.01
    assert values["hil.tuning"] is True
    client.subscribe_parameters(["gains.kp"])
    out = client.set_parameters({"gains.kp": 0.3, "hil.at_tick": TICK})
    assert out["gains.kp"] == 0.3
    assert "accepted at tick 10" in out["hil.last_outcome"]
    assert link.service.cfg.gains.kp == 0.3 and link.service.param_set == 1
    out = client.set_parameters({"gains.K_2": 0.02})  # one diagonal entry of K
    assert link.service.cfg.gains.K == ((0.01, 0.0), (0.0, 0.02))
    assert out["gains.K"] == [[0.01, 0.0], [0.0, 0.02]]
    refused = client.set_parameters({"gains.alpha": [[1.0, 2.0], [2.0, 1.0]]})
    assert refused["gains.alpha"] == [[0.05, 0.0], [0.0, 0.15]]  # the unchanged value
    assert "refused at tick 10" in refused["hil.last_outcome"]
    assert link.service.param_set == 2
    tuning.param_set_seen(2)  # as a cycle record with param_set 2 does
    client.get_parameters(["hil.tuning"])  # the update comes before this answer
    update = client.parameter_updates[-1]  # the sets' answers were published to it as well
    assert {p["name"]: p["value"] for p in update["parameters"]} == {"gains.kp": 0.3}


def test_a_set_for_a_later_tick_waits_for_that_tick_past_the_answer_timeout(serve):
    # the loop takes the set at tick 10 only after 1 s; a "get" is answered within 0.2 s
    link, client, _ = serve(allow_tuning=True, link=SlowTickLink(1.0), timeout_s=0.2)
    out = client.set_parameters({"gains.kp": 0.3, "hil.at_tick": TICK})
    assert out["gains.kp"] == 0.3 and "accepted at tick 10" in out["hil.last_outcome"]
    assert link.service.param_set == 1


def test_a_set_the_controller_never_answers_replies_with_the_values_and_why(serve):
    link, client, _ = serve(
        allow_tuning=True, link=SlowTickLink(None), timeout_s=0.2, scheduled_timeout_s=0.5
    )
    out = client.set_parameters({"gains.kp": 0.3, "hil.at_tick": TICK})
    assert out["gains.kp"] == 0.13 and "no answer from the controller" in out["hil.last_outcome"]
    assert link.service.param_set == 0


def test_services_arm_disarm_law_mark_and_a_refused_reset(serve):
    link, client, _ = serve(allow_tuning=True)
    names = {"/hil/arm", "/hil/disarm", "/hil/mark", "/hil/switch_law", "/hil/reset_scenario"}
    client.wait_services(names)
    mark = client.call_service("/hil/mark", {"note": "look here"})
    assert mark["accepted"] and mark["tick"] == TICK and mark["note"] == "look here"
    law = client.call_service("/hil/switch_law", {"law": "rhc"})
    assert law["accepted"] and link.service.cfg.controller.law == "rhc"
    bad = client.call_service("/hil/switch_law", {"law": "pid"})
    assert not bad["accepted"] and "law" in bad["reason"]
    reset = client.call_service("/hil/reset_scenario", {})
    assert not reset["accepted"] and "reset" in reset["reason"]
    assert client.call_service("/hil/disarm", {})["accepted"]


def test_without_allow_tuning_parameters_are_read_only(serve):
    link, client, _ = serve(allow_tuning=False)
    values = client.get_parameters(["gains.kp", "hil.tuning"])
    assert values == {"gains.kp": 0.13, "hil.tuning": False}
    out = client.set_parameters({"gains.kp": 0.3})
    assert out["gains.kp"] == 0.13 and "allow-tuning" in out["hil.last_outcome"]
    assert link.service.param_set == 0 and link.service.counters.refused == 0
    client.wait_services({"/hil/mark"})
    assert "/hil/arm" not in client.services and "/hil/switch_law" not in client.services


def test_layout_calibration_panels_name_advertised_parameters():
    import json
    from pathlib import Path

    layout = json.loads((Path(__file__).parents[2] / "foxglove" / "layout.json").read_text())
    panels = layout["configById"]
    sliders = {k: v for k, v in panels.items() if k.startswith("VariableSlider!")}
    names = {v["globalVariableName"] for v in sliders.values()}
    assert {"gains.kp", "gains.alpha_1", "gains.alpha_2", "gains.K_1", "gains.K_2"} <= names
    assert names <= set(ADVERTISED)
    (params,) = [k for k in panels if k.startswith("Parameters!")]
    tab = next(t for t in panels["Tab!main"]["tabs"] if t["title"].startswith("Calibration"))
    text = json.dumps(tab["layout"])
    assert params in text and all(k in text for k in sliders)


def test_a_client_subscribing_to_channels_raises_nothing_in_the_listener(serve, capfd, caplog):
    """The SDK calls every listener callback (subscribe, unsubscribe, ...) on the tuning front
    end, not only the Parameters ones; a missing one is an error line per channel and client."""
    _link, client, _tuning = serve(allow_tuning=False)
    topics = {CYCLE_TOPIC, DIAGNOSTICS_TOPIC}
    client.wait_channels(topics)
    client.subscribe(sorted(client.channels))
    client.get_parameters(["gains.kp"])  # answered after the subscribe was handled
    client.close()
    time.sleep(0.5)  # the server sees the disconnect (unsubscribe) on its own thread
    said = capfd.readouterr().err + caplog.text
    assert "Callback failed" not in said, said
