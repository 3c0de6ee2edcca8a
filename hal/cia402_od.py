"""The object dictionary of a CiA 402 servo drive in cyclic synchronous torque mode: ONE table.

Both sides of the ``cia402`` profile read it: the emulated drives build their
:class:`canopen.ObjectDictionary` from it (:func:`build_od`), and the shipped EDS
(``hal/cia402_drive.eds``, :data:`EDS_PATH`) is generated from it with :func:`canopen.export_od`
(:func:`eds_text`; ``python scripts/gen_docs.py`` keeps it current), so a master that only
knows the EDS (canopen's ``BaseNode402``, a PLC, CANopen tools) sees the same objects.

Units (CiA 402): positions in increments (:func:`increments_per_rad` from the encoder resolution
0x608F and the gear 0x6091), velocities in increments per second, torques in per mille of the
rated torque 0x6076 (mNm). 0x6071 and 0x6077 are INTEGER16, as the profile defines them.
"""

from __future__ import annotations

import io
import math
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

# Objects the drives and the master name in code.
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
SYNC_COB_ID = 0x1005
CYCLE_PERIOD = 0x1006
EMCY_COB_ID = 0x1014
HEARTBEAT_CONSUMER = 0x1016
HEARTBEAT_PRODUCER = 0x1017
RPDO_COMM = 0x1400
RPDO_MAP = 0x1600
TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
RATED_TORQUE = 0x6076
TORQUE_ACTUAL = 0x6077
ENCODER_RESOLUTION = 0x608F
GEAR_RATIO = 0x6091
INTERPOLATION_PERIOD = 0x60C2
SUPPORTED_MODES = 0x6502

CST_MODE = 10
"""0x6060/0x6061 value of cyclic synchronous torque mode."""
CST_SUPPORTED_BIT = 1 << 9
"""0x6502 bit of cyclic synchronous torque mode."""
NO_MODE = 0

EMCY_HEARTBEAT = 0x8130
"""CiA 301 EMCY: life guard or heartbeat error (the controller's heartbeat was lost)."""
EMCY_SYNC = 0x8700
"""CiA 402 EMCY: sync controller (no SYNC within the allowed periods)."""
EMCY_PARAMETER = 0x6320
"""CiA 301 EMCY: parameter error (operation cannot be enabled with the objects as they are)."""
EMCY_POSITION_LIMIT = 0x8612
"""CiA 402 EMCY: reference limit (the joint left its software position limits)."""
EMCY_VELOCITY_LIMIT = 0x8400
"""CiA 402 EMCY: velocity speed controller (the joint turned faster than its limit)."""

PDO_COUNT = {"rpdo": 2, "tpdo": 3}
"""PDOs the drive has (0x1400-0x1401, 0x1800-0x1802)."""
PDO_DISABLED = 1 << 31
"""COB-ID bit 31: the PDO does not exist (disabled)."""
MAP_ENTRIES = 8
"""Mapping entries per PDO (sub 1..8)."""

EDS_PATH: Path = Path(str(resources.files("hal") / "cia402_drive.eds"))
"""The shipped EDS, generated from this table (package data of ``hal``)."""

_U8, _U16, _U32 = datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32
_I8, _I16, _I32 = datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32
_STR = datatypes.VISIBLE_STRING


@dataclass(frozen=True)
class DriveParameters:
    """The per-drive values of the table (the EDS carries the defaults)."""

    rated_torque_mnm: int = 10_000
    """0x6076: motor rated torque, mNm (the unit of 0x6071/0x6072/0x6077 is its per mille)."""
    max_torque_permille: int = 15_000
    """0x6072: torque limit, per mille of the rated torque."""
    encoder_increments: int = 1_048_576
    """0x608F.1: increments per motor revolution (20-bit encoder)."""
    interpolation: tuple[int, int] = (20, -3)
    """0x60C2: interpolation time period as (value, index): value * 10**index s (the control
    period, as :func:`hal.cia402_master.units.interpolation_period` writes it)."""


def pdo_entry(index: int, subindex: int, bits: int) -> int:
    """A PDO mapping entry (CiA 301: index << 16 | subindex << 8 | length in bits)."""
    return index << 16 | subindex << 8 | bits


DEFAULT_MAPS: dict[int, tuple[int, ...]] = {
    RPDO_MAP: (pdo_entry(CONTROLWORD, 0, 16), pdo_entry(TARGET_TORQUE, 0, 16)),
    RPDO_MAP + 1: (),
    TPDO_MAP: (pdo_entry(STATUSWORD, 0, 16), pdo_entry(POSITION_ACTUAL, 0, 32)),
    TPDO_MAP + 1: (pdo_entry(VELOCITY_ACTUAL, 0, 32), pdo_entry(TORQUE_ACTUAL, 0, 16)),
    TPDO_MAP + 2: (),
}
"""The default mapping (issue 39): RPDO1 controlword + target torque, TPDO1 statusword +
position, TPDO2 velocity + torque; RPDO2 and TPDO3 are spare (disabled, empty)."""

_COB_BASE = {RPDO_COMM: 0x200, TPDO_COMM: 0x180}


def _var(index, sub, name, dtype, access, default, *, pdo=False, unit="", relative=None):
    var = ODVariable(name, index, sub)
    var.data_type = dtype
    var.access_type = access
    var.default = default
    var.pdo_mappable = pdo
    var.unit = unit
    if isinstance(default, int) and default < 0:
        var.default_raw = str(default)  # canopen's export writes "0x-3", which no parser reads
    if relative is not None:  # a COB-ID: "$NODEID+0x180" in the EDS
        var.relative = True
        var.default_raw = relative
    return var


def _group(cls, index, name, members):
    group = cls(name, index)
    group.add_member(_var(index, 0, "Highest sub-index supported", _U8, "ro", len(members)))
    for sub, (member_name, dtype, access, default) in enumerate(members, start=1):
        group.add_member(_var(index, sub, member_name, dtype, access, default))
    return group


def _cob_id(base: int, node_id: int | None, enabled: bool) -> tuple[int, str]:
    flag = 0 if enabled else PDO_DISABLED
    raw = f"$NODEID+0x{base | flag:X}"
    return (base | flag) + (node_id or 0), raw


def _pdo_objects(node_id: int | None) -> list:
    objects = []
    for comm, kind, mapping in ((RPDO_COMM, "RPDO", RPDO_MAP), (TPDO_COMM, "TPDO", TPDO_MAP)):
        for n in range(PDO_COUNT[kind.lower()]):
            entries = DEFAULT_MAPS[mapping + n]
            default, raw = _cob_id(_COB_BASE[comm] + 0x100 * n, node_id, bool(entries))
            record = ODRecord(f"{kind}{n + 1} communication parameter", comm + n)
            record.add_member(_var(comm + n, 0, "Highest sub-index supported", _U8, "ro", 2))
            record.add_member(_var(comm + n, 1, "COB-ID", _U32, "rw", default, relative=raw))
            record.add_member(_var(comm + n, 2, "Transmission type", _U8, "rw", 1))
            objects.append(record)
            members = [
                (f"Mapped object {i}", _U32, "rw", entries[i - 1] if i <= len(entries) else 0)
                for i in range(1, MAP_ENTRIES + 1)
            ]
            array = _group(ODRecord, mapping + n, f"{kind}{n + 1} mapping parameter", members)
            array[0].access_type = "rw"
            array[0].default = len(entries)
            objects.append(array)
    return objects


def _objects(node_id: int | None, p: DriveParameters) -> list:
    """The table: every object of the drive, in index order."""
    emcy, emcy_raw = _cob_id(0x80, node_id, True)
    objects = [
        _var(DEVICE_TYPE, 0, "Device type", _U32, "ro", 0x0002_0192),  # 402, servo drive
        _var(ERROR_REGISTER, 0, "Error register", _U8, "ro", 0, pdo=True),
        _var(SYNC_COB_ID, 0, "COB-ID SYNC", _U32, "rw", 0x80),
        _var(CYCLE_PERIOD, 0, "Communication cycle period", _U32, "rw", 0, unit="us"),
        _var(0x1008, 0, "Manufacturer device name", _STR, "const", "hil emulated CiA 402 drive"),
        _var(EMCY_COB_ID, 0, "COB-ID EMCY", _U32, "ro", emcy, relative=emcy_raw),
        _group(
            ODArray,
            HEARTBEAT_CONSUMER,
            "Consumer heartbeat time",
            [("Consumer heartbeat time 1", _U32, "rw", 0)],
        ),
        _var(HEARTBEAT_PRODUCER, 0, "Producer heartbeat time", _U16, "rw", 0, unit="ms"),
        _group(
            ODRecord,
            0x1018,
            "Identity object",
            [
                ("Vendor-ID", _U32, "ro", 0),
                ("Product code", _U32, "ro", 0x402),
                ("Revision number", _U32, "ro", 1),
                ("Serial number", _U32, "ro", 0),
            ],
        ),
        *_pdo_objects(node_id),
        _var(ERROR_CODE, 0, "Error code", _U16, "ro", 0, pdo=True),
        _var(CONTROLWORD, 0, "Controlword", _U16, "rw", 0, pdo=True),
        _var(STATUSWORD, 0, "Statusword", _U16, "ro", 0, pdo=True),
        _var(QUICK_STOP_OPTION, 0, "Quick stop option code", _I16, "rw", 6),
        _var(MODES_OF_OPERATION, 0, "Modes of operation", _I8, "rw", NO_MODE, pdo=True),
        _var(MODES_DISPLAY, 0, "Modes of operation display", _I8, "ro", NO_MODE, pdo=True),
        _var(POSITION_ACTUAL, 0, "Position actual value", _I32, "ro", 0, pdo=True, unit="inc"),
        _var(VELOCITY_ACTUAL, 0, "Velocity actual value", _I32, "ro", 0, pdo=True, unit="inc/s"),
        _var(TARGET_TORQUE, 0, "Target torque", _I16, "rw", 0, pdo=True, unit="permille"),
        _var(MAX_TORQUE, 0, "Max torque", _U16, "rw", p.max_torque_permille, unit="permille"),
        _var(RATED_TORQUE, 0, "Motor rated torque", _U32, "rw", p.rated_torque_mnm, unit="mNm"),
        _var(TORQUE_ACTUAL, 0, "Torque actual value", _I16, "ro", 0, pdo=True, unit="permille"),
        _group(
            ODArray,
            ENCODER_RESOLUTION,
            "Position encoder resolution",
            [
                ("Encoder increments", _U32, "rw", p.encoder_increments),
                ("Motor revolutions", _U32, "rw", 1),
            ],
        ),
        _group(
            ODArray,
            GEAR_RATIO,
            "Gear ratio",
            [
                ("Motor revolutions", _U32, "rw", 1),
                ("Shaft revolutions", _U32, "rw", 1),
            ],
        ),
        _group(
            ODRecord,
            INTERPOLATION_PERIOD,
            "Interpolation time period",
            [
                ("Interpolation time period value", _U8, "rw", p.interpolation[0]),
                ("Interpolation time index", _I8, "rw", p.interpolation[1]),
            ],
        ),
        _var(SUPPORTED_MODES, 0, "Supported drive modes", _U32, "ro", CST_SUPPORTED_BIT),
    ]
    return objects


def build_od(node_id: int | None = None, params: DriveParameters | None = None):
    """The drive's object dictionary (``node_id`` None: the node-independent EDS form)."""
    od = canopen.ObjectDictionary()
    od.node_id = node_id
    info = od.device_information
    info.vendor_name = "hil-rhc-visual-servo"
    info.product_name = "Emulated CiA 402 servo drive (CST)"
    info.product_number = 0x402
    info.revision_number = 1
    info.nr_of_RXPDO = PDO_COUNT["rpdo"]
    info.nr_of_TXPDO = PDO_COUNT["tpdo"]
    info.allowed_baudrates = {125e3, 250e3, 500e3, 1000e3}
    for obj in _objects(node_id, params or DriveParameters()):
        od.add_object(obj)
    return od


_FILE_INFO = {
    "FileName": "cia402_drive.eds",
    "FileVersion": "1",
    "FileRevision": "1",
    "Description": "Emulated CiA 402 servo drive, cyclic synchronous torque (hil emulator)",
    "CreatedBy": "hal/cia402_od.py (canopen.export_od)",
}
_DATES = re.compile(r"^(Creation|Modification)(Date|Time)=.*\n", re.MULTILINE)


def eds_text() -> str:
    """The EDS of :func:`build_od`, written by :func:`canopen.export_od`; the export's clock
    readings (creation/modification date and time) are dropped so the file is reproducible."""
    od = build_od()
    setattr(od, "__edsFileInfo", dict(_FILE_INFO))  # export_eds reads this attribute
    out = io.StringIO()
    canopen.export_od(od, out, doc_type="eds")
    return _DATES.sub("", out.getvalue())


def interpolation_seconds(value: int, index: int) -> float:
    """The period of a 0x60C2 (value, index) pair, s."""
    return value * 10.0**index


def increments_per_rad(
    encoder_increments: int, motor_revs: int = 1, gear_motor: int = 1, gear_shaft: int = 1
) -> float:
    """Position increments per radian of the joint: 0x608F.1/0x608F.2 * 0x6091.1/0x6091.2 / 2pi."""
    return encoder_increments / motor_revs * gear_motor / gear_shaft / (2.0 * math.pi)
