"""Feature freshness that cannot be bypassed (hal.vision_codec.FeatureDecoder): future stamps,
foreign sources and backwards stamps are rejected and counted exactly; the staleness age uses
both the capture stamp and the receive time. Pure: fake clock, no wall-clock windows."""

from __future__ import annotations

import pytest

from hal.config import RigConfig
from hal.vision_codec import FeatureMsg, encode_features
from hal.vision_receivers import FeatureDecoder, feature_age_ns

NOW = 50_000_000_000
MS = 1_000_000


def msg(frame: int, stamp_ns: int, *, source: int = 7, lockstep: bool = False) -> bytes:
    return encode_features(
        FeatureMsg(
            frame,
            stamp_ns,
            (frame % 1000) * 20 * MS,
            frame,
            (-120.0, -160.0),
            True,
            lockstep,
            source,
        )
    )


def decoder(**kw: object) -> FeatureDecoder:
    kw.setdefault("max_age_ns", 100 * MS)
    kw.setdefault("max_clock_skew_ns", 5 * MS)
    kw.setdefault("source_takeover_ns", 1_000 * MS)
    return FeatureDecoder(clock=lambda: NOW, **kw)  # type: ignore[arg-type]


def rejections(d: FeatureDecoder) -> dict[str, int]:
    c = d.as_dict()
    keys = ("future_stamp", "foreign_source", "backwards_stamp", "stale_age", "stale_order")
    return {k: c[k] for k in keys if c[k]}


def test_future_stamp_beyond_skew_is_rejected_and_counted():
    d = decoder()
    assert d.feed(msg(1, NOW + 5 * MS), NOW) is not None  # exactly the allowed skew
    assert d.feed(msg(2, NOW + 5 * MS + 1), NOW) is None
    assert d.feed(msg(3, NOW + 3_600 * 10**9), NOW) is None  # the f_age -3596 s
    assert rejections(d) == {"future_stamp": 2}
    c = d.as_dict()
    assert (c["accepted"], c["untrusted"], c["rejected"]) == (1, 2, 2)
    assert d.latest.frame == 1


def test_a_future_stamp_cannot_switch_the_stale_check_off():
    """The accepted message's age comes from the receive time once the stamp is ahead: a
    vision process that dies leaves the features going stale on schedule."""
    d = decoder()
    d.feed(msg(1, NOW + 4 * MS), NOW)  # within the skew, accepted
    assert d.age_ns(NOW) == 0  # never negative
    assert d.age_ns(NOW + 150 * MS) == 150 * MS  # by receive time
    assert d.fresh_latest(100 * MS, NOW + 99 * MS) is not None
    assert d.fresh_latest(100 * MS, NOW + 101 * MS) is None


@pytest.mark.parametrize(
    ("now", "stamp", "recv", "age"),
    [
        (100, 90, 95, 10),  # stamp older: age by stamp
        (100, 99, 50, 50),  # arrived long ago: age by receive time
        (100, 150, 100, 0),  # stamp in the future, just received: 0, not -50
        (100, 10**12, 40, 60),
    ],
)
def test_feature_age_uses_stamp_and_receive_time(now, stamp, recv, age):
    assert feature_age_ns(now, stamp, recv) == age


def test_foreign_source_is_rejected_while_the_locked_one_is_alive():
    d = decoder()
    assert d.feed(msg(1, NOW, source=1), NOW) is not None
    assert d.source == 1
    # another publisher interleaves, even with newer counters: rejected, every time
    for k in range(5):
        assert d.feed(msg(100 + k, NOW + k * MS, source=2), NOW + k * MS) is None
        assert d.feed(msg(2 + k, NOW + k * MS, source=1), NOW + k * MS) is not None
    assert rejections(d) == {"foreign_source": 5}
    assert d.as_dict()["source_changes"] == 0 and d.latest.source == 1
    # once the locked source was silent for the takeover time, a new one may take over
    later = NOW + 4 * MS + 1_000 * MS
    assert d.feed(msg(0, later, source=2), later) is not None
    assert d.source == 2 and d.as_dict()["source_changes"] == 1
    # and now the old one is the foreign one
    assert d.feed(msg(99, later + MS, source=1), later + MS) is None
    assert rejections(d) == {"foreign_source": 6}


def test_takeover_none_never_switches_source_without_reset():
    d = decoder(source_takeover_ns=None)
    d.feed(msg(1, NOW, source=1), NOW)
    late = NOW + 3_600 * 10**9
    assert d.feed(msg(2, late, source=2), late) is None
    d.reset()
    assert d.feed(msg(2, late, source=2), late) is not None


def test_backwards_stamp_and_frame_are_rejected_and_counted_by_reason():
    d = decoder()
    assert d.feed(msg(10, NOW), NOW) is not None
    assert d.feed(msg(11, NOW - 1), NOW) is None  # newer frame, older stamp
    assert d.feed(msg(9, NOW + 1), NOW + 1) is None  # newer stamp, older frame
    assert d.feed(msg(10, NOW + 2), NOW + 2) is None  # same frame again
    assert rejections(d) == {"backwards_stamp": 1, "stale_order": 2}
    assert d.as_dict()["accepted"] == 1


def test_resync_after_a_corrupt_counter_never_admits_an_older_stamp():
    d = decoder(resync_after=2)
    assert d.feed(msg(2**40, NOW), NOW) is not None  # corrupt, huge frame counter
    assert d.feed(msg(1, NOW + 1), NOW + 1) is None  # stale_order
    assert d.feed(msg(2, NOW - 1), NOW + 2) is None  # an older stamp never resyncs
    assert d.feed(msg(3, NOW + 3), NOW + 3) is not None  # fresh: resync
    assert rejections(d) == {"stale_order": 1, "backwards_stamp": 1}
    assert d.as_dict()["resyncs"] == 1


def test_every_message_lands_in_exactly_one_bucket():
    d = decoder()
    feeds = [
        (msg(1, NOW), NOW),
        (msg(2, NOW + 10 * MS), NOW),  # future
        (msg(2, NOW - 200 * MS), NOW),  # stale_age
        (msg(2, NOW, source=9), NOW),  # foreign
        (msg(2, NOW - 1), NOW),  # backwards stamp
        (msg(1, NOW), NOW),  # replay: stale_order
        (b"junk", NOW),  # bad_size
        (msg(2, NOW + 1), NOW + 1),
    ]
    for payload, t in feeds:
        d.feed(payload, t)
    c = d.as_dict()
    assert c["received"] == len(feeds) == c["accepted"] + c["rejected"]
    assert {k: c[k] for k in ("accepted", "future_stamp", "stale_age", "foreign_source",
                              "backwards_stamp", "stale_order", "bad_size")} == {
        "accepted": 2, "future_stamp": 1, "stale_age": 1, "foreign_source": 1,
        "backwards_stamp": 1, "stale_order": 1, "bad_size": 1,
    }  # fmt: skip


def test_lockstep_messages_are_judged_by_sim_time_but_still_source_locked():
    d = decoder()
    old = NOW - 10**12  # a republished lockstep log: monotonic stamps of another boot
    assert d.feed(msg(1, old, lockstep=True, source=3), NOW) is not None
    assert d.feed(msg(2, NOW + 10**12, lockstep=True, source=3), NOW) is not None
    assert d.feed(msg(3, NOW, lockstep=True, source=4), NOW) is None
    assert rejections(d) == {"foreign_source": 1}


def test_from_config_uses_the_controller_keys():
    cfg = RigConfig().with_overrides(
        {"controller.max_clock_skew_s": 0.002, "controller.feature_source_takeover_s": 0.5}
    )
    d = FeatureDecoder.from_config(cfg.controller)
    assert d.max_clock_skew_ns == 2 * MS and d.source_takeover_ns == 500 * MS
    assert d.max_age_ns == round(cfg.controller.feature_timeout_s * 1e9)
