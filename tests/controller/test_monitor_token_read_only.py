"""``hil.token`` set on a plain loopback monitor without ``--allow-tuning``: the answer says no
token is needed, and does not claim the client "may change the rig" (every set is refused
there; only the mark is offered)."""

from __future__ import annotations

from tests.support.param_link import tuning_monitor


def _answer(allow_tuning: bool) -> str:
    with tuning_monitor(allow_tuning) as (_, client):
        return client.set_parameters({"hil.token": "abc"}, timeout=30)["hil.last_outcome"]


def test_the_token_answer_of_a_read_only_monitor_says_it_is_read_only() -> None:
    line = _answer(allow_tuning=False)
    assert line.startswith("no access token is needed"), line
    assert "may change the rig" not in line and "--allow-tuning" in line, line


def test_the_token_answer_of_a_tuning_monitor_says_who_may_change_the_rig() -> None:
    line = _answer(allow_tuning=True)
    assert line.startswith("no access token is needed") and "may change the rig" in line, line
