"""E2E protection: CRC-8 SAE J1850, rolling counter, receiver verdicts and their counters."""

from __future__ import annotations

import can
import pytest

from hal.e2e import (
    COUNTER_MODULO,
    REJECTIONS,
    E2EReceiver,
    E2ESender,
    E2EStats,
    Verdict,
    crc8_sae_j1850,
    e2e_crc,
)
from hal.errors import HalCodecError

FRAME_ID = 0x180
DATA_ID = 0x2002
OTHER_ID = 0x100  # a database id this node sends itself


def frame(payload: bytes | bytearray, frame_id: int = FRAME_ID, **kw: object) -> can.Message:
    return can.Message(arbitration_id=frame_id, is_extended_id=False, data=payload, **kw)


def protected(sender: E2ESender, body: bytes = b"\x00" * 8) -> can.Message:
    return frame(sender.protect(DATA_ID, bytearray(body)))


def with_counter(counter: int, body: bytes = b"\x00\x00\x11\x22\x33\x44\x55\x66") -> can.Message:
    payload = bytearray(body)
    payload[1] = (payload[1] & 0xF0) | counter
    payload[0] = e2e_crc(DATA_ID, payload)
    return frame(payload)


def receiver(**kw: object) -> E2EReceiver:
    return E2EReceiver({FRAME_ID: DATA_ID}, ignore_ids=[OTHER_ID], **kw)


def test_crc8_sae_j1850_check_value() -> None:
    # The catalogued check value of CRC-8/SAE-J1850 (AUTOSAR Crc_CalculateCRC8).
    assert crc8_sae_j1850(b"123456789") == 0x4B
    assert crc8_sae_j1850(b"") == 0x00


def test_frame_crc_covers_data_id_and_payload_bytes_1_to_7() -> None:
    payload = bytes([0xAA, 1, 2, 3, 4, 5, 6, 7])
    expected = crc8_sae_j1850(bytes([DATA_ID & 0xFF, DATA_ID >> 8]) + payload[1:])
    assert e2e_crc(DATA_ID, payload) == expected
    assert e2e_crc(DATA_ID + 1, payload) != expected  # the data id is part of the CRC


def test_sender_counts_per_data_id_and_keeps_the_high_nibble() -> None:
    sender = E2ESender()
    counters = []
    for _ in range(2 * COUNTER_MODULO + 3):
        payload = sender.protect(DATA_ID, bytearray(b"\x00\xa0" + b"\x01" * 6))
        assert payload[1] >> 4 == 0xA
        assert payload[0] == e2e_crc(DATA_ID, payload)
        counters.append(payload[1] & 0x0F)
    assert counters[:17] == [*range(16), 0]
    assert sender.next_counter(0x1234) == 0  # an independent id starts at 0


def test_sender_rejects_a_payload_that_is_not_8_bytes() -> None:
    with pytest.raises(HalCodecError):
        E2ESender().protect(DATA_ID, bytearray(7))


def test_consecutive_frames_are_accepted() -> None:
    rx, sender = receiver(), E2ESender()
    for i in range(40):
        assert rx.check(protected(sender), t_ns=i) is Verdict.OK
    assert rx.stats.rejected == 0
    assert rx.stats.lost == 0


def test_repeated_counter_is_rejected() -> None:
    rx, sender = receiver(), E2ESender()
    msg = protected(sender)
    assert rx.check(msg, 0) is Verdict.OK
    assert rx.check(msg, 1) is Verdict.REPEATED_COUNTER
    assert rx.check(protected(sender), 2) is Verdict.OK
    assert rx.stats.repeated_counter == 1


@pytest.mark.parametrize("max_delta", [1, 3, 7])
def test_counter_gap_within_window_is_accepted_and_counted_as_lost(max_delta: int) -> None:
    rx = receiver(max_delta=max_delta)
    assert rx.check(with_counter(0), 0) is Verdict.OK
    assert rx.check(with_counter(max_delta), 1) is Verdict.OK
    assert rx.stats.lost == max_delta - 1
    assert rx.stats.rejected == 0


@pytest.mark.parametrize("max_delta", [1, 3, 7])
def test_counter_jump_beyond_window_is_rejected_then_resynchronised(max_delta: int) -> None:
    rx = receiver(max_delta=max_delta)
    assert rx.check(with_counter(5), 0) is Verdict.OK
    jumped = (5 + max_delta + 1) % COUNTER_MODULO
    assert rx.check(with_counter(jumped), 1) is Verdict.COUNTER_JUMP
    assert rx.check(with_counter((jumped + 1) % COUNTER_MODULO), 2) is Verdict.OK
    assert rx.stats.counter_jump == 1


def test_an_older_frame_replayed_is_rejected() -> None:
    rx, sender = receiver(), E2ESender()
    frames = [protected(sender) for _ in range(4)]
    for i, msg in enumerate(frames):
        assert rx.check(msg, i) is Verdict.OK
    assert rx.check(frames[1], 10) is Verdict.COUNTER_JUMP  # 2 steps back = 14 forward


def test_counter_wraps_from_15_to_0() -> None:
    rx = receiver()
    assert rx.check(with_counter(15), 0) is Verdict.OK
    assert rx.check(with_counter(0), 1) is Verdict.OK


def test_every_single_bit_error_is_a_bad_crc() -> None:
    sender = E2ESender()
    base = bytes(protected(sender, b"\x00\x00\x12\x34\x56\x78\x9a\xbc").data)
    for bit in range(64):
        rx = receiver()
        corrupted = bytearray(base)
        corrupted[bit // 8] ^= 1 << (bit % 8)
        assert rx.check(frame(corrupted), 0) is Verdict.BAD_CRC, f"bit {bit}"
        assert rx.stats.bad_crc == 1


def test_a_bad_crc_does_not_move_the_counter() -> None:
    rx, sender = receiver(), E2ESender()
    assert rx.check(protected(sender), 0) is Verdict.OK
    good = protected(sender)
    bad = bytearray(good.data)
    bad[5] ^= 0xFF
    assert rx.check(frame(bad), 1) is Verdict.BAD_CRC
    assert rx.check(good, 2) is Verdict.OK


@pytest.mark.parametrize("length", [0, 1, 7])
def test_wrong_length_is_rejected(length: int) -> None:
    rx = receiver()
    assert rx.check(frame(bytes(length)), 0) is Verdict.WRONG_LENGTH
    assert rx.stats.wrong_length == 1


def test_fd_frame_longer_than_8_bytes_is_wrong_length() -> None:
    rx = receiver()
    assert rx.check(frame(bytes(12), is_fd=True), 0) is Verdict.WRONG_LENGTH


def test_remote_frame_is_wrong_length() -> None:
    rx = receiver()
    msg = can.Message(arbitration_id=FRAME_ID, is_extended_id=False, is_remote_frame=True, dlc=8)
    assert rx.check(msg, 0) is Verdict.WRONG_LENGTH


def test_unknown_and_extended_ids_are_rejected() -> None:
    rx, sender = receiver(), E2ESender()
    good = protected(sender)
    assert rx.check(frame(good.data, frame_id=0x7FF), 0) is Verdict.UNKNOWN_ID
    extended = can.Message(arbitration_id=FRAME_ID, is_extended_id=True, data=good.data)
    assert rx.check(extended, 1) is Verdict.UNKNOWN_ID
    assert rx.stats.unknown_id == 2


def test_own_direction_ids_are_ignored_not_rejected() -> None:
    rx = receiver()
    assert rx.check(frame(bytes(8), frame_id=OTHER_ID), 0) is Verdict.IGNORED
    assert rx.stats.ignored == 1
    assert rx.stats.rejected == 0


def test_error_frame_is_counted() -> None:
    rx = receiver()
    assert rx.check(can.Message(is_error_frame=True), 0) is Verdict.ERROR_FRAME
    assert rx.stats.error_frame == 1


def test_silence_reinitialises_the_counter() -> None:
    rx = receiver(reinit_after_ns=1000)
    assert rx.check(with_counter(3), 0) is Verdict.OK
    assert rx.check(with_counter(12), 500) is Verdict.COUNTER_JUMP  # resync on 12
    assert rx.check(with_counter(4), 2000) is Verdict.OK  # 1500 ns of silence: accepted


def test_a_repeat_does_not_refresh_the_silence_timer() -> None:
    rx = receiver(reinit_after_ns=1000)
    assert rx.check(with_counter(3), 0) is Verdict.OK
    assert rx.check(with_counter(3), 900) is Verdict.REPEATED_COUNTER
    assert rx.check(with_counter(3), 1500) is Verdict.OK  # 1500 ns since the last good frame


def test_reinit_can_be_disabled_and_reset_forgets_counters() -> None:
    rx = receiver(reinit_after_ns=None)
    assert rx.check(with_counter(3), 0) is Verdict.OK
    assert rx.check(with_counter(3), 10**15) is Verdict.REPEATED_COUNTER
    rx.reset()
    assert rx.check(with_counter(3), 10**15 + 1) is Verdict.OK


@pytest.mark.parametrize("max_delta", [0, 16, -1])
def test_max_delta_is_validated(max_delta: int) -> None:
    with pytest.raises(HalCodecError, match="max_delta"):
        receiver(max_delta=max_delta)


def test_stats_total_and_dict() -> None:
    stats = E2EStats()
    for verdict in REJECTIONS:
        stats.record(verdict)
    stats.record(Verdict.IGNORED)
    stats.record(Verdict.OK)
    assert stats.rejected == len(REJECTIONS)
    as_dict = stats.as_dict()
    assert as_dict["rejected"] == len(REJECTIONS)
    assert as_dict["accepted"] == 1
    assert as_dict["ignored"] == 1
    snapshot = stats.copy()
    stats.record(Verdict.BAD_CRC)
    assert snapshot.bad_crc == 1
    assert stats.bad_crc == 2
