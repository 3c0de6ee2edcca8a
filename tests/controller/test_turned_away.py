"""The start-up error's account of inputs that came and were refused, with the likeliest
cause: another rig key (bad MAC), or a sender's clock off by more than SecOC's window."""

from __future__ import annotations

from hal.e2e import E2EStats, Verdict
from hal.vision_receivers import RxCounts
from rt_controller.runtime.hardware import turned_away


def test_nothing_refused_says_nothing():
    assert turned_away(E2EStats().rejections(), RxCounts().rejections()) == ""


def test_a_bad_mac_names_the_key():
    can = E2EStats()
    for _ in range(3):
        can.record(Verdict.BAD_MAC)
    can.record(Verdict.OK)
    said = turned_away(can.rejections(), RxCounts(bad_mac=2, accepted=5).rejections())
    assert said == (
        "3 DSP frames rejected (bad_mac 3); 2 feature messages rejected (bad_mac 2); "
        "signed with another rig key? (every process needs the same --key-file)"
    )


def test_freshness_names_the_clock():
    can = E2EStats()
    can.record(Verdict.FUTURE_FRESHNESS)
    can.record(Verdict.STALE_FRESHNESS)
    said = turned_away(can.rejections(), {})
    assert said.startswith("2 DSP frames rejected (stale_freshness 1, future_freshness 1); ")
    assert said.endswith("is the DSP's clock within 1 s of this host's? (SecOC freshness: PTP/NTP)")


def test_features_from_the_future_name_the_camera_s_host():
    """Capture stamps are the capturing host's CLOCK_MONOTONIC, which no PTP aligns."""
    said = turned_away({}, RxCounts(future_stamp=7).rejections())
    assert said == (
        "7 feature messages rejected (future_stamp 7); features stamped ahead of this host's "
        "monotonic clock: a camera must run on the controller's host (no two hosts share a "
        "monotonic clock)"
    )


def test_other_rejections_are_listed_without_a_guess():
    assert turned_away({}, RxCounts(bad_size=4, stale_age=1).rejections()) == (
        "5 feature messages rejected (bad_size 4, stale_age 1)"
    )
