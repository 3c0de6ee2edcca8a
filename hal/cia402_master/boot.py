"""Boot of CiA 402 drives by SDO and NMT, with canopen's own services (no byte is encoded
here): NMT reset communication and the boot-up of each node, heartbeat producer 0x1017 and
consumer 0x1016, interpolation time period 0x60C2, torque limit 0x6072, the PDO maps (one RPDO,
two TPDOs, all transmitted on every SYNC), cyclic synchronous torque with 0x6061 read back."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import canopen
from canopen.objectdictionary import INTEGER16, INTEGER32, UNSIGNED16
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from hal.cia402_master.units import DriveUnits, interpolation_period
from hal.cia402_master.watch import state_of
from hal.cia402_od import (
    CONTROLWORD,
    CST_MODE,
    CST_SUPPORTED_BIT,
    ENCODER_RESOLUTION,
    GEAR_RATIO,
    HEARTBEAT_CONSUMER,
    HEARTBEAT_PRODUCER,
    INTERPOLATION_PERIOD,
    MAX_TORQUE,
    MODES_DISPLAY,
    MODES_OF_OPERATION,
    POSITION_ACTUAL,
    RATED_TORQUE,
    STATUSWORD,
    SUPPORTED_MODES,
    TARGET_TORQUE,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
)
from hal.errors import HalDriveError, HalStopped, HalTimeoutError

SYNCHRONOUS_EVERY_SYNC = 1
"""PDO transmission type 1: a TPDO is sent after every SYNC, an RPDO takes effect at the next."""

RPDO_MAP: dict[int, tuple[int, ...]] = {1: (CONTROLWORD, TARGET_TORQUE)}
"""RPDO number -> objects: controlword, target torque."""
TPDO_MAP: dict[int, tuple[int, ...]] = {
    1: (STATUSWORD, POSITION_ACTUAL),
    2: (VELOCITY_ACTUAL, TORQUE_ACTUAL),
}
"""TPDO number -> objects: statusword + position actual; velocity actual + torque actual."""
TYPES = {
    CONTROLWORD: UNSIGNED16,
    STATUSWORD: UNSIGNED16,
    POSITION_ACTUAL: INTEGER32,
    VELOCITY_ACTUAL: INTEGER32,
    TARGET_TORQUE: INTEGER16,
    TORQUE_ACTUAL: INTEGER16,
}
"""The CiA 402 data types of the mapped objects (the EDS must agree: a wrong type would be
mapped with a wrong length)."""
MODE_READBACK_S = 0.5
"""How long 0x6061 may take to show the mode written to 0x6060."""


@dataclass(frozen=True)
class BootSettings:
    """What the master writes to every drive."""

    master_id: int
    """The controller's node id: the drives consume its heartbeat."""
    heartbeat_ms: int
    """Producer heartbeat time of the drives (0x1017) and of the controller."""
    consumer_ms: int
    """The drives' consumer time of the controller's heartbeat (0x1016.1)."""
    period_s: float
    """The control period: 0x60C2, and the SYNC period."""
    boot_timeout_s: float = 20.0
    """How long a node may take to send its boot-up after NMT reset communication: a rig
    starts its processes together, and an emulated drive on a slow host (user-mode Linux)
    comes up many seconds after the controller (the DSP profile waits as long)."""


def _what(node: canopen.RemoteNode, index: int, sub: int | None) -> str:
    place = f"0x{index:04X}" if sub is None else f"0x{index:04X}.{sub}"
    return f"node {node.id} {place}"


@contextmanager
def sdo_step(node: canopen.RemoteNode, index: int, sub: int | None, doing: str) -> Iterator[None]:
    """Turn canopen's SDO errors into one :class:`HalDriveError` line naming the object."""
    try:
        yield
    except SdoAbortedError as exc:
        raise HalDriveError(f"{_what(node, index, sub)}: {doing} refused ({exc})") from None
    except SdoCommunicationError as exc:
        raise HalDriveError(
            f"{_what(node, index, sub)}: {doing} got no SDO answer ({exc}): is the node at "
            f"this id and bit rate, and in NMT pre-operational or operational?"
        ) from None


def sdo_write(node: canopen.RemoteNode, index: int, sub: int | None, value: int) -> None:
    """One expedited SDO download by canopen, errors as :class:`HalDriveError`."""
    with sdo_step(node, index, sub, f"writing {value}"):
        target = node.sdo[index] if sub is None else node.sdo[index][sub]
        target.raw = value


def sdo_read(node: canopen.RemoteNode, index: int, sub: int | None = None) -> Any:
    """One SDO upload by canopen, errors as :class:`HalDriveError`."""
    with sdo_step(node, index, sub, "reading"):
        target = node.sdo[index] if sub is None else node.sdo[index][sub]
        return target.raw


def reset_communication(
    nodes: Iterable[canopen.RemoteNode],
    booted: dict[int, threading.Event],
    timeout_s: float,
    stop: Any | None = None,
    on_wait: Callable[[], None] | None = None,
) -> None:
    """NMT reset communication to each node (addressed, never broadcast: other devices on a
    shared bus keep running), then ``on_wait()`` (say what is awaited: a drive may take many
    seconds), then wait until ``booted[node id]`` is set (by whoever follows the node's
    heartbeats, on its boot-up message)."""
    nodes = list(nodes)
    for node in nodes:
        booted[node.id].clear()
    for node in nodes:
        node.nmt.state = "RESET COMMUNICATION"
    if on_wait is not None:
        on_wait()
    deadline = time.monotonic() + timeout_s
    for node in nodes:
        while not booted[node.id].wait(0.05):
            if stop is not None and stop.is_set():
                raise HalStopped("stopped while waiting for the drives' boot-up")
            if time.monotonic() > deadline:
                silent = [n.id for n in nodes if not booted[n.id].is_set()]
                ids = ", ".join(str(i) for i in silent)
                many = len(silent) > 1
                raise HalTimeoutError(
                    f"node{'s' if many else ''} {ids} sent no boot-up within {timeout_s:g} s "
                    f"of NMT reset communication: {'are they' if many else 'is it'} powered, "
                    f"on this bus at its bit rate, with node id{'s' if many else ''} {ids}?"
                )


def check_types(node: canopen.RemoteNode) -> None:
    """The node's object dictionary types the mapped objects as CiA 402 does."""
    od = node.object_dictionary
    for index, want in TYPES.items():
        if index not in od:
            raise HalDriveError(f"node {node.id}: the EDS has no object 0x{index:04X}")
        got = od[index].data_type
        if got != want:
            raise HalDriveError(
                f"node {node.id}: the EDS types 0x{index:04X} as data type 0x{got:04X}, "
                f"CiA 402 says 0x{want:04X}: fix the EDS"
            )


UNIT_OBJECTS: dict[str, tuple[int, int | None]] = {
    "encoder_increments": (ENCODER_RESOLUTION, 1),
    "motor_revolutions": (ENCODER_RESOLUTION, 2),
    "gear_motor_revolutions": (GEAR_RATIO, 1),
    "gear_shaft_revolutions": (GEAR_RATIO, 2),
    "rated_torque_mnm": (RATED_TORQUE, None),
}
""":class:`DriveUnits` field -> the object it is read from."""


def read_units(node: canopen.RemoteNode) -> DriveUnits:
    """The drive's encoder resolution, gear ratio and rated torque, read by SDO; a value
    of 0 (a drive whose vendor tool never stored it) is a :class:`HalDriveError` naming the
    node and the object."""
    values = {}
    for name, (index, sub) in UNIT_OBJECTS.items():
        values[name] = int(sdo_read(node, index, sub))
        if values[name] <= 0:
            raise HalDriveError(
                f"{_what(node, index, sub)} reads {values[name]}, must be > 0: set the "
                f"drive's true value with the vendor's tool and store it (0x1010)"
            )
    return DriveUnits(**values)


def configure(
    node: canopen.RemoteNode, settings: BootSettings, torque_limit_nm: float
) -> tuple[DriveUnits, int]:
    """Heartbeats (the drive's producer on, its consumer of the controller off until
    arming: :func:`watch_controller`), interpolation period and torque limit by SDO; the
    drive's units and the torque limit it took (per mille)."""
    check_types(node)
    sdo_write(node, HEARTBEAT_PRODUCER, None, settings.heartbeat_ms)
    watch_controller(node, settings, on=False)
    value, index = interpolation_period(settings.period_s)
    sdo_write(node, INTERPOLATION_PERIOD, 1, value)
    sdo_write(node, INTERPOLATION_PERIOD, 2, index)
    units = read_units(node)
    limit = units.limit_per_mille(torque_limit_nm)
    sdo_write(node, MAX_TORQUE, None, limit)
    return units, limit


def watch_controller(node: canopen.RemoteNode, settings: BootSettings, *, on: bool) -> None:
    """The drive's heartbeat consumer 0x1016.1: the controller's node id and consumer time
    (``on``), or 0 (off). Off during boot and after the run: the controller's process may
    stall longer than the consumer time before it arms (locking its memory, compiling), and
    a drive must not fault for that; on from the first arming step."""
    value = (settings.master_id << 16) | settings.consumer_ms if on else 0
    sdo_write(node, HEARTBEAT_CONSUMER, 1, value)


def _remap(maps: Any, layout: dict[int, tuple[int, ...]], node: canopen.RemoteNode) -> None:
    for number, pdo in maps.map.items():
        with sdo_step(node, pdo.com_record.od.index, None, f"mapping PDO {number}"):
            pdo.read()
            pdo.clear()
            objects = layout.get(number)
            pdo.enabled = objects is not None
            if objects:
                for index in objects:
                    pdo.add_variable(index)
                pdo.trans_type = SYNCHRONOUS_EVERY_SYNC
                pdo.cob_id = pdo.predefined_cob_id or pdo.cob_id
            pdo.save()


def map_pdos(node: canopen.RemoteNode) -> None:
    """RPDO1 = controlword + target torque; TPDO1 = statusword + position actual; TPDO2 =
    velocity actual + torque actual; all on every SYNC; every other PDO disabled (in NMT
    pre-operational, as CiA 301 asks). Then the maps are read back and compared."""
    _remap(node.rpdo, RPDO_MAP, node)
    _remap(node.tpdo, TPDO_MAP, node)
    got = mapping(node)
    want = {
        "rpdo": {n: (SYNCHRONOUS_EVERY_SYNC, objs) for n, objs in RPDO_MAP.items()},
        "tpdo": {n: (SYNCHRONOUS_EVERY_SYNC, objs) for n, objs in TPDO_MAP.items()},
    }
    if got != want:
        raise HalDriveError(f"node {node.id}: PDO mapping reads back as {got}, wanted {want}")


Mapping = dict[str, dict[int, tuple[int, tuple[int, ...]]]]


def mapping(node: canopen.RemoteNode) -> Mapping:
    """The enabled PDOs as the drive reports them by SDO: ``{"rpdo": {n: (transmission
    type, (index, ...))}, "tpdo": {...}}``."""
    out: Mapping = {}
    for name, maps in (("rpdo", node.rpdo), ("tpdo", node.tpdo)):
        enabled = {}
        for number, pdo in maps.map.items():
            with sdo_step(node, pdo.com_record.od.index, None, "reading PDO"):
                pdo.read()
            if pdo.enabled:
                enabled[number] = (int(pdo.trans_type), tuple(var.index for var in pdo.map))
        out[name] = enabled
    return out


def enter_cst(node: canopen.RemoteNode, timeout_s: float = MODE_READBACK_S) -> None:
    """0x6060 = 10 (cyclic synchronous torque), then 0x6061 read back until it says 10;
    :class:`HalDriveError` when the drive does not support CST or does not switch."""
    supported = int(sdo_read(node, SUPPORTED_MODES))
    if not supported & CST_SUPPORTED_BIT:
        raise HalDriveError(
            f"node {node.id}: 0x6502 = 0x{supported:08X} does not advertise cyclic synchronous "
            f"torque (bit 9): this drive cannot run the cia402 profile"
        )
    sdo_write(node, MODES_OF_OPERATION, None, CST_MODE)
    deadline = time.monotonic() + timeout_s
    while True:
        shown = int(sdo_read(node, MODES_DISPLAY))
        if shown == CST_MODE:
            return
        if time.monotonic() > deadline:
            raise HalDriveError(
                f"node {node.id}: 0x6061 reads {shown} {timeout_s:g} s after 0x6060 = "
                f"{CST_MODE}: the drive did not enter cyclic synchronous torque"
            )
        time.sleep(0.01)


def describe(node: canopen.RemoteNode) -> dict[str, Any]:
    """What a drive says of itself by SDO: power state, mode, units, limits, heartbeats,
    0x60C2 and the PDO maps (``hil cia402 check``)."""
    units = read_units(node)
    value, index = sdo_read(node, INTERPOLATION_PERIOD, 1), sdo_read(node, INTERPOLATION_PERIOD, 2)
    consumer = int(sdo_read(node, HEARTBEAT_CONSUMER, 1))
    statusword = int(sdo_read(node, STATUSWORD))
    return {
        "node": node.id,
        "state": state_of(statusword).lower(),
        "statusword": f"0x{statusword:04X}",
        "mode_display": int(sdo_read(node, MODES_DISPLAY)),
        "increments_per_rad": units.increments_per_rad,
        "gear_ratio": units.gear_ratio,
        "rated_torque_nm": units.joint_rated_torque_nm,
        "torque_limit_per_mille": int(sdo_read(node, MAX_TORQUE)),
        "torque_limit_nm": units.torque_nm(int(sdo_read(node, MAX_TORQUE))),
        "interpolation_period_s": value * 10.0**index,
        "heartbeat_ms": int(sdo_read(node, HEARTBEAT_PRODUCER)),
        "heartbeat_consumer": {"node": consumer >> 16 & 0x7F, "ms": consumer & 0xFFFF},
        "pdo": {
            kind: {str(n): [f"0x{i:04X}" for i in objs] for n, (_t, objs) in maps.items()}
            for kind, maps in mapping(node).items()
        },
    }


__all__ = [
    "CST_MODE",
    "RPDO_MAP",
    "TPDO_MAP",
    "BootSettings",
    "configure",
    "describe",
    "enter_cst",
    "map_pdos",
    "mapping",
    "read_units",
    "reset_communication",
    "sdo_read",
    "sdo_write",
    "watch_controller",
]
