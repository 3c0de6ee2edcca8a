"""The whole rig's configuration (:class:`RigConfig`, one field per TOML section) and how it is
read: from a TOML file, from JSON (a log's embedded config) or from a nested dict, each value
type-checked and the result validated (:func:`hal.config.validation.validate`)."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import stat
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hal.config.cia402 import Cia402Config
from hal.config.control import ControllerConfig, GainsConfig, RhcConfig
from hal.config.devices import DspConfig, TransportConfig, VisionConfig
from hal.config.experiment import RatesConfig, ScenarioConfig
from hal.config.hardware import HardwareConfig
from hal.config.plant import CameraConfig, PlantConfig, RobotConfig
from hal.config.validation import validate
from hal.config.values import Mat2, Vec2, diag, shown
from hal.errors import HalConfigError


@dataclass(frozen=True)
class RigConfig:
    """The whole rig: every section of the TOML file."""

    robot: RobotConfig = field(default_factory=RobotConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    gains: GainsConfig = field(default_factory=GainsConfig)
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    rates: RatesConfig = field(default_factory=RatesConfig)
    rhc: RhcConfig = field(default_factory=RhcConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    dsp: DspConfig = field(default_factory=DspConfig)
    transport: TransportConfig = field(default_factory=TransportConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    vision: VisionConfig = field(default_factory=VisionConfig)
    cia402: Cia402Config = field(default_factory=Cia402Config)
    hardware: HardwareConfig = field(default_factory=HardwareConfig)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain nested dict (lists for tuples), the inverse of :func:`config_from_dict`."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    def with_overrides(self, overrides: dict[str, Any]) -> RigConfig:
        """A validated copy with ``{"section.key": value}`` overrides applied (command-line
        options): every value gets the same type and range checks as in a file."""
        data = self.to_dict()
        for dotted, value in overrides.items():
            section, _, key = dotted.partition(".")
            if section not in data or not key:
                raise HalConfigError(
                    f"unknown config key {dotted!r} (a key is section.name; sections: "
                    f"{', '.join(data)})"
                )
            data[section][key] = list(value) if isinstance(value, tuple) else value
        return config_from_dict(data)


_SECTIONS: dict[str, type] = {f.name: f.type for f in dataclasses.fields(RigConfig)}
_SECTION_TYPES: dict[str, type] = {
    name: cls
    for name, cls in typing.get_type_hints(RigConfig).items()
    if dataclasses.is_dataclass(cls)
}


def _number(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise HalConfigError(f"{key}: expected a number, got {shown(value)}")
    try:  # an integer literal beyond any float (TOML has no limit) overflows here
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise HalConfigError(f"{key}: must be finite, got {shown(value)}")
    return number


def _coerce(value: Any, hint: Any, key: str) -> Any:
    if hint is float:
        return _number(value, key)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise HalConfigError(f"{key}: expected an integer, got {shown(value)}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise HalConfigError(f"{key}: expected true or false, got {shown(value)}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise HalConfigError(f"{key}: expected a string, got {shown(value)}")
        return value
    if hint == Vec2:
        if not isinstance(value, list | tuple) or len(value) != 2:
            raise HalConfigError(f"{key}: expected a list of 2 numbers, got {shown(value)}")
        return tuple(_number(v, f"{key}[{i}]") for i, v in enumerate(value))
    if hint == Mat2:
        if isinstance(value, list | tuple) and len(value) == 2:
            if all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
                return diag(_number(value[0], f"{key}[0]"), _number(value[1], f"{key}[1]"))
            if all(isinstance(r, list | tuple) and len(r) == 2 for r in value):
                return tuple(
                    tuple(_number(v, f"{key}[{i}][{j}]") for j, v in enumerate(row))
                    for i, row in enumerate(value)
                )
        raise HalConfigError(
            f"{key}: expected a 2x2 matrix [[a, b], [c, d]] or its diagonal [a, d], "
            f"got {shown(value)}"
        )
    raise HalConfigError(f"{key}: unsupported type {hint!r}")  # pragma: no cover


RETIRED_KEYS = {
    "controller.state_wait_us": "a tick never waits for its joint state (a late one is counted "
    "in late_states and its age compensated)",
    "controller.gil_switch_us": "the control process runs no other Python thread",
    "controller.recorder": "the MCAP log is always written by the recorder's own process",
    "controller.rehearse": "the rehearsal before each release bought under 1 % of a 50 Hz "
    "period (hil bench loop) and went",
}
"""Keys older versions had, with why they went: refused in a config file (with the reason),
ignored in a log's embedded config (they never changed what the per-tick rule computes)."""


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    """The resolved field types of a section class, once per class (a sweep builds a config
    per run; resolving them is most of the build's time)."""
    return typing.get_type_hints(cls)


def _build_section(name: str, data: Any, *, retired_ok: bool = False) -> Any:
    cls = _SECTION_TYPES[name]
    if not isinstance(data, dict):
        raise HalConfigError(f"[{name}]: expected a table, got {shown(data)}")
    hints = _type_hints(cls)
    known = [f.name for f in dataclasses.fields(cls)]
    kwargs = {}
    for key, value in data.items():
        why = RETIRED_KEYS.get(f"{name}.{key}")
        if why is not None:
            if retired_ok:
                continue
            raise HalConfigError(f"{name}.{key} was removed: {why}; delete it from the file")
        if key not in hints:
            raise HalConfigError(f"unknown key {name}.{key} ({_hint(key, known, name)})")
        kwargs[key] = _coerce(value, hints[key], f"{name}.{key}")
    return cls(**kwargs)


def _sections_with(key: str) -> list[str]:
    """The sections that have a key named ``key``."""
    return [s for s, cls in _SECTION_TYPES.items() if key in _type_hints(cls)]


def _listed(names: list[str]) -> str:
    """``[a]``, ``[a] or [b]``, ``[a], [b] or [c]``."""
    tables = [f"[{n}]" for n in names]
    return tables[0] if len(tables) == 1 else f"{', '.join(tables[:-1])} or {tables[-1]}"


def _hint(key: str, known: list[str], section: str) -> str:
    """What an unknown ``key`` of ``[section]`` may have meant: a near name of the section,
    else the sections that have it; then the section's keys."""
    import difflib

    near = difflib.get_close_matches(key, known, n=1, cutoff=0.75)
    elsewhere = [s for s in _sections_with(key) if s != section]
    if near:
        lead = f"did you mean {near[0]}? "
    elif elsewhere:
        lead = f"{key} is a key of {_listed(elsewhere)}; "
    else:
        lead = ""
    return f"{lead}known keys: {', '.join(known)}"


def _not_a_section(name: str, body: Any) -> str:
    """The error of a top-level name that is no section: a table is a misspelt section; a
    value is a key written before any ``[section]`` header (or outside its section)."""
    import difflib

    sections = list(_SECTIONS)
    if isinstance(body, dict):
        near = difflib.get_close_matches(name, sections, n=1, cutoff=0.75)
        lead = f"did you mean [{near[0]}]? " if near else ""
        return f"unknown section [{name}] ({lead}known sections: {', '.join(sections)})"
    owners = _sections_with(name)
    if owners:
        return f"{name} = {shown(body)} is outside any section: write it under {_listed(owners)}"
    return (
        f"unknown key {name} outside any section (every key goes under its [section] "
        f"header; known sections: {', '.join(sections)})"
    )


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def config_from_dict(
    data: dict[str, Any],
    *,
    source: str | None = None,
    retired_ok: bool = False,
    files: bool = True,
) -> RigConfig:
    """Build and validate a :class:`RigConfig` from a nested dict (parsed TOML or JSON).

    Exactly the checks of a file (types, ranges, cross-field constraints); ``source`` (e.g.
    ``"log metadata"``) prefixes the one-line error, as the path does for a file;
    ``retired_ok`` skips :data:`RETIRED_KEYS` (a log written by an older version);
    ``files=False`` does not read the files it names (a log's config, read on another host).
    """
    try:
        if not isinstance(data, dict):
            raise HalConfigError(f"config: expected a table of sections, got {type(data).__name__}")
        sections = {}
        for name, body in data.items():
            if name not in _SECTIONS:
                raise HalConfigError(_not_a_section(name, body))
            sections[name] = _build_section(name, body, retired_ok=retired_ok)
        return validate(RigConfig(**sections), files=files)
    except HalConfigError as exc:
        msg = _one_line(str(exc))
        raise HalConfigError(f"{source}: {msg}" if source else msg) from None


def read_text_file(path: str | Path, what: str) -> str:
    """The UTF-8 text of the user's file ``path`` (a config, a study spec), or
    :class:`HalConfigError` in one line: ``cannot read {what} PATH: why`` (missing, a folder, a
    FIFO or a device, which would block or never end and is never opened) or ``PATH: not UTF-8
    text`` naming the first bad byte and its offset (a binary named by mistake)."""
    p = Path(path)
    try:  # stat first: a FIFO or a device is never opened
        mode = p.stat().st_mode
        if not stat.S_ISREG(mode):
            kind = "is a directory" if stat.S_ISDIR(mode) else "not a regular file"
            raise HalConfigError(f"cannot read {what} {p}: {kind}")
        raw = p.read_bytes()
    except OSError as exc:
        raise HalConfigError(f"cannot read {what} {p}: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise HalConfigError(
            f"{p}: not UTF-8 text (invalid byte 0x{raw[exc.start]:02x} at offset {exc.start})"
        ) from None


def load_config(path: str | Path | None = None) -> RigConfig:
    """Load and validate a TOML rig config; ``None`` gives the embedded defaults."""
    if path is None:
        return validate(RigConfig())
    p = Path(path)
    text = read_text_file(p, "config file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise HalConfigError(f"{p}: not valid TOML: {_one_line(str(exc))}") from None
    except RecursionError:
        raise HalConfigError(f"{p}: not valid TOML: nested too deeply") from None
    return config_from_dict(data, source=str(p))


def config_from_json(text: str | bytes, *, source: str = "embedded config") -> RigConfig:
    """Inverse of :meth:`RigConfig.to_json` (used to replay a log's embedded configuration);
    validated exactly like a file, errors prefixed with ``source``; keys older versions wrote
    and this one retired (:data:`RETIRED_KEYS`) are skipped."""
    try:
        data = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise HalConfigError(f"{source}: not valid JSON: {_one_line(str(exc))}") from None
    return config_from_dict(data, source=source, retired_ok=True, files=False)
