"""``hil up``'s table says what its rows count: ``rejections`` lists only rejections (the
accepted and received counts of the same block are the ``input_counts`` row), and the recorder's
``written`` says it is the messages of the topics listed, not every message of the log (the
writer's /scene, /camera and /tf drawings are not counted)."""

from __future__ import annotations

from rt_controller.commands.up import table_view

REJECTIONS = {
    "can_rx": {"accepted": 357, "ignored": 0, "lost": 0, "bad_crc": 2, "rejected": 2},
    "features": {
        "received": 193,
        "accepted": 190,
        "stale_age": 3,
        "stale": 3,
        "rejected": 3,
        "repeats": 4,
        "resyncs": 0,
    },
    "dsp_rejected_frames": 1,
}


def test_rejections_lists_only_rejections():
    table = table_view({"rejections": REJECTIONS})
    assert table["rejections"] == (
        "can_rx.bad_crc 2, can_rx.rejected 2, features.stale_age 3, features.stale 3, "
        "features.rejected 3, dsp_rejected_frames 1"
    )
    assert table["input_counts"] == (
        "can_rx.accepted 357, features.received 193, features.accepted 190, features.repeats 4"
    )


def test_a_run_without_rejections_says_none():
    ok = {"can_rx": {"accepted": 357, "bad_crc": 0}, "features": {"received": 193}}
    table = table_view({"rejections": {**ok, "dsp_rejected_frames": 0}})
    assert table["rejections"] == "none"
    assert table["input_counts"] == "can_rx.accepted 357, features.received 193"


def test_the_recorder_row_says_what_written_counts():
    recorder = {"/controller/cycle": 150, "/hal/can/rx": 357, "written": 507, "dropped": 0}
    row = table_view({"recorder": recorder})["recorder"]
    assert row.startswith("/controller/cycle 150, /hal/can/rx 357, written 507 (")
    assert "topics listed" in row and "/scene" in row and "/camera" in row


def test_a_cia402_run_counts_its_syncs_as_input_not_rejection():
    can_rx = {"authenticated": False, "syncs_sent": 205}  # CiA 402: SYNCs sent, no MAC judged
    table = table_view({"rejections": {"can_rx": can_rx, "features": {"received": 40}}})
    assert table["rejections"] == "none"
    assert table["input_counts"] == "can_rx.syncs_sent 205, features.received 40"


def test_the_links_own_counts_are_inputs_but_a_driver_error_is_shown_as_a_problem():
    can_rx = {"accepted": 50, "foreign_stamps": 50, "drains_cut": 1, "transport_errors": 2}
    table = table_view({"rejections": {"can_rx": can_rx}})
    assert table["rejections"] == "can_rx.transport_errors 2"
    assert table["input_counts"] == (
        "can_rx.accepted 50, can_rx.foreign_stamps 50, can_rx.drains_cut 1"
    )
