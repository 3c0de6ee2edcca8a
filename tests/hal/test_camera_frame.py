"""Wire format of camera frames: round trip, malformed and mis-sized frames rejected and counted;
regions of interest (their offset authenticated) and the grabber's region requests."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from hal.camera_frame import (
    HEADER_SIZE,
    ROI_SIZE,
    FrameDecoder,
    RoiRequest,
    decode_frame,
    decode_roi_request,
    encode_frame,
    encode_roi_request,
    frame_size,
)
from hal.errors import HalCodecError

KEY = b"k" * 32


def pixels(w: int = 64, h: int = 48, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)


def frame(seq: int = 3, period: int = 7, lockstep: bool = True, img=None, **kw) -> bytes:
    args = dict(
        seq=seq,
        stamp_ns=123_456_789,
        sim_time_ns=140_000_000,
        exposure_ns=4_000_000,
        period=period,
        lockstep=lockstep,
        source=0xABCDEF,
        key=KEY,
    )
    args.update(kw)
    return encode_frame(pixels() if img is None else img, **args)


def test_round_trip_is_exact_and_zero_copy():
    img = pixels(640, 480, seed=4)
    buf = frame(img=img)
    assert len(buf) == frame_size(640, 480)
    out = decode_frame(buf)
    assert (out.seq, out.period, out.stamp_ns, out.sim_time_ns) == (3, 7, 123_456_789, 140_000_000)
    assert (out.exposure_ns, out.lockstep, out.source, out.encoding) == (
        4_000_000,
        True,
        0xABCDEF,
        "mono8",
    )
    assert (out.width, out.height) == (640, 480)
    np.testing.assert_array_equal(out.pixels, img)
    assert not out.pixels.flags.writeable
    assert np.shares_memory(out.pixels, np.frombuffer(buf, np.uint8))


def test_decoder_accepts_authentic_frames_in_order():
    dec = FrameDecoder(key=KEY)
    assert dec.feed(frame(seq=0, period=0)) is not None
    assert dec.feed(frame(seq=1, period=1)) is not None
    assert dec.as_dict()["accepted"] == 2
    assert dec.last is not None and dec.last.seq == 1


@pytest.mark.parametrize(
    ("mangle", "counter"),
    [
        (lambda b: b[:-1], "bad_size"),
        (lambda b: b + b"\0", "bad_size"),
        (lambda b: b[:20], "bad_size"),
        (lambda b: b"", "bad_size"),
        (lambda b: b"XX" + b[2:], "bad_magic"),
        (lambda b: b[:2] + b"\x09" + b[3:], "bad_version"),
        (lambda b: b[:3] + b"\x80" + b[4:], "bad_flags"),
        (lambda b: b[:52] + b"\x07" + b[53:], "bad_value"),
        (lambda b: b[:48] + struct.pack("<H", 0) + b[50:], "bad_value"),
        (
            lambda b: b[:48] + struct.pack("<H", 65) + b[50:60] + struct.pack("<H", 65) + b[62:],
            "bad_size",
        ),
        (lambda b: b[:48] + struct.pack("<H", 65) + b[50:], "bad_value"),  # wider than the sensor
        (lambda b: b[:56] + struct.pack("<H", 1) + b[58:], "bad_value"),  # offset: outside
        (lambda b: b[:60] + struct.pack("<H", 0) + b[62:], "bad_value"),
        (lambda b: b[:32] + struct.pack("<q", -1) + b[40:], "bad_value"),
        (
            lambda b: b[: HEADER_SIZE + 5] + bytes([b[HEADER_SIZE + 5] ^ 1]) + b[HEADER_SIZE + 6 :],
            "bad_mac",
        ),
        (lambda b: 42, "bad_type"),
    ],
)
def test_malformed_frames_are_rejected_and_counted(mangle, counter):
    bad = mangle(frame())
    dec = FrameDecoder(key=KEY)
    assert dec.feed(bad) is None
    c = dec.as_dict()
    assert c[counter] == 1 and c["received"] == 1 and c["rejected"] == 1 and c["accepted"] == 0
    if counter != "bad_mac":
        with pytest.raises(HalCodecError, match=counter):
            decode_frame(bad)


def test_other_rigs_key_is_rejected():
    dec = FrameDecoder(key=b"x" * 32)
    assert dec.feed(frame()) is None
    assert dec.as_dict()["bad_mac"] == 1


def test_lockstep_resend_is_returned_and_counted_not_accepted_twice():
    dec = FrameDecoder(key=KEY)
    buf = frame(seq=5, period=5)
    assert dec.feed(buf) is not None
    again = dec.feed(frame(seq=5, period=5, stamp_ns=999))
    assert again is not None and again.seq == 5
    c = dec.as_dict()
    assert (c["accepted"], c["resent"], c["rejected"]) == (1, 1, 0)


def test_old_frames_are_stale_and_a_new_camera_takes_over():
    dec = FrameDecoder(key=KEY)
    assert dec.feed(frame(seq=5, period=5, lockstep=False)) is not None
    assert dec.feed(frame(seq=4, period=4, lockstep=False)) is None
    assert dec.feed(frame(seq=5, period=5, lockstep=False)) is None
    assert dec.as_dict()["stale_order"] == 2
    assert dec.feed(frame(seq=0, period=0, lockstep=False, source=1)) is not None
    assert dec.as_dict()["source_changes"] == 1


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((4, 4), dtype=np.uint16),
        np.zeros((4, 4, 3), dtype=np.uint8),
        np.zeros((0, 4), dtype=np.uint8),
        [[1, 2], [3, 4]],
    ],
)
def test_encoder_refuses_what_no_receiver_accepts(bad):
    with pytest.raises(HalCodecError):
        encode_frame(bad, seq=0, stamp_ns=0, sim_time_ns=0, exposure_ns=0, period=0, key=KEY)


def test_encoder_refuses_out_of_range_fields():
    with pytest.raises(HalCodecError, match="exposure"):
        frame(exposure_ns=-1)
    with pytest.raises(HalCodecError, match="out of range"):
        frame(seq=-1)


def test_fuzzed_payloads_never_raise():
    rng = np.random.default_rng(3)
    good = frame()
    dec = FrameDecoder(key=KEY)
    for _ in range(300):
        b = bytearray(good)
        for i in rng.integers(0, len(b), rng.integers(1, 6)):
            b[i] = int(rng.integers(0, 256))
        dec.feed(bytes(b[: int(rng.integers(0, len(b) + 1))]))
    c = dec.as_dict()
    assert c["received"] == 300
    assert c["accepted"] + c["resent"] + c["rejected"] == 300


def test_a_region_round_trips_with_its_offset():
    img = pixels(640, 480, seed=2)
    buf = frame(img=img[100:231, 200:331], x0=200, y0=100, sensor_size=(640, 480))
    assert len(buf) == frame_size(131, 131)
    out = decode_frame(buf)
    assert (out.x0, out.y0, out.sensor_size, out.is_roi) == (200, 100, (640, 480), True)
    np.testing.assert_array_equal(out.pixels, img[100:231, 200:331])
    whole = decode_frame(frame(img=img))
    assert (whole.x0, whole.y0, whole.sensor_size, whole.is_roi) == (0, 0, (640, 480), False)
    with pytest.raises(HalCodecError, match="not inside"):
        frame(img=img[:10, :10], x0=635, y0=0, sensor_size=(640, 480))


@pytest.mark.parametrize("field", [56, 58, 60, 62])
def test_a_tampered_region_offset_or_sensor_size_is_rejected_and_counted(field):
    """The offset and the sensor's size are authenticated like the rest of the header: a frame
    whose region was moved (still inside the sensor) fails the MAC."""
    buf = frame(img=pixels(40, 30), x0=200, y0=100, sensor_size=(640, 480))
    (value,) = struct.unpack_from("<H", buf, field)
    bad = buf[:field] + struct.pack("<H", value + 1) + buf[field + 2 :]
    assert decode_frame(bad).sensor_size is not None  # well formed...
    dec = FrameDecoder(key=KEY)
    assert dec.feed(bad) is None  # ...but not authentic
    c = dec.as_dict()
    assert (c["bad_mac"], c["rejected"], c["accepted"]) == (1, 1, 0)


@pytest.mark.parametrize("lockstep", [True, False])
def test_a_region_then_the_same_frame_whole_are_both_accepted(lockstep):
    dec = FrameDecoder(key=KEY)
    img = pixels(64, 48)
    roi = frame(seq=5, period=5, lockstep=lockstep, img=img[:20, :30], sensor_size=(64, 48))
    assert dec.feed(roi) is not None
    whole = dec.feed(frame(seq=5, period=5, lockstep=lockstep, img=img))
    assert whole is not None and not whole.is_roi
    again = dec.feed(roi)  # the region again: lockstep re-sends are returned, realtime is stale
    assert (again is not None) == lockstep
    c = dec.as_dict()
    assert (c["accepted"], c["resent"], c["stale_order"]) == (2, int(lockstep), int(not lockstep))


def test_region_requests_round_trip_and_bad_ones_are_refused():
    for req in (RoiRequest(7, 12, (1, 2, 131, 132)), RoiRequest(7, 13, None)):
        buf = encode_roi_request(req, KEY)
        assert len(buf) == ROI_SIZE
        assert decode_roi_request(buf, KEY) == req
    good = encode_roi_request(RoiRequest(7, 12, (1, 2, 131, 132)), KEY)
    with pytest.raises(HalCodecError, match="bad_mac"):
        decode_roi_request(good, b"x" * 32)
    with pytest.raises(HalCodecError, match="bad_mac"):
        decode_roi_request(good[:16] + struct.pack("<H", 9) + good[18:], KEY)  # moved window
    for bad in (good[:-1], b"", good[:2] + b"\x02" + good[3:], 42):
        with pytest.raises(HalCodecError, match="malformed"):
            decode_roi_request(bad, KEY)
    for window in ((5, 5, 5, 9), (0, 0, 70000, 10), (-1, 0, 5, 5)):
        with pytest.raises(HalCodecError):
            encode_roi_request(RoiRequest(7, 1, window), KEY)
    assert RoiRequest(1, 1, (-5, 470, 30, 500)).clamped(640, 480) == (0, 470, 30, 480)
    assert RoiRequest(1, 1, (700, 0, 720, 10)).clamped(640, 480) is None
