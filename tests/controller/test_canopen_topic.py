"""The log's ``/hal/canopen`` topic: each CAN frame of a ``cia402`` run decoded by the file's
writer (:class:`CycleRecorder`, in a run the recorder's process), right after its raw record
and at the same log time. The frames are the profile's own traffic, packed here by hand as
CiA 301/402 lay them out (little endian), so the expected records are known."""

from __future__ import annotations

import json
import struct

import can
import jsonschema
import pytest
from mcap.reader import make_reader

from hal.config import RigConfig
from rt_controller.logtools.reader import read_log
from rt_controller.runtime.record_encoding import CANOPEN_SCHEMA, can_dict, canopen_dict
from rt_controller.runtime.recorder import (
    CAN_RX_TOPIC,
    CAN_TX_TOPIC,
    CANOPEN_TOPIC,
    CycleRecorder,
)
from rt_controller.runtime.recorder_process import RecorderProcess

CIA402 = RigConfig().with_overrides({"hardware.profile": "cia402"})

FRAMES = [  # (direction, COB-ID, payload): a boot, one period, a fault
    ("tx", 0x000, bytes([0x82, 0x00])),  # NMT reset communication, all nodes
    ("rx", 0x701, b"\x00"),  # boot-up
    ("tx", 0x601, struct.pack("<BHBI", 0x2B, 0x1017, 0, 100)),  # heartbeat 100 ms
    ("rx", 0x581, struct.pack("<BHBI", 0x60, 0x1017, 0, 0)),
    ("tx", 0x602, struct.pack("<BHBI", 0x40, 0x6061, 0, 0)),  # read the mode back
    ("rx", 0x582, struct.pack("<BHBI", 0x4F, 0x6061, 0, 10)),  # CST
    ("rx", 0x582, struct.pack("<BHBI", 0x80, 0x1600, 1, 0x06040043)),  # refused remap
    ("tx", 0x201, struct.pack("<Hh", 0x000F, -300)),
    ("tx", 0x080, b""),
    ("rx", 0x181, struct.pack("<Hi", 0x0637, 123456)),
    ("rx", 0x281, struct.pack("<ih", -7000, -300)),
    ("rx", 0x082, struct.pack("<HB5s", 0x8700, 0x11, bytes(5))),
    ("rx", 0x702, b"\x05"),
]


def raw(direction: str, cob_id: int, data: bytes, t_ns: int = 1_000) -> dict:
    msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
    return can_dict(t_ns, msg)


def decoded(direction: str, cob_id: int, data: bytes) -> dict:
    return canopen_dict(direction, raw(direction, cob_id, data))


def test_known_frames_give_known_records():
    assert decoded("rx", 0x181, struct.pack("<Hi", 0x0637, 123456)) == {
        "t_ns": 1_000,
        "direction": "rx",
        "cob_id": 0x181,
        "kind": "tpdo1",
        "node": 1,
        "data": struct.pack("<Hi", 0x0637, 123456).hex(),
        "fields": {"statusword": 0x0637, "position_actual": 123456, "state": "OPERATION ENABLED"},
    }
    assert decoded("tx", 0x201, struct.pack("<Hh", 0x000F, -300))["fields"] == {
        "controlword": 0x0F,
        "target_torque": -300,
    }
    assert decoded("rx", 0x281, struct.pack("<ih", -7000, -300))["fields"] == {
        "velocity_actual": -7000,
        "torque_actual": -300,
    }
    sync = decoded("tx", 0x080, b"")
    assert (sync["kind"], sync["node"], sync["fields"]) == ("sync", None, {})
    nmt = decoded("tx", 0x000, bytes([0x82, 0x00]))["fields"]
    assert nmt == {"command": "reset communication", "target": 0}
    emcy = decoded("rx", 0x082, struct.pack("<HB5s", 0x8700, 0x11, bytes(5)))
    assert emcy["node"] == 2 and emcy["fields"]["code"] == 0x8700
    assert emcy["fields"]["register"] == 0x11 and emcy["fields"]["error_reset"] is False


def test_sdo_frames_name_their_service_object_and_value():
    write = decoded("tx", 0x601, struct.pack("<BHBI", 0x2B, 0x1017, 0, 100))
    assert write["kind"] == "sdo_request" and write["node"] == 1
    assert write["fields"] == {
        "sdo_command": 0x2B,
        "sdo_service": "initiate download",
        "index": 0x1017,
        "subindex": 0,
        "sdo_value": 100,  # expedited, 2 bytes
    }
    answer = decoded("rx", 0x581, struct.pack("<BHBI", 0x60, 0x1017, 0, 0))["fields"]
    assert answer["sdo_service"] == "initiate download" and "sdo_value" not in answer
    mode = decoded("rx", 0x582, struct.pack("<BHBI", 0x4F, 0x6061, 0, 10))["fields"]
    assert (mode["sdo_service"], mode["index"], mode["sdo_value"]) == (
        "initiate upload",
        0x6061,
        10,
    )
    abort = decoded("rx", 0x582, struct.pack("<BHBI", 0x80, 0x1600, 1, 0x06040043))["fields"]
    assert abort["sdo_service"] == "abort" and (abort["index"], abort["subindex"]) == (0x1600, 1)
    assert abort["abort_code"] == 0x06040043
    assert abort["text"] == "General parameter incompatibility reason"
    segment = decoded("tx", 0x601, bytes([0x00]) + bytes(7))["fields"]
    assert segment["sdo_service"] == "download segment" and "index" not in segment


def test_every_record_follows_the_topic_schema():
    for frame in FRAMES:
        jsonschema.validate(decoded(*frame), CANOPEN_SCHEMA)


@pytest.mark.parametrize(
    ("record", "error"),
    [
        ({"t_ns": 1, "arbitration_id": 0x181, "data": "zz"}, "data is not hex"),
        ({"t_ns": 1, "data": "00"}, "not an 11-bit CANopen identifier"),
        ({"t_ns": 1, "arbitration_id": 0x181, "is_extended_id": True, "data": ""}, "11-bit"),
        ({"t_ns": 1, "arbitration_id": 0x181, "data": "3706"}, "tpdo1 needs 6"),
        ({"t_ns": 1, "arbitration_id": 0x601, "data": "2b1710"}, "needs 8"),
    ],
)
def test_a_frame_that_does_not_decode_is_marked_not_raised(record, error):
    out = canopen_dict("rx", record)
    assert error in out["error"]
    jsonschema.validate(out, CANOPEN_SCHEMA)


def _feed(rec) -> None:
    for i, (direction, cob_id, data) in enumerate(FRAMES):
        msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
        rec.record_can(msg, 1_000_000 + 1_000 * i, direction)


def _messages(path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        messages = reader.iter_messages(log_time_order=False)  # file order
        return [(ch.topic, m.log_time, m.data) for _s, ch, m in messages]


def test_the_writer_decodes_each_frame_right_after_its_raw_record(tmp_path):
    path = tmp_path / "cia402.mcap"
    with CycleRecorder(path, CIA402) as rec:
        _feed(rec)
    assert rec.as_dict()[CANOPEN_TOPIC] == len(FRAMES) and rec.encode_errors == 0
    messages = [m for m in _messages(path) if m[0] != "/diagnostics"]
    assert len(messages) == 2 * len(FRAMES)
    for (topic, log_time, data), (topic2, log_time2, data2) in zip(
        messages[::2], messages[1::2], strict=True
    ):
        assert topic in (CAN_RX_TOPIC, CAN_TX_TOPIC) and topic2 == CANOPEN_TOPIC
        assert log_time2 == log_time
        direction = "rx" if topic == CAN_RX_TOPIC else "tx"
        assert json.loads(data2) == canopen_dict(direction, json.loads(data))
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    channel = next(c for c in summary.channels.values() if c.topic == CANOPEN_TOPIC)
    schema = summary.schemas[channel.schema_id]
    assert schema.name == "hil.CanopenFrame" and json.loads(schema.data) == CANOPEN_SCHEMA


def test_the_reader_and_the_tables_expose_the_topic(tmp_path):
    path = tmp_path / "cia402.mcap"
    with CycleRecorder(path, CIA402) as rec:
        _feed(rec)
    log = read_log(path)
    assert log.topic_counts[CANOPEN_TOPIC] == len(FRAMES)
    assert log.schemas[CANOPEN_TOPIC] == "hil.CanopenFrame"
    assert [r["kind"] for r in log.canopen][:3] == ["nmt", "heartbeat", "sdo_request"]
    assert read_log(path, raw=False).canopen == []  # counted, not kept

    from rt_controller.logs import load

    table = load(path).arrays("canopen")
    assert list(table["kind"]) == [r["kind"] for r in log.canopen]
    tpdo2 = table["kind"] == "tpdo2"
    assert table["torque_actual"][tpdo2].tolist() == [-300.0]
    read = (table["index"] == 0x6061) & (table["kind"] == "sdo_response")
    assert table["sdo_value"][read].tolist() == [10.0]  # the request has no value


def test_a_dsp_log_has_no_canopen_topic(tmp_path, cfg):
    path = tmp_path / "dsp.mcap"
    with CycleRecorder(path, cfg) as rec:
        _feed(rec)
    assert CANOPEN_TOPIC not in rec.as_dict()
    log = read_log(path)
    assert CANOPEN_TOPIC not in log.channels and log.canopen == []


def test_the_recorder_process_writes_the_same_topic_and_counts_it(tmp_path):
    """What the daemon uses: the decoding happens in the child; nothing is decoded in this
    process (its counters during the run have no such topic), and the file is the same as an
    in-process writer's, run after run."""
    with CycleRecorder(tmp_path / "here.mcap", CIA402) as here:
        _feed(here)
    logs = []
    for k in range(2):
        with RecorderProcess(tmp_path / f"child{k}.mcap", CIA402) as child:
            _feed(child)
            assert CANOPEN_TOPIC not in child.as_dict()
        assert child.finished and child.error is None
        assert child.as_dict()[CANOPEN_TOPIC] == len(FRAMES)
        logs.append(tmp_path / f"child{k}.mcap")
    want = [(t, d) for t, _lt, d in _messages(tmp_path / "here.mcap") if t == CANOPEN_TOPIC]
    for path in logs:
        assert [(t, d) for t, _lt, d in _messages(path) if t == CANOPEN_TOPIC] == want
