"""The online parameters' wire (rt_controller/calibration/link.py): only the rig's key tunes
the rig, a replayed request is refused, and both are counted."""

from __future__ import annotations

import secrets
import time

import pytest

from hal.config import RigConfig
from rt_controller.calibration.link import (
    ANSWER_TIMEOUT_S,
    REPLY_LABEL,
    REQUEST_LABEL,
    SCHEDULED_TIMEOUT_S,
    ParameterLinkError,
    ParameterServer,
    request,
    seal,
    unseal,
)
from rt_controller.calibration.parameters import ParameterService

KEY = bytes(range(32))


def _request(op, key=KEY, **kw):
    body = {"op": op, "nonce": secrets.token_hex(16), "t_unix_ns": time.time_ns(), **kw}
    return seal(body, key, REQUEST_LABEL)


def _serve(server, payload):
    got = []
    server.handle(payload, got.append)
    return got


def test_get_and_set_with_the_rig_key():
    svc = ParameterService(RigConfig())
    server = ParameterServer(svc, KEY)
    (reply,) = _serve(server, _request("get"))
    out = unseal(reply, KEY, REPLY_LABEL)
    assert out["values"]["gains.kp"] == 0.13 and out["param_set"] == 0
    (dump,) = _serve(server, _request("dump"))
    assert "[gains]" in unseal(dump, KEY, REPLY_LABEL)["toml"]
    replies = _serve(server, _request("set", changes={"gains.kp": 0.2}, at_tick=3))
    assert replies == []  # answered by the control thread at the tick
    cfg, (outcome,) = svc.due(3)
    assert cfg.gains.kp == 0.2 and outcome.tick == 3 and outcome.accepted
    (reply,) = replies
    assert unseal(reply, KEY, REPLY_LABEL)["outcome"]["tick"] == 3


def test_another_key_a_replay_or_an_old_request_changes_nothing_and_is_counted():
    svc = ParameterService(RigConfig())
    server = ParameterServer(svc, KEY)
    assert _serve(server, _request("set", key=bytes(32), changes={"gains.kp": 0.2})) == [None]
    ok = _request("set", changes={"gains.kp": 0.3})
    _serve(server, ok)
    assert _serve(server, ok) == [None]  # the same nonce again
    old = seal(
        {"op": "set", "nonce": "ab", "t_unix_ns": time.time_ns() - 10**12, "changes": {}},
        KEY,
        REQUEST_LABEL,
    )
    assert _serve(server, old) == [None]
    assert _serve(server, b"garbage") == [None]
    cfg, outs = svc.due(0)
    assert len(outs) == 1 and cfg.gains.kp == 0.3
    assert svc.counters.as_dict() == {"accepted": 1, "refused": 0, "unauthenticated": 4}


class RecordingSession:
    """zenoh's ``session.get`` that never answers and records how long it was asked to wait."""

    def __init__(self) -> None:
        self.session = self
        self.waits: list[float] = []

    def get(self, _key, payload, timeout):
        self.waits.append(timeout)
        return []


def test_a_request_for_a_later_tick_waits_for_that_tick_not_for_an_immediate_answer():
    s = RecordingSession()
    for kw in ({}, {"at_tick": 2400}):
        with pytest.raises(ParameterLinkError, match="ended unanswered"):
            request(s, KEY, "set", changes={"gains.kp": 0.3}, **kw)
    with pytest.raises(ParameterLinkError):
        request(s, KEY, "action", action="mark", at_tick=7)
    with pytest.raises(ParameterLinkError):
        request(s, KEY, "set", changes={}, at_tick=7, timeout_s=2.5)
    assert s.waits == [ANSWER_TIMEOUT_S, SCHEDULED_TIMEOUT_S, SCHEDULED_TIMEOUT_S, 2.5]
    assert SCHEDULED_TIMEOUT_S > 10 * ANSWER_TIMEOUT_S


def test_hil_param_help_names_the_waits_request_uses(capsys):
    from rt_controller.cli import main

    with pytest.raises(SystemExit):
        main(["param", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"default {ANSWER_TIMEOUT_S:g} s; with --at-tick {SCHEDULED_TIMEOUT_S:g} s" in text


class SlowSession(RecordingSession):
    """zenoh's ``session.get`` that ends its query at the timeout without an answer."""

    def get(self, _key, payload, timeout):
        time.sleep(timeout)
        return super().get(_key, payload, timeout)


def test_no_answer_says_whether_the_query_timed_out_or_ended_unanswered():
    """A query zenoh ends at once had nobody to answer it (no controller on the endpoint, or
    one that refused a request of another rig key); only one that ran out its time is a
    timeout."""
    with pytest.raises(ParameterLinkError, match="ended unanswered after") as early:
        request(RecordingSession(), KEY, "get")
    assert "within" not in str(early.value)
    with pytest.raises(ParameterLinkError, match=r"within 0\.05 s"):
        request(SlowSession(), KEY, "get", timeout_s=0.05)
