"""hal.cia402_frames: one frame of the cia402 bus decoded by its COB-ID and the profile's PDO
maps. The payloads are packed here by hand, as CiA 301/402 lay them out (little endian:
statusword UNSIGNED16 + position INTEGER32; velocity INTEGER32 + torque INTEGER16;
controlword UNSIGNED16 + target torque INTEGER16)."""

from __future__ import annotations

import struct

import pytest

from hal.cia402_frames import decode


def test_tpdo1_gives_statusword_power_state_and_position():
    out = decode(0x183, struct.pack("<Hi", 0x0637, -123456))
    assert out == {
        "kind": "tpdo1",
        "node": 3,
        "statusword": 0x0637,
        "position_actual": -123456,
        "state": "OPERATION ENABLED",
    }
    assert decode(0x181, struct.pack("<Hi", 0x0608, 0))["state"] == "FAULT"


def test_tpdo2_and_rpdo1_carry_signed_16_bit_torques():
    assert decode(0x282, struct.pack("<ih", -70000, -5)) == {
        "kind": "tpdo2",
        "node": 2,
        "velocity_actual": -70000,
        "torque_actual": -5,
    }
    assert decode(0x201, struct.pack("<Hh", 0x000F, -300)) == {
        "kind": "rpdo1",
        "node": 1,
        "controlword": 0x000F,
        "target_torque": -300,
    }


def test_sync_nmt_heartbeat_and_sdo():
    assert decode(0x080, b"") == {"kind": "sync", "node": None}
    assert decode(0x000, bytes([0x82, 0x01])) == {
        "kind": "nmt",
        "node": None,
        "command": "reset communication",
        "target": 1,
    }
    assert decode(0x701, b"\x05") == {"kind": "heartbeat", "node": 1, "nmt_state": "OPERATIONAL"}
    assert decode(0x701, b"\x00")["nmt_state"] == "INITIALISING"  # boot-up
    assert decode(0x601, bytes(8))["kind"] == "sdo_request"
    assert decode(0x581, bytes(8))["kind"] == "sdo_response"


def test_sdo_service_object_value_and_abort():
    """A write of 0x60C2:01 = 20 (expedited, 1 byte), 0x6061's answer 10, a refused remap."""
    out = decode(0x602, struct.pack("<BHBI", 0x2F, 0x60C2, 1, 20))
    assert out == {
        "kind": "sdo_request",
        "node": 2,
        "sdo_command": 0x2F,
        "sdo_service": "initiate download",
        "index": 0x60C2,
        "subindex": 1,
        "sdo_value": 20,
    }
    answer = decode(0x582, struct.pack("<BHBI", 0x4F, 0x6061, 0, 0x0A))
    assert (answer["sdo_service"], answer["index"], answer["sdo_value"]) == (
        "initiate upload",
        0x6061,
        10,
    )
    abort = decode(0x581, struct.pack("<BHBI", 0x80, 0x1A00, 0, 0x06010000))
    assert abort["sdo_service"] == "abort" and abort["abort_code"] == 0x06010000
    assert abort["text"] == "Unsupported access to an object"
    assert "index" not in decode(0x601, bytes([0x60]) + bytes(7))  # an upload segment
    assert "error" in decode(0x601, bytes([0x2F, 0xC2, 0x60]))  # an initiate cut short


def test_emcy_code_register_and_error_reset():
    out = decode(0x082, struct.pack("<HB5s", 0x8700, 0x11, bytes(5)))
    assert out["kind"] == "emcy" and out["node"] == 2
    assert out["code"] == 0x8700 and out["register"] == 0x11 and not out["error_reset"]
    assert decode(0x082, bytes(8))["error_reset"] is True


@pytest.mark.parametrize(
    ("cob_id", "data"),
    [(0x181, b"\x37\x06"), (0x281, b""), (0x201, b"\x0f"), (0x081, b"\x00"), (0x000, b"\x01")],
)
def test_a_frame_too_short_for_its_kind_is_marked_not_raised(cob_id, data):
    out = decode(cob_id, data)
    assert "error" in out and out["kind"] in ("tpdo1", "tpdo2", "rpdo1", "emcy", "nmt")


def test_each_field_name_has_one_type_over_all_kinds():
    """The log's frame table mixes the kinds in one column per field name (``hil export
    --format parquet`` needs one type per column: an NMT ``command`` is a string, so the SDO
    command byte has a name of its own)."""
    frames = [
        (0x000, bytes([0x01, 0x00])),
        (0x080, b""),
        (0x081, struct.pack("<HB5s", 0x8700, 0x11, bytes(5))),
        (0x181, struct.pack("<Hi", 0x0637, 5)),
        (0x281, struct.pack("<ih", 5, 5)),
        (0x201, struct.pack("<Hh", 0x0F, 5)),
        (0x581, bytes([0x60]) + bytes(7)),
        (0x601, bytes([0x2B]) + bytes(7)),
        (0x581, struct.pack("<BHBI", 0x4F, 0x6061, 0, 10)),
        (0x581, struct.pack("<BHBI", 0x80, 0x1600, 1, 0x06040043)),
        (0x601, bytes([0x00]) + bytes(7)),
        (0x701, b"\x05"),
    ]
    types: dict[str, set[type]] = {}
    for cob_id, data in frames:
        for name, value in decode(cob_id, data).items():
            if value is not None:
                types.setdefault(name, set()).add(type(value))
    mixed = {name: t for name, t in types.items() if len(t) > 1}
    assert not mixed, mixed
