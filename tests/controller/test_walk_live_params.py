"""Findings of the walk of the live tools: a set to the value in force is no change, and a
mark's note has a documented limit (refused and counted beyond it, never cut silently)."""

from __future__ import annotations

import json

from hal.config import RigConfig
from rt_controller.calibration.link import MAX_NOTE, event_line, outcome_line, request
from rt_controller.calibration.parameters import ParameterService, Request
from tests.support.param_link import KEY, LoopbackLink


def test_a_set_to_the_value_in_force_is_unchanged_not_an_applied_change():
    svc = ParameterService(RigConfig())
    kp = svc.cfg.gains.kp
    svc.submit(Request({"gains.kp": kp}, source="test"))
    cfg, (out,) = svc.due(5)
    assert cfg is None  # nothing to reconfigure
    rec = out.record()
    assert rec["accepted"] is True and rec["unchanged"] is True, rec
    assert rec["param_set"] == 0 and svc.param_set == 0
    assert svc.counters.accepted == 0 and svc.counters.as_dict()["unchanged"] == 1
    line = outcome_line({"outcome": rec})
    assert line.startswith("unchanged at tick 5") and "accepted" not in line, line


def test_a_set_with_one_real_change_is_still_an_accepted_change():
    svc = ParameterService(RigConfig())
    svc.submit(Request({"gains.kp": svc.cfg.gains.kp, "rhc.kmax": svc.cfg.rhc.kmax + 1}))
    cfg, (out,) = svc.due(1)
    assert cfg is not None and out.accepted and not out.record()["unchanged"]
    assert svc.param_set == 1 and svc.counters.accepted == 1
    assert "unchanged" not in svc.counters.as_dict()


def test_a_mark_with_a_note_beyond_the_limit_is_refused_with_the_reason_and_counted():
    link = LoopbackLink()
    out = request(link, KEY, "action", action="mark", note="x" * 100_000)
    event = out["event"]
    assert event["accepted"] is False, event
    assert f"limit {MAX_NOTE}" in event["reason"] and "100000" in event["reason"], event
    assert len(event["note"]) <= MAX_NOTE
    assert link.service.counters.as_dict()["oversized"] == 1
    assert "refused" in event_line(out) and len(event_line(out)) < 300
    fine = request(link, KEY, "action", action="mark", note="y" * MAX_NOTE)["event"]
    assert fine["accepted"] is True and fine["note"] == "y" * MAX_NOTE


def test_replay_does_not_apply_an_unchanged_set_the_controller_did_not_apply():
    """The controller neither reconfigures nor rebuilds the law for an unchanged set: a replay
    that applied it (a law rebuild for gains.kp) would not repeat the run."""
    from rt_controller.calibration.parameters import accepted_changes

    svc = ParameterService(RigConfig())
    svc.submit(Request({"gains.kp": svc.cfg.gains.kp}))
    svc.submit(Request({"gains.kp": 0.3}, at_tick=7))
    records = [o.record() for t in (3, 7) for o in svc.due(t)[1]]
    assert accepted_changes(records) == [(7, {"gains.kp": 0.3})]


def test_an_unchanged_set_at_the_tick_of_a_change_is_not_applied_either():
    """The loop rebuilds the law for the keys of the applied records only: an unchanged set
    sharing its tick with a change adds no key, in the run as in its replay."""
    from rt_controller.calibration.parameters import accepted_changes

    svc = ParameterService(RigConfig())
    svc.submit(Request({"gains.kp": svc.cfg.gains.kp}))
    svc.submit(Request({"controller.predict_state": not svc.cfg.controller.predict_state}))
    records = [o.record() for o in svc.due(4)[1]]
    assert [set(c) for _, c in accepted_changes(records)] == [{"controller.predict_state"}]


def test_the_services_schema_says_the_notes_limit():
    """What a Foxglove client is shown is what the controller holds a mark's note to."""
    from importlib.resources import files

    schema = json.loads(
        files("rt_controller.monitor").joinpath("service_request_schema.json").read_text()
    )
    assert schema["properties"]["note"]["maxLength"] == MAX_NOTE
