"""What ``hil monitor`` answers a Foxglove client off the happy path: a set of a read-only
parameter and a token given to a monitor that checks none. A real foxglove-sdk server and an
independent WebSocket client; the controller's link played in-process
(:mod:`tests.support.param_link`)."""

from __future__ import annotations

import pytest

from hal.config import RigConfig
from rt_controller.monitor.access import AccessGate
from rt_controller.monitor.bridge import MonitorBridge
from tests.support.foxglove_ws import FoxgloveClient
from tests.support.param_link import LoopbackLink, tuning_monitor


@pytest.fixture
def served():
    with tuning_monitor() as pair:
        yield pair


@pytest.mark.parametrize("name", ["hil.tuning", "hil.last_outcome"])
def test_a_set_of_a_read_only_parameter_is_refused_not_answered_with_an_older_outcome(served, name):
    link, client = served
    refused = client.set_parameters({"foo.bar": 1})["hil.last_outcome"]
    assert "unknown config key" in refused
    out = client.set_parameters({name: "x" if name == "hil.last_outcome" else False})
    assert out["hil.last_outcome"] == f"refused here: {name} cannot be set (read-only)"
    assert out.get("hil.tuning", True) is True and link.service.param_set == 0


def test_a_token_given_to_a_monitor_that_checks_none_is_not_said_to_be_right():
    """On plain loopback every client may tune: a wrong token must not read as "accepted"."""
    line = AccessGate("open").present(1, "not the token")
    assert "accepted" not in line and "no access token is needed" in line


def test_the_url_of_a_monitor_on_ipv6_loopback_is_one_a_client_can_open():
    """``hil monitor --host ::1`` prints its URL for Foxglove: ws://::1:PORT is no URL."""
    import socket

    if not socket.has_ipv6:
        pytest.skip("no IPv6 on this host")
    link = LoopbackLink()
    try:
        bridge = MonitorBridge(RigConfig(), link, host="::1", port=0)
    except Exception as exc:  # an IPv6 stack without ::1
        pytest.skip(f"cannot serve on ::1: {exc}")
    try:
        assert bridge.url == f"ws://[::1]:{bridge.port}"
        FoxgloveClient.open(bridge.url).close()
    finally:
        bridge.close()


@pytest.mark.parametrize(
    ("body", "why"),
    [
        ([1, 2], "not a JSON object"),
        ("look here", "not a JSON object"),
        ({"note": {"a": 1}}, "note must be text"),
    ],
)
def test_a_service_request_that_is_no_request_object_is_refused(served, body, why):
    """A mark whose body is a list or a string was made with an empty note, and a note that is
    an object was stored as its Python text: refused, with the reason, and nothing marked."""
    _, client = served
    client.wait_services({"/hil/mark"})
    out = client.call_service("/hil/mark", body)
    assert out["accepted"] is False and why in out["reason"], out
    assert client.call_service("/hil/mark", {"note": "fine"})["accepted"] is True
