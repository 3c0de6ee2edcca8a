"""``hil controller``'s summary table (and ``hil up``'s, the same view): every block of counts
in words (``accepted 2, refused 0``; ``none`` for an empty one), never a Python dict; ``--json``
prints the summary as it is."""

from __future__ import annotations

import json

from hal.bus import BusSpec
from rt_controller.commands.controller import shown
from rt_controller.commands.output import print_summary

BUS = BusSpec("udp_multicast", "239.75.0.1", {"port": 35188})


def summary() -> dict:
    """A lone controller's summary, as its daemon returns it (the blocks that matter here)."""
    return {
        "law": "ioc",
        "can": "auto",
        "ticks": 50,
        "drive_ticks": {"disarmed": 8, "no_status": 2},
        "dsp_faults": {},
        "parameters": {"accepted": 2, "refused": 0, "unauthenticated": 0},
        "recorder": {"written": 340, "dropped": 0},
        "problems": [],
    }


def table_rows(out: str) -> dict[str, str]:
    """The two-column table printed by :func:`print_summary`, as key -> value."""
    return {
        cells[1].strip(): cells[2].strip()
        for line in out.splitlines()
        if len(cells := line.split("│")) == 4
    }


def test_the_table_words_every_block_of_counts(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    print_summary(shown(summary(), BUS, as_json=False), False, "hil controller")
    rows = table_rows(capsys.readouterr().out)
    assert rows["drive_ticks"] == "disarmed 8, no_status 2", rows
    assert rows["dsp_faults"] == "none", rows
    assert rows["parameters"] == "accepted 2, refused 0, unauthenticated 0", rows
    # zero counters left out, as before
    assert rows["recorder"].startswith("written 340 (the topics listed"), rows
    assert rows["can"] == "udp_multicast:239.75.0.1:35188", rows
    assert rows["problems"] == "none", rows  # an empty list, not a blank cell
    assert not [k for k, v in rows.items() if "{" in v], rows


def test_a_nested_block_is_flattened_to_dotted_keys():
    table = shown({"exit_codes": {"rig": {"emulator": 0, "vision": -15}}}, BUS, as_json=False)
    assert table["exit_codes"] == "rig.emulator 0, rig.vision -15"


def test_json_is_the_summary_unchanged(capsys):
    print_summary(shown(summary(), BUS, as_json=True), True, "hil controller")
    assert json.loads(capsys.readouterr().out) == {**summary(), "can": str(BUS)}
