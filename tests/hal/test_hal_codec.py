"""The DBC and the typed codec: layout, scalings, round trips, saturation, E2E, directions."""

from __future__ import annotations

import math

import can
import cantools
import pytest

from hal.can_codec import ControllerCodec, DspCodec, DspCommand, bench_codec
from hal.can_database import DBC_PATH, load_database
from hal.can_frames import (
    ENCODER_COUNTS_PER_REV,
    RAD_PER_COUNT,
    DspControl,
    DspStatus,
    JointPosition,
    JointVelocity,
    Sync,
    TorqueCommand,
)
from hal.config import RigConfig
from hal.e2e import E2ESender
from hal.errors import HalCodecError
from tests.support import e2e_crc_reference

RAW_DB = cantools.database.load_file(str(DBC_PATH))  # plain cantools, as any DBC tool reads it

TAU1_LSB = 0.005
TAU2_LSB = 0.0005
DQ_LSB = 1e-5


def signal(message: str, name: str) -> cantools.database.can.Signal:
    return RAW_DB.get_message_by_name(message).get_signal_by_name(name)


# ------------------------------------------------------------------------------ database


def test_database_has_the_names_design_md_fixes() -> None:
    names = {m.name: {s.name for s in m.signals} for m in RAW_DB.messages}
    assert {"Tau1", "Tau2", "Enable"} <= names["TorqueCommand"]
    assert {"Q1", "Q2"} <= names["JointPosition"]
    assert {"Dq1", "Dq2"} <= names["JointVelocity"]
    assert {"TorqueEnabled", "WatchdogTripped", "TorqueSaturated"} <= names["DspStatus"]
    assert "Tick" in names["Sync"]
    assert "Command" in names["DspControl"]


def test_every_message_is_fd_16_byte_with_crc_counter_secoc_and_unique_data_id() -> None:
    data_ids = set()
    for msg in RAW_DB.messages:
        assert msg.length == 16 and msg.is_fd and not msg.is_extended_frame, msg.name
        crc, counter = msg.get_signal_by_name("CRC"), msg.get_signal_by_name("Counter")
        assert (crc.start, crc.length) == (0, 8)
        assert (counter.start, counter.length) == (8, 4)
        fv, mac = msg.get_signal_by_name("Freshness"), msg.get_signal_by_name("Mac")
        assert (fv.start, fv.length, mac.start, mac.length) == (64, 32, 96, 32)
        data_id = msg.dbc.attributes["E2EDataID"].value
        assert 0 < data_id <= 0xFFFF
        data_ids.add(data_id)
    assert len(data_ids) == len(RAW_DB.messages)
    assert load_database().by_name.keys() == {m.name for m in RAW_DB.messages}


def test_directions_come_from_the_dbc_nodes() -> None:
    db = load_database()
    assert {s.name for s in db.sent_by("Controller")} == {"TorqueCommand", "DspControl"}
    assert {s.name for s in db.received_by("Controller")} == {
        "JointPosition",
        "JointVelocity",
        "DspStatus",
        "Sync",
    }
    assert {s.name for s in db.received_by("DSP")} == {"TorqueCommand", "DspControl"}


def test_angle_resolution_is_a_20_bit_encoder(cfg: RigConfig) -> None:
    assert cfg.dsp.encoder_counts == ENCODER_COUNTS_PER_REV == 2**20
    for name in ("Q1", "Q2"):
        sig = signal("JointPosition", name)
        assert sig.scale == pytest.approx(2 * math.pi / 2**20, rel=1e-15)
        assert sig.length == 24 and sig.is_signed
        # +-8 revolutions of range: multi-turn, far beyond the arm's travel.
        assert sig.minimum == pytest.approx(-8 * 2 * math.pi)
        assert sig.maximum == pytest.approx(8 * 2 * math.pi - RAD_PER_COUNT)


def test_torque_range_covers_the_limits_with_amplifier_resolution(cfg: RigConfig) -> None:
    tau1_max, tau2_max = cfg.robot.tau_max
    for name, limit, lsb in (("Tau1", tau1_max, TAU1_LSB), ("Tau2", tau2_max, TAU2_LSB)):
        sig = signal("TorqueCommand", name)
        assert sig.scale == lsb
        assert sig.minimum <= -limit and sig.maximum >= limit
        assert sig.length == 16  # a 16-bit torque DAC


def test_dbc_ranges_match_the_raw_integer_ranges() -> None:
    for msg in RAW_DB.messages:
        for sig in msg.signals:
            lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
            hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
            assert sig.minimum == pytest.approx(lo * sig.scale + sig.offset), sig.name
            assert sig.maximum == pytest.approx(hi * sig.scale + sig.offset), sig.name


# ---------------------------------------------------------------------------- round trips


def roundtrip(frame, sender, receiver):  # type: ignore[no-untyped-def]
    msg = sender.encode(frame)
    assert isinstance(msg, can.Message)
    assert msg.dlc == 16 and msg.is_fd and not msg.is_extended_id
    decoded = receiver.decode(msg, 0)
    assert decoded is not None, receiver.stats
    return decoded


def test_torque_command_roundtrip_within_half_an_lsb() -> None:
    ctl, dsp = ControllerCodec(), DspCodec()
    for tau1, tau2 in [(0.0, 0.0), (149.99, -14.99), (-150.0, 15.0), (1.2345678, -0.0123456)]:
        got = roundtrip(TorqueCommand(tau1, tau2, True, 513), ctl, dsp)
        assert isinstance(got, TorqueCommand)
        assert got.tau1 == pytest.approx(tau1, abs=TAU1_LSB / 2 + 1e-12)
        assert got.tau2 == pytest.approx(tau2, abs=TAU2_LSB / 2 + 1e-12)
        assert got.enable is True and got.tick == 513


def test_dsp_control_roundtrip() -> None:
    ctl, dsp = ControllerCodec(), DspCodec()
    for command in DspCommand:
        assert roundtrip(DspControl(command), ctl, dsp) == DspControl(command)
    assert dsp.decode_command(ctl.encode_control(DspCommand.ENABLE)) == DspControl(
        DspCommand.ENABLE
    )


def test_encoder_counts_travel_exactly() -> None:
    dsp, ctl = DspCodec(), ControllerCodec()
    for counts in (0, 1, -1, 123_456, -(2**23), 2**23 - 1, 2**20 // 12):
        q = counts * RAD_PER_COUNT
        got = roundtrip(JointPosition(q, q, counts % 16), dsp, ctl)
        assert got == JointPosition(q, q, counts % 16)


def test_joint_state_roundtrip_within_half_an_lsb() -> None:
    dsp, ctl = DspCodec(), ControllerCodec()
    q, dq = (math.pi / 6, -math.pi / 6), (0.123456789, -3.3)
    pos_msg, vel_msg = dsp.encode_state(q, dq, 21)
    pos, vel = ctl.decode(pos_msg, 0), ctl.decode(vel_msg, 0)
    assert isinstance(pos, JointPosition) and isinstance(vel, JointVelocity)
    assert pos.sample == vel.sample == 21 % 16
    assert pos.q1 == pytest.approx(q[0], abs=RAD_PER_COUNT / 2)
    assert pos.q2 == pytest.approx(q[1], abs=RAD_PER_COUNT / 2)
    assert vel.dq1 == pytest.approx(dq[0], abs=DQ_LSB / 2)
    assert vel.dq2 == pytest.approx(dq[1], abs=DQ_LSB / 2)


def test_status_and_sync_roundtrip_and_wrap() -> None:
    dsp, ctl = DspCodec(), ControllerCodec()
    status = DspStatus(True, True, True, True, rejected_frames=17, watchdog_trips=3, tick=4095)
    assert roundtrip(status, dsp, ctl) == status
    assert roundtrip(DspStatus(True, False, tick=2**32 - 1), dsp, ctl).tick == 4095  # mod 4096
    saturated = roundtrip(
        DspStatus(False, False, rejected_frames=300, watchdog_trips=999), dsp, ctl
    )
    assert (saturated.rejected_frames, saturated.watchdog_trips) == (255, 15)
    assert roundtrip(Sync(7), dsp, ctl) == Sync(7)
    assert roundtrip(Sync(2**32 + 5), dsp, ctl) == Sync(5)
    assert roundtrip(TorqueCommand(0, 0, False, 70_000), ControllerCodec(), DspCodec()).tick == (
        70_000 & 0xFFFF
    )


def test_frames_decode_with_plain_cantools_and_verify_with_the_dbc_data_id() -> None:
    msg = ControllerCodec().encode_torque(12.5, -1.25, tick=9)
    decoded = RAW_DB.decode_message(msg.arbitration_id, bytes(msg.data))
    assert decoded["Tau1"] == pytest.approx(12.5)
    assert decoded["Tau2"] == pytest.approx(-1.25)
    assert decoded["Tick"] == 9 and decoded["Enable"] == 1 and decoded["Counter"] == 0
    data_id = RAW_DB.get_message_by_frame_id(msg.arbitration_id).dbc.attributes["E2EDataID"].value
    # the independent bitwise reference, not hal's own table-driven CRC
    assert decoded["CRC"] == e2e_crc_reference(data_id, bytes(msg.data))


# ----------------------------------------------------------------------- encode policies


def test_out_of_range_values_saturate_to_the_frame_range() -> None:
    ctl, dsp = ControllerCodec(), DspCodec()
    got = roundtrip(TorqueCommand(1e6, -1e6), ctl, dsp)
    assert got.tau1 == pytest.approx(signal("TorqueCommand", "Tau1").maximum)
    assert got.tau2 == pytest.approx(signal("TorqueCommand", "Tau2").minimum)
    # Measured joint angles and speeds are never pinned: beyond the frame they raise.
    for frame in (JointPosition(1e3, 0.0), JointPosition(0.0, -51.0), JointVelocity(90.0, 0.0)):
        with pytest.raises(HalCodecError, match="beyond the frame"):
            dsp.encode(frame)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_raise_and_do_not_use_up_a_counter(bad: float) -> None:
    ctl = ControllerCodec()
    with pytest.raises(HalCodecError, match="finite"):
        ctl.encode_torque(bad, 0.0)
    assert ctl.encode_torque(0.0, 0.0).data[1] & 0x0F == 0


def test_a_node_cannot_encode_the_other_nodes_messages() -> None:
    with pytest.raises(HalCodecError, match="does not send"):
        ControllerCodec().encode(Sync(1))
    with pytest.raises(HalCodecError, match="does not send"):
        DspCodec().encode(TorqueCommand(0, 0))
    with pytest.raises(HalCodecError, match="cannot encode"):
        DspCodec().encode("not a frame")  # type: ignore[arg-type]


def test_counters_advance_per_message() -> None:
    dsp = DspCodec()
    counters = [dsp.encode_sync(k).data[1] & 0xF for k in range(3)]
    pos, vel = dsp.encode_state((0, 0), (0, 0), 0)
    assert counters == [0, 1, 2]
    assert (pos.data[1] & 0xF, vel.data[1] & 0xF) == (0, 0)


# ------------------------------------------------------------------------ receive policy


def test_own_direction_frames_are_ignored() -> None:
    ctl = ControllerCodec()
    assert ctl.decode(ControllerCodec().encode_torque(1, 1), 0) is None
    assert ctl.stats.ignored == 1 and ctl.stats.rejected == 0


@pytest.mark.parametrize(
    "fields",
    [
        pytest.param({"Command": 7}, id="unknown command"),
        pytest.param({"Command": 5}, id="the scenario reset, no longer on CAN"),
    ],
)
def test_a_malformed_command_with_valid_crc_is_a_decode_error(fields: dict) -> None:
    spec = load_database().by_name["DspControl"]
    signals = {"CRC": 0, "Counter": 0, "Freshness": 0, "Mac": 0}
    signals.update(fields)
    payload = bytearray(spec.message.encode(signals)[:8])
    E2ESender().protect(spec.data_id, payload)
    dsp = DspCodec()
    raw = can.Message(arbitration_id=spec.frame_id, data=payload, is_extended_id=False)
    msg = ControllerCodec().sign(raw)  # authentic: the rig's own key
    assert dsp.decode(msg, 0) is None
    assert dsp.stats.decode_error == 1 and dsp.stats.rejected == 1


def test_the_dbc_holds_only_what_a_real_dsp_implements() -> None:
    """The harness's scenario reset and camera seed left the CAN database for the
    simulator-control channel (hal.sim_control): no command value, no signal for them."""
    db = cantools.database.load_file(str(DBC_PATH))
    control = db.get_message_by_name("DspControl")
    assert {s.name for s in control.signals} == {"CRC", "Counter", "Command", "Freshness", "Mac"}
    assert set(control.get_signal_by_name("Command").choices) == {1, 2, 3, 4}
    text = DBC_PATH.read_text()
    assert "RESET_SCENARIO" not in text and "Seed" not in text
    assert [c.name for c in DspCommand] == ["ENABLE", "DISABLE", "FAULT_RESET", "DISABLE_VOLTAGE"]


def test_decode_command_drops_non_command_frames() -> None:
    dsp = DspCodec()
    assert dsp.decode_command(DspCodec().encode_sync(1), 0) is None
    assert dsp.stats.ignored == 1


def test_bench_codec_reports_microseconds() -> None:
    result = bench_codec(50)
    assert set(result) == {
        "encode_torque_us",
        "decode_torque_us",
        "encode_state_us",
        "decode_state_us",
    }
    assert all(value > 0 for value in result.values())


@pytest.mark.parametrize("message", sorted(load_database().by_name))
def test_the_compiled_packer_equals_cantools_on_random_frames(message: str) -> None:
    """HeadPacker (the run-time path) against cantools itself, both ways: random raw words
    decode to the same signals, and random physical values (on and between the grid, at the
    signal limits) encode to the same bytes."""
    import random

    spec = load_database().by_name[message]
    head, packer = spec.head, spec.packer
    rng = random.Random(message)
    for _ in range(500):
        data = bytes(rng.getrandbits(8) for _ in range(8))
        want = head.decode_simple(data, decode_choices=False, scaling=True)
        got = packer.decode(data)
        assert got == want and all(type(got[k]) is type(want[k]) for k in want)
        values = {}
        for sig in head.signals:
            lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
            hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
            raw = rng.choice((lo, hi, rng.randint(lo, hi)))
            if sig.scale == 1 and sig.offset == 0:
                values[sig.name] = raw
            else:  # a physical value near a grid point, so that rounding is exercised
                nudge = rng.uniform(-0.49, 0.49) if lo < raw < hi else 0.0
                values[sig.name] = (raw + nudge) * sig.scale + sig.offset
        assert packer.encode(values) == head.encode(values, scaling=True, strict=False)


def test_the_packer_refuses_a_value_its_bits_cannot_carry() -> None:
    packer = load_database().by_name["TorqueCommand"].packer
    values = {"CRC": 0, "Counter": 0, "Enable": 1, "Tau1": 200.0, "Tau2": 0.0, "Tick": 1}
    with pytest.raises(HalCodecError, match=r"Tau1: raw value 40000 does not fit"):
        packer.encode(values)
    with pytest.raises(HalCodecError, match=r"cannot encode TorqueCommand\.Tau2"):
        packer.encode({**values, "Tau1": 0.0, "Tau2": math.nan})
