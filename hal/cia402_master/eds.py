"""The EDS each drive is described by: the shipped one (``hal/cia402_drive.eds``, our emulated
drive's) or the drive vendor's (``cia402.eds_1`` / ``cia402.eds_2``), read with canopen and
checked to hold every object the master reads, writes or maps (:data:`REQUIRED_OBJECTS`), so
a wrong file is one line at the configuration's load, not an error in the middle of a boot.

A relative path is relative to the working directory of the command, like the other file keys
(``transport.key_file``, ``transport.zenoh_config``)."""

from __future__ import annotations

import functools
import io
import logging
import stat
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ODVariable, datatypes

from hal.cia402_master import boot
from hal.cia402_od import (
    CONTROLWORD,
    EDS_PATH,
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
    RPDO_COMM,
    RPDO_MAP,
    STATUSWORD,
    SUPPORTED_MODES,
    TARGET_TORQUE,
    TORQUE_ACTUAL,
    TPDO_COMM,
    TPDO_MAP,
    VELOCITY_ACTUAL,
)
from hal.errors import HalConfigError

NAMES = {
    CONTROLWORD: "controlword",
    STATUSWORD: "statusword",
    MODES_OF_OPERATION: "modes of operation",
    MODES_DISPLAY: "modes of operation display",
    POSITION_ACTUAL: "position actual",
    VELOCITY_ACTUAL: "velocity actual",
    TARGET_TORQUE: "target torque",
    MAX_TORQUE: "max torque",
    RATED_TORQUE: "motor rated torque",
    TORQUE_ACTUAL: "torque actual",
    SUPPORTED_MODES: "supported drive modes",
    ENCODER_RESOLUTION: "position encoder resolution",
    GEAR_RATIO: "gear ratio",
    INTERPOLATION_PERIOD: "interpolation time period",
    HEARTBEAT_CONSUMER: "consumer heartbeat time",
    HEARTBEAT_PRODUCER: "producer heartbeat time",
}
"""What the objects are called in the one-line errors (CiA 301 / CiA 402 names)."""


def _required() -> tuple[tuple[int, int | None, str], ...]:
    """(index, subindex or None, name) of every object :mod:`~hal.cia402_master.boot` and
    :mod:`~hal.cia402_master.master` read, write or map, from their own tables."""
    out: list[tuple[int, int | None, str]] = []
    for kind, maps, comm, mapping in (
        ("RPDO", boot.RPDO_MAP, RPDO_COMM, RPDO_MAP),
        ("TPDO", boot.TPDO_MAP, TPDO_COMM, TPDO_MAP),
    ):
        for number, objects in maps.items():
            out += [(comm + number - 1, s, f"{kind}{number} communication") for s in (1, 2)]
            subs = range(len(objects) + 1)
            out += [(mapping + number - 1, s, f"{kind}{number} mapping") for s in subs]
            out += [(index, None, NAMES[index]) for index in objects]
    for index, sub in boot.UNIT_OBJECTS.values():
        out.append((index, sub, NAMES[index]))
    out += [
        (HEARTBEAT_PRODUCER, None, NAMES[HEARTBEAT_PRODUCER]),
        (HEARTBEAT_CONSUMER, 1, NAMES[HEARTBEAT_CONSUMER]),
        (INTERPOLATION_PERIOD, 1, "interpolation time period value"),
        (INTERPOLATION_PERIOD, 2, "interpolation time index"),
        (MAX_TORQUE, None, NAMES[MAX_TORQUE]),
        (SUPPORTED_MODES, None, NAMES[SUPPORTED_MODES]),
        (MODES_OF_OPERATION, None, NAMES[MODES_OF_OPERATION]),
        (MODES_DISPLAY, None, NAMES[MODES_DISPLAY]),
    ]
    return tuple(dict.fromkeys(out))


REQUIRED_OBJECTS = _required()
"""(index, subindex or None, name) of every object the master needs in a drive's EDS: the PDO
communication (COB-ID, transmission type) and mapping records it sets, the objects it maps,
the units it reads (0x608F, 0x6091, 0x6076), the heartbeats, 0x60C2, 0x6072, 0x6502, 0x6060
and 0x6061."""


def eds_path(value: str) -> Path:
    """The EDS a ``cia402.eds_N`` value names: the shipped one when empty."""
    return Path(value) if value else EDS_PATH


def missing_objects(od: canopen.ObjectDictionary) -> list[str]:
    """``0xIIII (name)`` (or ``0xIIII.S (name)`` when the object is there without that
    subindex) of each object of :data:`REQUIRED_OBJECTS` that ``od`` lacks, once each."""
    missing: dict[str, None] = {}
    for index, sub, name in sorted(REQUIRED_OBJECTS, key=lambda r: (r[0], r[1] or 0)):
        obj = od.get(index)
        if obj is None:
            missing[f"0x{index:04X} ({NAMES.get(index, name)})"] = None
        elif sub is not None:
            try:
                if isinstance(obj, ODVariable) or obj[sub] is None:
                    raise KeyError(sub)
            except KeyError:
                missing[f"0x{index:04X}.{sub} ({name})"] = None
    return list(missing)


def wrong_types(od: canopen.ObjectDictionary) -> list[str]:
    """Each mapped object ``od`` types otherwise than CiA 402 (:data:`boot.TYPES`): the
    master would map it with a wrong length."""
    names = {v: k for k, v in vars(datatypes).items() if k.isupper() and isinstance(v, int)}
    out = []
    for index, want in boot.TYPES.items():
        got = getattr(od.get(index), "data_type", want)
        if got != want:
            out.append(
                f"0x{index:04X} ({NAMES[index]}) is {names.get(got, f'type 0x{got:04X}')}, "
                f"not {names[want]}"
            )
    return out


@contextmanager
def _quiet_canopen() -> Iterator[None]:
    """canopen logs a warning (with a deprecated call) for an EDS without [DeviceInfo]: our
    error is the one line."""
    log = logging.getLogger("canopen.objectdictionary.eds")
    was, log.disabled = log.disabled, True
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            yield
    finally:
        log.disabled = was


def _read(path: Path) -> str:
    """The file's text (UTF-8, else Latin-1 as older vendor tools write it); OSError as is."""
    mode = path.stat().st_mode  # a FIFO or a device is never opened
    if not stat.S_ISREG(mode):
        raise OSError("is a directory" if stat.S_ISDIR(mode) else "not a regular file")
    raw = path.read_bytes()
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _parse(text: str, name: str, node_id: int) -> canopen.ObjectDictionary:
    source = io.StringIO(text)
    source.name = name if name.lower().endswith((".eds", ".dcf")) else "drive.eds"
    with _quiet_canopen():
        return canopen.import_od(source, node_id)


def _said(exc: Exception) -> str:
    """The parser's complaint in one short line (its first, with the line number if any)."""
    errors = getattr(exc, "errors", None)  # configparser's ParsingError: the lines it skipped
    if errors and isinstance(errors[0], tuple):
        lineno, line = errors[0][:2]
        return f"line {lineno} is not KEY=VALUE nor [SECTION]: {str(line)[:80]}"
    lines = str(exc).splitlines() or [type(exc).__name__]
    said = lines[0].strip()[:160]
    lineno = getattr(exc, "lineno", None)
    return f"{said} (line {lineno})" if lineno else said


@functools.lru_cache(maxsize=16)
def _problem(path: str, _stamp: tuple[int, int], node_id: int) -> str | None:
    """Why the file cannot describe a drive (one line, from its path on), or None; once per
    version of the file (a sweep validates a configuration per run)."""
    try:
        od = _parse(_read(Path(path)), path, node_id)
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    except Exception as exc:  # canopen's parser raises whatever it meets
        return f"{path} is not an EDS canopen can read: {_said(exc)}"
    if not len(od):
        return f"{path} is not an EDS canopen can read: it describes no object"
    missing = missing_objects(od)
    if missing:
        return f"{path} lacks {', '.join(missing)} that the cia402 master reads, writes or maps"
    types = wrong_types(od)
    if types:
        return f"{path} types {'; '.join(types)} (CiA 402): the cia402 master maps them"
    return None


def check_eds(key: str, value: str, node_id: int) -> Path:
    """The EDS ``value`` of config key ``key`` (empty: the shipped one), or a one-line
    :class:`HalConfigError` naming the key and the file: unreadable, not parsed by canopen,
    lacking objects the master needs (each by index and name) or typing a mapped one wrong."""
    path = eds_path(value)
    try:
        st = path.stat()
        stamp = (st.st_mtime_ns, st.st_size)
    except OSError as exc:
        raise HalConfigError(f"{key}: cannot read {path}: {exc.strerror or exc}") from None
    problem = _problem(str(path), stamp, node_id)
    if problem is not None:
        raise HalConfigError(f"{key}: {problem}")
    return path


def drive_dictionary(key: str, value: str, node_id: int) -> canopen.ObjectDictionary:
    """The object dictionary of the drive at ``node_id`` from its EDS (checked as by
    :func:`check_eds`)."""
    path = check_eds(key, value, node_id)
    try:
        return _parse(_read(path), str(path), node_id)
    except Exception as exc:  # changed since the check
        raise HalConfigError(f"{key}: {path} cannot be read again: {_said(exc)}") from None


def configured(cfg: Any) -> list[tuple[str, str, int]]:
    """(key, value, node id) of each joint's EDS in ``cfg``'s ``[cia402]``."""
    c = cfg.cia402
    return [("cia402.eds_1", c.eds_1, c.node_id_1), ("cia402.eds_2", c.eds_2, c.node_id_2)]


__all__ = [
    "REQUIRED_OBJECTS",
    "check_eds",
    "configured",
    "drive_dictionary",
    "eds_path",
    "missing_objects",
    "wrong_types",
]
