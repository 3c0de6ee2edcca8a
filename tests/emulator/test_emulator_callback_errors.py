"""An exception in one of the emulator's zenoh callbacks (swallowed by the session, counted in
its ``callback_errors``) is in the emulator's final summary and a warning line: a lost sim
control command or region request is never silent."""

from __future__ import annotations

import time

import pytest

from hal.config import RigConfig
from hal.secoc import rig_key
from hal.sim_control import SimControlSender
from hal.zenoh_session import open_session
from plant_emulator.entry import callback_errors_text, serve_sim_control, with_callback_errors


class FailingNode:
    """A plant whose reset fails (a bug in the sim link's path)."""

    def request_reset(self, seed: int | None = None) -> bool:
        raise RuntimeError("the reset failed")


def test_a_failed_sim_control_callback_is_in_the_summary(
    endpoint: str, capsys: pytest.CaptureFixture[str]
) -> None:
    key = rig_key(RigConfig())
    with open_session(listen=True, endpoint=endpoint) as session:
        assert with_callback_errors({}, session)["callback_errors"] == 0
        with serve_sim_control(session, FailingNode(), key) as receiver:
            SimControlSender(session, key=key).reset_scenario(7)
            deadline = time.monotonic() + 10
            while session.callback_errors < 1 and time.monotonic() < deadline:
                time.sleep(0.01)
            summary = with_callback_errors({"mode": "realtime"}, session)
    assert receiver.counts.accepted == 1
    assert summary == {"mode": "realtime", "callback_errors": 1}
    assert callback_errors_text(summary) == ", 1 zenoh callback errors"
    assert "warning: 1 zenoh message(s) lost to errors in callbacks" in capsys.readouterr().err


def test_without_a_session_there_is_no_count(capsys: pytest.CaptureFixture[str]) -> None:
    summary = with_callback_errors({}, None)
    assert summary == {"callback_errors": None} and callback_errors_text(summary) == ""
    assert capsys.readouterr().err == ""
