"""``hil up``'s table never prints a Python ``None``: a figure that does not apply to the run
(RHC's horizon and steps under another law, the host's steal time in lockstep) or an event that
did not happen (the target's jump not seen) says so in words; ``--json`` keeps the nulls."""

from __future__ import annotations

from rt_controller.commands.up import table_view


def test_the_table_says_in_words_what_none_means():
    summary = {
        "clock": "lockstep",
        "law": "ioc",
        "horizon_s": None,
        "steps": None,
        "jump_seen_s": None,
        "host_steal_percent": None,
        "ticks": 100,
    }
    table = table_view(summary)
    assert None not in table.values(), table
    assert "rhc" in table["horizon_s"] and "rhc" in table["steps"]
    assert table["jump_seen_s"] == "not seen"
    assert summary["horizon_s"] is None  # the summary itself (--json) is left as it is


def test_figures_that_apply_are_left_as_they_are():
    summary = {"law": "rhc", "horizon_s": 0.1, "steps": 10, "jump_seen_s": 3.02, "ticks": 5}
    assert table_view(summary) == summary
