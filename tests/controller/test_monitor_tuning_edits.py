"""Edits of one matrix while the controller has not answered yet, and faults inside the
Foxglove callbacks of the monitor's tuning front-end (rt_controller/monitor/tuning.py): the
callbacks are called as the SDK calls them, one after the other, with the link to the
controller played in-process by the real ParameterServer."""

from __future__ import annotations

import logging
from types import SimpleNamespace

from foxglove.websocket import Parameter

from rt_controller.monitor.tuning import TuningFrontEnd
from tests.support.param_link import KEY, TICK, LoopbackLink

CLIENT = SimpleNamespace(id=1)
"""The connection the SDK names in each callback."""


class BusyLink(LoopbackLink):
    """A controller whose loop has not reached a tick boundary yet: a "get" is answered at
    once, a set waits in its queue, unanswered, until the test runs the loop's ``due``."""

    def get(self, _key, payload, timeout):
        got: list = []
        self.server.handle(payload, got.append)
        ok = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: got[0]))
        return [SimpleNamespace(ok=ok)] if got and got[0] is not None else []


class BrokenLink(LoopbackLink):
    """A link that raises what no request expects once ``broken`` is set."""

    broken = False

    def get(self, key, payload, timeout):
        if self.broken:
            raise RuntimeError("zenoh session closed")
        return super().get(key, payload, timeout)


def _set(tuning: TuningFrontEnd, **values) -> dict:
    params = [Parameter(name.replace("__", "."), value=v) for name, v in values.items()]
    return {p.name: p.get_value() for p in tuning.on_set_parameters(CLIENT, params)}


def test_diagonal_edits_the_controller_has_not_answered_yet_compose():
    link = BusyLink()
    tuning = TuningFrontEnd(link, KEY, allow_tuning=True)
    out = _set(tuning, gains__alpha_1=0.1)  # unanswered in time: it may still take effect
    assert "no answer" in out["hil.last_outcome"]
    _set(tuning, gains__alpha_2=0.2)
    link.service.due(TICK)  # the loop reaches the boundary: both sets land, in order
    assert link.service.cfg.gains.alpha == ((0.1, 0.0), (0.0, 0.2))


def test_a_whole_matrix_edit_keeps_an_unanswered_diagonal_edit():
    link = BusyLink()
    tuning = TuningFrontEnd(link, KEY, allow_tuning=True)
    shown = _set(tuning, gains__alpha_1=0.1)["gains.alpha"]  # the controller's value
    shown[0][1] = shown[1][0] = 0.01  # the panel's edit: the off-diagonal entries only
    _set(tuning, gains__alpha=shown)
    link.service.due(TICK)
    assert link.service.cfg.gains.alpha == ((0.1, 0.01), (0.01, 0.15))


def test_an_edit_that_would_undo_an_unanswered_scheduled_edit_is_refused_visibly():
    link = BusyLink()
    tuning = TuningFrontEnd(link, KEY, allow_tuning=True)
    _set(tuning, gains__alpha_1=0.1, hil__at_tick=TICK + 5)
    out = _set(tuning, gains__alpha_2=0.2)  # for the next tick, before that one lands
    assert out["hil.last_outcome"].startswith("refused")
    assert f"tick {TICK + 5}" in out["hil.last_outcome"]
    assert out["gains.alpha"] == [[0.05, 0.0], [0.0, 0.15]]  # the unchanged value
    link.service.due(TICK + 5)
    assert link.service.cfg.gains.alpha == ((0.1, 0.0), (0.0, 0.15))
    assert link.service.param_set == 1  # the refused one never reached the controller
    _set(tuning, gains__alpha_2=0.2)  # said again: now it starts from the landed value
    link.service.due(TICK + 6)
    assert link.service.cfg.gains.alpha == ((0.1, 0.0), (0.0, 0.2))


def test_a_fault_in_a_callback_is_said_once_counted_and_answered_with_the_values(caplog):
    link = BrokenLink()
    tuning = TuningFrontEnd(link, KEY, allow_tuning=True)
    assert _set(tuning, gains__kp=0.2)["gains.kp"] == 0.2
    link.broken = True
    caplog.set_level(logging.ERROR, logger="rt_controller.monitor.tuning")
    out = _set(tuning, gains__kp=0.3)
    assert out["gains.kp"] == 0.2  # the last value known: unchanged
    assert "zenoh session closed" in out["hil.last_outcome"]
    got = tuning.on_get_parameters(CLIENT, ["gains.kp"])
    assert [(p.name, p.get_value()) for p in got] == [("gains.kp", 0.2)]
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "RuntimeError: zenoh session closed" in errors[0]
    assert "\n" not in errors[0]
    assert tuning.failed == 2


class SilentLink(LoopbackLink):
    """A controller that does not answer (yet): every request times out."""

    def get(self, key, payload, timeout):
        return []


def test_a_token_refused_while_the_controller_is_silent_says_the_refusal():
    """A monitor started before its controller answers: a wrong token is refused for what it
    is, and a silent controller is the link's answer, not a fault of the monitor's."""
    from rt_controller.monitor.access import AccessGate

    tuning = TuningFrontEnd(SilentLink(), KEY, allow_tuning=True, gate=AccessGate("token", KEY))
    out = _set(tuning, hil__token="not the token")
    assert "token" in out["hil.last_outcome"] and "no answer" not in out["hil.last_outcome"]
    open_gate = TuningFrontEnd(SilentLink(), KEY, allow_tuning=True)
    assert "no answer" in _set(open_gate, gains__kp=0.3)["hil.last_outcome"]
    assert tuning.failed == open_gate.failed == 0
