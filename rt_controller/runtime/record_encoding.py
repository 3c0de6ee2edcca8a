"""How the log's JSON records are spelt: the schemas of the raw inputs, and compact JSON.

The ``/hal/can/rx`` and ``/hal/can/tx`` frames and the ``/vision/features`` payloads are
recorded as received; :func:`encode_json` writes every JSON record of the log (numpy values
as lists and scalars, non-finite floats as null).
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

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


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, bytes | bytearray | memoryview):
        return bytes(obj).hex()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _finite(obj: Any) -> Any:
    """Copy of ``obj`` with NaN/inf replaced by None (JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


def encode_json(obj: Any) -> bytes:
    """Compact JSON; numpy values become lists/scalars, non-finite floats become null."""
    try:
        text = json.dumps(obj, default=_json_default, allow_nan=False, separators=(",", ":"))
    except ValueError:
        text = json.dumps(_finite(obj), default=_json_default, separators=(",", ":"))
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
