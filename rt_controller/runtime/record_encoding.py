"""How the log's JSON records are spelt: the schemas of the raw inputs, and compact JSON.

The ``/hal/can/rx`` and ``/hal/can/tx`` frames and the ``/vision/features`` payloads are
recorded as received (a ``cia402`` run's frames also decoded, on ``/hal/canopen``:
:func:`canopen_dict`, in the recorder's process); :func:`encode_json` writes every JSON record
of the log (numpy values as lists and scalars, non-finite floats as null).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from hal.strict_json import finite

CAN_SCHEMA: dict[str, Any] = {
    "title": "hil.CanFrame",
    "description": "A raw CAN frame as received (/hal/can/rx) or sent (/hal/can/tx).",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "time.monotonic_ns() at receive/send"},
        "timestamp": {"type": "number", "description": "python-can Message.timestamp, s"},
        "arbitration_id": {"type": "integer"},
        "is_extended_id": {"type": "boolean"},
        "dlc": {"type": "integer"},
        "data": {"type": "string", "description": "payload bytes as lowercase hex"},
        "is_fd": {"type": "boolean"},
        "bitrate_switch": {"type": "boolean"},
        "is_error_frame": {"type": "boolean"},
        "is_remote_frame": {"type": "boolean"},
        "channel": {"type": "string", "description": "bus channel, empty if unknown"},
    },
    "required": ["t_ns", "arbitration_id", "dlc", "data", "is_fd"],
}

VISION_SCHEMA: dict[str, Any] = {
    "title": "hil.VisionPayload",
    "description": "A vision message (zenoh key hil/vision/features) exactly as received: the "
    "raw payload bytes (decode them with hal's vision codec) and the receive time.",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "time.monotonic_ns() at receive"},
        "size": {"type": "integer", "description": "payload length, bytes"},
        "data": {"type": "string", "contentEncoding": "base64", "description": "raw payload"},
    },
    "required": ["t_ns", "size", "data"],
}


CANOPEN_SCHEMA: dict[str, Any] = {
    "title": "hil.CanopenFrame",
    "description": "A cia402 run's CANopen frame decoded (/hal/canopen): one message per "
    "frame of /hal/can/rx and /hal/can/tx, written by the recorder process from the raw "
    "record, decoded by hal.cia402_frames.decode (its COB-ID and the profile's PDO maps).",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer", "description": "the raw frame's t_ns (monotonic)"},
        "direction": {
            "type": "string",
            "enum": ["rx", "tx"],
            "description": "rx: received, tx: sent",
        },
        "cob_id": {"type": "integer", "description": "the frame's COB-ID (arbitration id)"},
        "kind": {
            "type": "string",
            "description": "nmt, sync, emcy, rpdo1, tpdo1, tpdo2, sdo_request, sdo_response, "
            "heartbeat or other",
        },
        "node": {"type": ["integer", "null"], "description": "node id; null for NMT, SYNC"},
        "data": {"type": "string", "description": "payload bytes as lowercase hex"},
        "fields": {
            "type": "object",
            "description": "the kind's decoded fields, raw object values (increments, "
            "increments/s, per mille of the rated torque)",
            "properties": {
                "statusword": {"type": "integer", "description": "0x6041 (TPDO1)"},
                "state": {"type": "string", "description": "CiA 402 power state (TPDO1)"},
                "position_actual": {"type": "integer", "description": "0x6064 (TPDO1)"},
                "velocity_actual": {"type": "integer", "description": "0x606C (TPDO2)"},
                "torque_actual": {"type": "integer", "description": "0x6077 (TPDO2)"},
                "controlword": {"type": "integer", "description": "0x6040 (RPDO1)"},
                "target_torque": {"type": "integer", "description": "0x6071 (RPDO1)"},
                "counter": {"type": "integer", "description": "SYNC counter, if sent"},
                "command": {"type": "string", "description": "NMT command"},
                "target": {"type": "integer", "description": "NMT target node (0: all)"},
                "nmt_state": {"type": "string", "description": "heartbeat's NMT state"},
                "code": {"type": "integer", "description": "EMCY error code"},
                "register": {"type": "integer", "description": "EMCY error register 0x1001"},
                "error_reset": {"type": "boolean", "description": "EMCY code 0x00xx"},
                "text": {"type": "string", "description": "EMCY or SDO abort code's meaning"},
                "sdo_command": {"type": ["integer", "null"], "description": "SDO command byte"},
                "sdo_service": {"type": "string", "description": "e.g. initiate download"},
                "index": {"type": "integer", "description": "SDO object index"},
                "subindex": {"type": "integer", "description": "SDO object subindex"},
                "sdo_value": {"type": "integer", "description": "SDO expedited value"},
                "abort_code": {"type": "integer", "description": "SDO abort code"},
            },
            "additionalProperties": False,
        },
        "error": {"type": "string", "description": "why the payload does not fit its kind"},
    },
    "required": ["t_ns", "direction", "cob_id", "kind", "node", "data", "fields"],
}


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, bytes | bytearray | memoryview):
        return bytes(obj).hex()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def encode_json(obj: Any) -> bytes:
    """Compact JSON; numpy values become lists/scalars, non-finite floats become null."""
    try:
        text = json.dumps(obj, default=_json_default, allow_nan=False, separators=(",", ":"))
    except ValueError:
        text = json.dumps(finite(obj), default=_json_default, separators=(",", ":"))
    return text.encode()


def can_dict(t_ns: int, msg: Any) -> dict[str, Any]:
    """The ``/hal/can/*`` record of a python-can ``Message`` sent or received at ``t_ns``."""
    data = bytes(msg.data)
    channel = getattr(msg, "channel", None)
    return {
        "t_ns": t_ns,
        "timestamp": float(getattr(msg, "timestamp", 0.0) or 0.0),
        "arbitration_id": int(msg.arbitration_id),
        "is_extended_id": bool(getattr(msg, "is_extended_id", False)),
        "dlc": int(getattr(msg, "dlc", len(data))),
        "data": data.hex(),
        "is_fd": bool(getattr(msg, "is_fd", False)),
        "bitrate_switch": bool(getattr(msg, "bitrate_switch", False)),
        "is_error_frame": bool(getattr(msg, "is_error_frame", False)),
        "is_remote_frame": bool(getattr(msg, "is_remote_frame", False)),
        "channel": "" if channel is None else str(channel),
    }


def canopen_dict(direction: str, raw: dict[str, Any]) -> dict[str, Any]:
    """The ``/hal/canopen`` record (:data:`CANOPEN_SCHEMA`) of one ``/hal/can/*`` record
    (``direction`` ``"rx"`` or ``"tx"``): the frame decoded by :func:`hal.cia402_frames.decode`,
    which never raises (what does not fit its kind gets an ``error``)."""
    from hal.cia402_frames import decode  # canopen's import only where frames are decoded

    data = raw.get("data") or ""
    cob_id = raw.get("arbitration_id")
    try:
        payload, bad = bytes.fromhex(data), None
    except (TypeError, ValueError):
        payload, bad = b"", "data is not hex"
    if isinstance(cob_id, int) and not raw.get("is_extended_id"):
        fields = decode(cob_id, payload)
    else:
        fields = {"kind": "other", "node": None, "error": "not an 11-bit CANopen identifier"}
    kind, node, error = fields.pop("kind"), fields.pop("node"), fields.pop("error", None)
    out = {
        "t_ns": raw.get("t_ns"),
        "direction": direction,
        "cob_id": cob_id if isinstance(cob_id, int) else -1,
        "kind": kind,
        "node": node,
        "data": data if bad is None else "",
        "fields": fields,
    }
    if bad or error:
        out["error"] = bad or error
    return out
