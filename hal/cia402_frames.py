"""One CANopen frame of the ``cia402`` profile's bus, decoded by its COB-ID (CiA 301's
predefined connection set) and the profile's PDO maps (:mod:`hal.cia402_master.boot`): NMT,
SYNC, EMCY, the TPDOs (statusword and power state, position, velocity, torque actual), the
RPDO (controlword, target torque), SDO (service, object, expedited value, abort code) and
heartbeat.

The recorder writes the log's ``/hal/canopen`` topic with this, offline tools (``hil report``,
the log's tables) read the raw ``/hal/can/*`` frames with it; it never raises on a frame: one
too short for its kind is returned with an ``error``.
"""

from __future__ import annotations

import struct
from typing import Any

from canopen.emcy import EmcyError
from canopen.nmt import NMT_STATES
from canopen.objectdictionary import INTEGER16, INTEGER32, UNSIGNED16
from canopen.sdo.constants import EXPEDITED, SDO_STRUCT, SIZE_SPECIFIED
from canopen.sdo.exceptions import SdoAbortedError

from hal.cia402_master.boot import RPDO_MAP, TPDO_MAP, TYPES
from hal.cia402_master.watch import state_of
from hal.cia402_od import (
    CONTROLWORD,
    POSITION_ACTUAL,
    STATUSWORD,
    TARGET_TORQUE,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
)

SYNC_ID = 0x080
NMT_ID = 0x000
FIELD_NAMES = {
    CONTROLWORD: "controlword",
    STATUSWORD: "statusword",
    POSITION_ACTUAL: "position_actual",
    VELOCITY_ACTUAL: "velocity_actual",
    TARGET_TORQUE: "target_torque",
    TORQUE_ACTUAL: "torque_actual",
}
"""The decoded fields' names (raw object values: increments, increments/s, per mille)."""
_FORMATS = {UNSIGNED16: "H", INTEGER16: "h", INTEGER32: "i"}
_PDO_BASES = {0x180: ("tpdo", 1), 0x280: ("tpdo", 2), 0x200: ("rpdo", 1)}
"""Function code -> the PDO it carries on the predefined connection set."""
_SDO_SERVICES = {
    "sdo_request": {
        0: "download segment",
        1: "initiate download",
        2: "initiate upload",
        3: "upload segment",
        4: "abort",
        5: "block upload",
        6: "block download",
    },
    "sdo_response": {
        0: "upload segment",
        1: "download segment",
        2: "initiate upload",
        3: "initiate download",
        4: "abort",
        5: "block download",
        6: "block upload",
    },
}
"""The command specifier (the command byte's top 3 bits) of a request (client to drive) and
of a response (CiA 301, 7.2.4.3)."""
_SDO_WITH_OBJECT = frozenset({"initiate download", "initiate upload", "abort"})
_SDO_WITH_VALUE = {"sdo_request": {"initiate download"}, "sdo_response": {"initiate upload"}}
"""The frames whose expedited payload is the object's value (a write, a read's answer)."""
_NMT_COMMANDS = {
    1: "start",
    2: "stop",
    0x80: "enter pre-operational",
    0x81: "reset node",
    0x82: "reset communication",
}


def _pdo_layout(objects: tuple[int, ...]) -> tuple[str, tuple[str, ...]]:
    fmt = "<" + "".join(_FORMATS[TYPES[index]] for index in objects)
    return fmt, tuple(FIELD_NAMES[index] for index in objects)


_LAYOUTS = {("tpdo", n): _pdo_layout(objs) for n, objs in TPDO_MAP.items()} | {
    ("rpdo", n): _pdo_layout(objs) for n, objs in RPDO_MAP.items()
}


def decode(cob_id: int, data: bytes) -> dict[str, Any]:
    """The frame's ``kind`` (``nmt``, ``sync``, ``emcy``, ``tpdo1``, ``tpdo2``, ``rpdo1``,
    ``sdo_request``, ``sdo_response``, ``heartbeat``, ``other``), its ``node`` (None for
    NMT and SYNC) and the kind's fields (each field name has one type over all kinds: the
    log's tables mix the kinds); ``error`` when the payload does not fit."""
    if cob_id == NMT_ID:
        if len(data) < 2:
            return {"kind": "nmt", "node": None, "error": f"{len(data)} bytes, NMT needs 2"}
        command = _NMT_COMMANDS.get(data[0], f"0x{data[0]:02X}")
        return {"kind": "nmt", "node": None, "command": command, "target": int(data[1])}
    if cob_id == SYNC_ID:
        out: dict[str, Any] = {"kind": "sync", "node": None}
        if data:
            out["counter"] = int(data[0])
        return out
    base, node = cob_id & 0x780, cob_id & 0x7F
    if base == 0x080:
        return _emcy(node, data)
    if base in _PDO_BASES:
        return _pdo(*_PDO_BASES[base], node, data)
    if base == 0x580:
        return _sdo("sdo_response", node, data)
    if base == 0x600:
        return _sdo("sdo_request", node, data)
    if base == 0x700:
        if not data:
            return {"kind": "heartbeat", "node": node, "error": "no payload"}
        state = data[0] & 0x7F
        return {"kind": "heartbeat", "node": node, "nmt_state": NMT_STATES.get(state, str(state))}
    return {"kind": "other", "node": node}


def _emcy(node: int, data: bytes) -> dict[str, Any]:
    if len(data) < 3:
        return {"kind": "emcy", "node": node, "error": f"{len(data)} bytes, EMCY needs 8"}
    code, register = struct.unpack_from("<HB", data)
    err = EmcyError(code, register, bytes(data[3:8]).ljust(5, b"\0"), 0.0)
    return {
        "kind": "emcy",
        "node": node,
        "code": code,
        "register": register,
        "error_reset": code & 0xFF00 == 0,
        "text": err.get_desc(),
    }


def _sdo(kind: str, node: int, data: bytes) -> dict[str, Any]:
    """An SDO frame: its command byte, the service it names, and for an initiate or an abort
    the object (``index``, ``subindex``); an expedited value as ``sdo_value`` (unsigned, little
    endian), an abort's ``abort_code`` and its ``text``. Segments carry no object."""
    out: dict[str, Any] = {"kind": kind, "node": node, "sdo_command": data[0] if data else None}
    if not data:
        return out
    service = _SDO_SERVICES[kind].get(data[0] >> 5, f"unknown ({data[0] >> 5})")
    out["sdo_service"] = service
    if service not in _SDO_WITH_OBJECT:
        return out
    if len(data) < 8:
        out["error"] = f"{len(data)} bytes, SDO {service} needs 8"
        return out
    command, out["index"], out["subindex"] = SDO_STRUCT.unpack_from(data)
    if service == "abort":
        code = int.from_bytes(data[4:8], "little")
        out["abort_code"] = code
        out["text"] = SdoAbortedError.CODES.get(code, "unknown abort code")
    elif command & EXPEDITED and service in _SDO_WITH_VALUE[kind]:
        unused = (command >> 2) & 0x3 if command & SIZE_SPECIFIED else 0
        out["sdo_value"] = int.from_bytes(data[4 : 8 - unused], "little")
    return out


def _pdo(kind: str, number: int, node: int, data: bytes) -> dict[str, Any]:
    name = f"{kind}{number}"
    fmt, names = _LAYOUTS[(kind, number)]
    size = struct.calcsize(fmt)
    if len(data) < size:
        return {"kind": name, "node": node, "error": f"{len(data)} bytes, {name} needs {size}"}
    out: dict[str, Any] = {"kind": name, "node": node}
    out.update(zip(names, struct.unpack_from(fmt, data), strict=True))
    if "statusword" in out:
        out["state"] = state_of(out["statusword"])
    return out


__all__ = ["FIELD_NAMES", "NMT_ID", "SYNC_ID", "decode"]
