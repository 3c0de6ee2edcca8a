"""Wire format of the vision link: round trips, malformed and stale rejection (counted), fuzz."""

from __future__ import annotations

import math
import random
import struct
import threading

import pytest

from hal.errors import HalCodecError
from hal.vision_codec import (
    FEATURES_SIZE,
    POSE_SIZE,
    FeatureMsg,
    PoseMsg,
    decode_features,
    decode_pose,
    encode_features,
    encode_pose,
)
from hal.vision_receivers import REJECTION_FIELDS, FeatureDecoder, PoseDecoder

NOW = 10_000_000_000


def feat(frame: int = 1, pose_seq: int = 1, **kw) -> FeatureMsg:
    base = dict(
        frame=frame,
        stamp_ns=NOW,
        sim_time_ns=20_000_000,
        pose_seq=pose_seq,
        f=(-120.0, -160.0),
        valid=True,
        lockstep=False,
        source=7,
    )
    base.update(kw)
    return FeatureMsg(**base)


@pytest.mark.parametrize(("image", "flags"), [(False, 0x03), (True, 0x07)])
def test_features_round_trip_is_bit_exact(image, flags):
    """Bit2 says the frame's camera image follows for the log."""
    msg = feat(
        frame=2**40,
        pose_seq=2**63,
        f=(math.pi, -1e-300),
        lockstep=True,
        source=2**32 - 1,
        image=image,
    )
    buf = encode_features(msg)
    assert len(buf) == FEATURES_SIZE == 72
    assert buf[:4] == b"HF\x02" + bytes([flags])
    assert decode_features(buf) == msg
    assert msg.as_dict()["f"] == [math.pi, -1e-300]


@pytest.mark.parametrize(("seed", "flags"), [(None, 0x01), (0, 0x03), (2**64 - 1, 0x03)])
def test_pose_round_trip(seed, flags):
    """Camera pose v3: the run's noise seed travels with its flag (None: no seed named)."""
    msg = PoseMsg(5, 100_000_000, NOW, 0.45, 0.13, 0.0, True, 3, seed)
    buf = encode_pose(msg)
    assert len(buf) == POSE_SIZE == 80
    assert buf[:4] == b"HP\x03" + bytes([flags])
    assert struct.unpack_from("<Q", buf, 56) == (seed or 0,)
    assert decode_pose(buf) == msg


def test_a_pose_of_another_version_or_with_a_stray_seed_is_refused():
    """A v2 pose (no seed field) is a bad version; a seed without its flag a bad value; a seed
    that is not an integer is refused at encode."""
    good = encode_pose(PoseMsg(1, 0, 0, 0.1, 0.2, 0.3, True, 9, 4))
    with pytest.raises(HalCodecError, match="bad_version"):
        decode_pose(good[:2] + b"\x02" + good[3:])
    with pytest.raises(HalCodecError, match="bad_value"):
        decode_pose(good[:3] + b"\x01" + good[4:])
    with pytest.raises(HalCodecError, match="seed"):
        encode_pose(PoseMsg(1, 0, 0, 0.1, 0.2, 0.3, True, 9, 1.5))  # type: ignore[arg-type]


def test_little_endian_layout_is_documented_one():
    buf = encode_features(feat(frame=9, pose_seq=4, f=(1.5, -2.0)))
    fields = struct.unpack("<2sBBIQqqQdd16s", buf)
    magic, ver, flags, src, frame, stamp, sim, seq, fx, fy, _mac = fields
    assert (magic, ver, flags, src, frame, stamp, sim, seq, fx, fy) == (
        b"HF",
        2,
        1,
        7,
        9,
        NOW,
        20_000_000,
        4,
        1.5,
        -2.0,
    )


@pytest.mark.parametrize("f", [(math.nan, 0.0), (0.0, math.inf)])
def test_encoder_refuses_non_finite(f):
    with pytest.raises(HalCodecError):
        encode_features(feat(f=f))
    with pytest.raises(HalCodecError):
        encode_pose(PoseMsg(0, 0, 0, f[0], f[1], 0.0))


def test_encoder_refuses_out_of_range_counters():
    with pytest.raises(HalCodecError):
        encode_features(feat(frame=-1))


def test_decode_errors_name_the_problem():
    good = encode_features(feat())
    with pytest.raises(HalCodecError, match="bad_size"):
        decode_features(good[:-1])
    with pytest.raises(HalCodecError, match="bad_magic"):
        decode_features(b"XX" + good[2:])
    with pytest.raises(HalCodecError, match="bad_version"):
        decode_features(good[:2] + b"\x01" + good[3:])
    with pytest.raises(HalCodecError, match="bad_size"):
        decode_features(encode_pose(PoseMsg(0, 0, 0, 0.0, 0.0, 0.0)))
    with pytest.raises(HalCodecError, match="bad_magic"):
        decode_features(encode_pose(PoseMsg(0, 0, 0, 0.0, 0.0, 0.0))[: len(good)])


def test_decoder_keeps_latest_valid_with_receive_time():
    d = FeatureDecoder(clock=lambda: NOW)
    assert d.latest is None and d.age_ns() is None
    assert d.feed(encode_features(feat(frame=1)), NOW + 5) is not None
    assert d.feed(encode_features(feat(frame=2, valid=False, f=(0.0, 0.0))), NOW + 6) is not None
    assert d.latest.frame == 1 and d.latest_recv_ns == NOW + 5
    assert d.last.frame == 2 and d.counts.invalid == 1
    assert d.age_ns(NOW + 1_000) == 1_000


def test_decoder_rejects_stale_by_age_but_not_lockstep():
    d = FeatureDecoder(max_age_ns=50_000_000)
    old = NOW - 60_000_000
    assert d.feed(encode_features(feat(frame=1, stamp_ns=old)), NOW) is None
    assert d.counts.stale_age == 1
    # lockstep messages are judged in simulation time by the controller, not by wall age
    assert d.feed(encode_features(feat(frame=1, stamp_ns=old, lockstep=True)), NOW) is not None
    assert d.sim_age_ns(60_000_000) == 40_000_000


def test_decoder_rejects_replays_and_backwards_frames():
    d = FeatureDecoder(max_age_ns=None, clock=lambda: NOW)
    a, b = encode_features(feat(frame=5, pose_seq=5)), encode_features(feat(frame=4, pose_seq=6))
    assert d.feed(a) is not None
    assert d.feed(a) is None  # replay
    assert d.feed(b) is None  # frame counter going backwards
    assert d.counts.stale_order == 2 and d.counts.accepted == 1


def test_lockstep_resend_of_same_frame_for_newer_pose_is_accepted():
    d = FeatureDecoder(max_age_ns=None, clock=lambda: NOW)
    for seq in (10, 11, 12):
        assert d.feed(encode_features(feat(frame=3, pose_seq=seq, lockstep=True))) is not None
    assert d.pose_seq == 12 and d.counts.repeats == 2 and d.counts.rejected == 0


def test_publisher_restart_resets_ordering():
    # A restarted publisher (new source id) takes over once the old one was silent long enough.
    d = FeatureDecoder(max_age_ns=None, source_takeover_ns=1_000, clock=lambda: NOW)
    d.feed(encode_features(feat(frame=100, pose_seq=100, source=1)), NOW)
    assert d.feed(encode_features(feat(frame=0, pose_seq=0, source=2)), NOW + 999) is None
    assert d.feed(encode_features(feat(frame=0, pose_seq=0, source=2)), NOW + 1_000) is not None
    assert d.counts.source_changes == 1 and d.pose_seq == 0 and d.counts.foreign_source == 1


def test_corrupt_huge_counter_cannot_lock_the_receiver_out():
    d = FeatureDecoder(max_age_ns=None, resync_after=3, clock=lambda: NOW)
    d.feed(encode_features(feat(frame=2**63, pose_seq=0)))
    results = [d.feed(encode_features(feat(frame=k, pose_seq=k))) for k in range(1, 5)]
    assert [r is not None for r in results] == [False, False, True, True]
    assert d.counts.resyncs == 1 and d.counts.stale_order == 2


def test_wait_pose_seq_wakes_on_answer():
    d = FeatureDecoder(max_age_ns=None, clock=lambda: NOW)
    assert d.wait_pose_seq(3, 0.01) is None
    t = threading.Timer(0.05, lambda: d.feed(encode_features(feat(frame=1, pose_seq=3))))
    t.start()
    try:
        got = d.wait_pose_seq(3, 5.0)
    finally:
        t.join()
    assert got is not None and got.pose_seq == 3


def test_pose_decoder_counts_and_orders():
    d = PoseDecoder()
    p = encode_pose(PoseMsg(1, 0, 0, 0.1, 0.2, 0.3, False, 9))
    assert d.feed(p) is not None
    assert d.feed(p) is None
    assert d.feed(b"garbage") is None
    assert d.feed(None) is None  # type: ignore[arg-type]
    c = d.counts
    assert (c.accepted, c.stale_order, c.bad_size, c.bad_type) == (1, 1, 1, 1)


def _mutate(rng: random.Random, good: bytes) -> tuple[bytes, str]:
    """A bad payload and the counter it must land in."""
    kind = rng.randrange(7)
    if kind == 0:  # random bytes of a wrong size
        n = rng.choice([n for n in range(0, 120) if n != FEATURES_SIZE])
        return rng.randbytes(n), "bad_size"
    if kind == 1:  # truncated or extended
        return (good[: rng.randrange(FEATURES_SIZE)] if rng.random() < 0.5 else good + b"\0"), (
            "bad_size"
        )
    if kind == 2:
        magic = rng.randbytes(2)
        while magic == b"HF":
            magic = rng.randbytes(2)
        return magic + good[2:], "bad_magic"
    if kind == 3:
        return good[:2] + bytes([rng.choice([0, 1, *range(3, 256)])]) + good[3:], "bad_version"
    if kind == 4:
        return good[:3] + bytes([rng.randrange(8, 256)]) + good[4:], "bad_flags"
    if kind == 5:
        bad = rng.choice([math.nan, math.inf, -math.inf])
        off = rng.choice([40, 48])
        return good[:off] + struct.pack("<d", bad) + good[off + 8 :], "bad_value"
    # random size-correct bytes: flags or value or magic almost surely wrong
    buf = bytearray(rng.randbytes(FEATURES_SIZE))
    buf[0:2] = b"HF" if rng.random() < 0.5 else buf[0:2]
    return bytes(buf), "random"


BUCKETS = ("accepted", *(k for k in REJECTION_FIELDS if k != "bad_mac"))
"""The counters of :class:`RxCounts` of which every message increments exactly one (these
messages all carry the rig key's MAC)."""


def test_fuzz_5000_payloads_no_crash_every_bad_one_counted():
    """Every feed lands in exactly one bucket, and the one the test knows it must (an oracle
    per message, so a double count or a wrong bucket fails, not only a missing count)."""
    rng = random.Random(1234)
    d = FeatureDecoder(max_age_ns=50_000_000, clock=lambda: NOW)
    expected = dict.fromkeys(BUCKETS, 0)
    frame = 0
    random_fed = 0

    def feed(payload: bytes, bucket: str | None) -> object:
        """Feed one payload; check it landed in ``bucket`` (any one bucket when None)."""
        before = [getattr(d.counts, k) for k in BUCKETS]
        received = d.counts.received
        msg = d.feed(payload, NOW)
        delta = {k: getattr(d.counts, k) - b for k, b in zip(BUCKETS, before, strict=True)}
        assert d.counts.received == received + 1
        assert sorted(delta.values()) == [0] * (len(BUCKETS) - 1) + [1], delta
        landed = next(k for k, v in delta.items() if v)
        assert bucket is None or landed == bucket, (bucket, landed)
        assert (landed == "accepted") == (msg is not None)
        expected[landed] += 1
        return msg

    for i in range(5000):
        if i % 5 == 0:  # interleave good traffic so the decoder keeps moving
            frame += 1
            feed(encode_features(feat(frame=frame, pose_seq=frame)), "accepted")
            continue
        if i % 5 == 1:  # a replay (not newer than the last accepted) or an old message
            if rng.random() < 0.5:
                feed(encode_features(feat(frame=frame, pose_seq=frame)), "stale_order")
            else:
                feed(encode_features(feat(frame=frame + 1, stamp_ns=NOW - 10**9)), "stale_age")
            continue
        payload, kind = _mutate(rng, encode_features(feat(frame=frame + 1, pose_seq=frame + 1)))
        if kind == "random":  # any one bucket; which one is the decoder's call
            random_fed += 1
            msg = feed(payload, None)
            if msg is not None:  # astronomically unlikely but legal: keep the books straight
                frame = max(frame, msg.frame)
            continue
        feed(payload, kind)
    c = d.counts
    assert c.received == 5000
    assert {k: getattr(c, k) for k in BUCKETS} == expected  # exact, bucket by bucket
    assert c.accepted + c.rejected == 5000  # every message lands in one bucket
    assert c.malformed == sum(expected[k] for k in BUCKETS if k.startswith("bad_"))
    for kind in ("bad_size", "bad_magic", "bad_version", "bad_flags", "bad_value"):
        assert expected[kind] > 0, kind  # every mutation kind was exercised
    assert expected["stale_order"] > 0 and expected["stale_age"] > 0
    assert random_fed > 0 and c.bad_type == 0
    assert d.latest is not None and d.latest.frame == frame
