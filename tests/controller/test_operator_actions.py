"""Operator actions over the parameters link (rt_controller/calibration/operator.py): arm,
disarm and marks are queued for the control thread, a scenario reset is refused with its
reason, and each answer names its tick."""

from __future__ import annotations

import secrets
import time

from hal.config import RigConfig
from rt_controller.calibration.link import REPLY_LABEL, REQUEST_LABEL, ParameterServer, seal, unseal
from rt_controller.calibration.operator import ACTIONS, EVENT_SCHEMA
from rt_controller.calibration.parameters import ParameterService

KEY = bytes(range(32))


def _action(action: str, **kw) -> bytes:
    body = {
        "op": "action",
        "action": action,
        "nonce": secrets.token_hex(16),
        "t_unix_ns": time.time_ns(),
        **kw,
    }
    return seal(body, KEY, REQUEST_LABEL)


def test_a_mark_is_answered_at_the_tick_the_loop_takes_it():
    svc = ParameterService(RigConfig())
    server = ParameterServer(svc, KEY)
    got: list = []
    server.handle(_action("mark", note="gain step", source="foxglove"), got.append)
    assert got == []  # answered by the control thread
    (act,) = svc.actions.due(7)
    assert (act.action, act.note) == ("mark", "gain step")
    out = act.finish(7, t_ns=5)
    assert out.accepted and out.tick == 7
    (reply,) = got
    event = unseal(reply, KEY, REPLY_LABEL)["event"]
    assert event["action"] == "mark" and event["tick"] == 7 and event["note"] == "gain step"
    assert set(event) <= set(EVENT_SCHEMA["properties"])
    assert svc.actions.due(8) == []


def test_reset_and_unknown_actions_are_refused_with_a_reason_at_their_tick():
    svc = ParameterService(RigConfig())
    server = ParameterServer(svc, KEY)
    got: list = []
    server.handle(_action("reset_scenario"), got.append)
    server.handle(_action("self_destruct"), got.append)
    reset, unknown = svc.actions.due(3)
    assert "reset" in reset.refusal and "unknown action" in unknown.refusal
    for act in (reset, unknown):
        act.finish(3, accepted=False, reason=act.refusal)
    events = [unseal(r, KEY, REPLY_LABEL)["event"] for r in got]
    assert [(e["action"], e["accepted"], e["tick"]) for e in events] == [
        ("reset_scenario", False, 3),
        ("self_destruct", False, 3),
    ]
    assert {"arm", "disarm", "mark", "reset_scenario"} <= set(ACTIONS)


def test_arm_and_disarm_wait_for_their_tick():
    svc = ParameterService(RigConfig())
    server = ParameterServer(svc, KEY)
    got: list = []
    server.handle(_action("disarm", at_tick=10), got.append)
    assert svc.actions.due(9) == []
    (act,) = svc.actions.due(10)
    act.finish(10, accepted=False, reason="already disarmed")
    event = unseal(got[0], KEY, REPLY_LABEL)["event"]
    assert event["reason"] == "already disarmed" and event["at_tick"] == 10


def test_hil_param_names_every_action():
    from rt_controller.commands.param import ACTION_NAMES

    assert set(ACTION_NAMES) == set(ACTIONS)
