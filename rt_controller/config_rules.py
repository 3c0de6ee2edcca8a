"""Configuration rules shared by the CLI, the experiment runner and the benchmarks.

One place for how command-line style overrides (``--law``, ``--rate``, ``--horizon`` ...) change
a :class:`~hal.config.RigConfig`, and for writing a config back as TOML for a child process.
Pure functions: no argparse, no I/O beyond returning text.
"""

from __future__ import annotations

import json
import math
from typing import Any

from hal.config import RigConfig
from hal.errors import HalConfigError
from rt_controller.errors import ControllerConfigError

MAX_PREDICTION_STEP_S = 0.05
"""Largest T/N chosen automatically when only the horizon is given."""
OPTIONS = {
    "controller.law": "--law",
    "rates.control_hz": "--rate",
    "rhc.horizon": "--horizon",
    "rhc.steps": "--steps",
    "rhc.kmax": "--kmax",
    "rhc.zeta": "--zeta",
    "camera.seed": "--seed",
    "scenario.disturbance": "--no-disturbance",
    "controller.clock": "--clock",
    "transport.can": "--can",
    "transport.zenoh_endpoint": "--zenoh-endpoint",
    "transport.zenoh_config": "--zenoh-config",
    "hardware.profile": "--profile",
}
"""The command-line option of each key :func:`apply_overrides` sets (named in its errors)."""


def physics_for_rate(cfg: RigConfig, rate: float) -> float:
    """The physics rate to use at control rate ``rate``: an integer multiple of it and no slower
    than configured."""
    physics = cfg.rates.physics_hz
    if abs(physics / rate - round(physics / rate)) > 1e-9 or physics < rate:
        return rate * math.ceil(physics / rate)
    return physics


def apply_overrides(
    cfg: RigConfig,
    *,
    law: str | None = None,
    rate: float | None = None,
    horizon: float | None = None,
    steps: int | None = None,
    kmax: int | None = None,
    zeta: float | None = None,
    seed: int | None = None,
    disturbance: bool | None = None,
    clock: str | None = None,
    can: str | None = None,
    zenoh_endpoint: str | None = None,
    zenoh_config: str | None = None,
    profile: str | None = None,
    sets: dict[str, Any] | None = None,
    from_command_line: bool = False,
) -> RigConfig:
    """``cfg`` with the given settings changed (None = keep), validated.

    ``sets``: any other keys, ``{"camera.model": "analytic"}`` (``--set``, :func:`parse_sets`),
    by the same rules as the named settings (``rates.control_hz`` there moves the physics rate
    as ``rate`` does); a key given both ways is refused. Only the horizon given: N =
    max(rhc.steps, ceil(T / 0.05)) keeps the prediction step small enough for the arm's fast
    modes. A new rate moves the physics rate by :func:`physics_for_rate`. An error names the
    key (``rates.control_hz: ...``, as a config file's would); ``from_command_line``: the
    option too (``rates.control_hz (--rate): ...``).
    """
    pairs = {
        "controller.law": law,
        "rates.control_hz": rate,
        "rhc.horizon": horizon,
        "rhc.steps": steps,
        "rhc.kmax": kmax,
        "rhc.zeta": zeta,
        "camera.seed": seed,
        "scenario.disturbance": disturbance,
        "controller.clock": clock,
        "transport.can": can,
        "transport.zenoh_endpoint": zenoh_endpoint,
        "transport.zenoh_config": zenoh_config,
        "hardware.profile": profile,
    }
    given: dict[str, Any] = {k: v for k, v in pairs.items() if v is not None}
    options = {k: OPTIONS[k] for k in given}
    for key, value in (sets or {}).items():
        if key in given:
            raise ControllerConfigError(
                f"{OPTIONS[key]} and --set {key} both set {key}: give it once"
            )
        given[key], options[key] = value, "--set"
    try:
        return _overridden(cfg, given)
    except (HalConfigError, ControllerConfigError) as exc:
        named = _naming_the_option(exc, options) if from_command_line else exc
        if named is exc:
            raise
        raise named from None


def _overridden(cfg: RigConfig, given: dict[str, Any]) -> RigConfig:
    """``cfg`` with ``given`` and what follows from it (N from T, physics rate from rate)."""
    overrides = dict(given)
    horizon = given.get("rhc.horizon")
    if horizon is not None and "rhc.steps" not in given and _positive(horizon):
        # (any other horizon gets the type or range error of with_overrides)
        overrides["rhc.steps"] = max(cfg.rhc.steps, math.ceil(horizon / MAX_PREDICTION_STEP_S))
    rate = given.get("rates.control_hz")
    if rate is not None:
        if not _positive(rate):  # before physics_for_rate divides by it
            raise ControllerConfigError(
                f"rates.control_hz: must be a positive number, got {rate!r}"
            )
        physics = physics_for_rate(cfg, rate)
        if physics != cfg.rates.physics_hz:
            overrides["rates.physics_hz"] = physics
    return cfg.with_overrides(overrides) if overrides else cfg


def _positive(value: Any) -> bool:
    """A finite number above 0 (not a bool, not a string)."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    return number and math.isfinite(value) and value > 0


def _naming_the_option(exc: Exception, options: dict[str, str]) -> Exception:
    """``exc`` with the option after the key its message starts with (``key (--opt): ...``);
    ``exc`` itself when it names none of ``options``' keys (a rule between keys)."""
    text = str(exc)
    for key, option in options.items():
        if text.startswith(f"{key}:"):
            return type(exc)(f"{key} ({option}){text[len(key) :]}")
    return exc


def parse_sets(items: list[str], option: str = "--set") -> dict[str, Any]:
    """``["gains.kp=0.2", ...]`` -> ``{"gains.kp": 0.2}``; values are JSON, else strings. A
    malformed item or a key given twice is refused, naming ``option`` (what the user typed)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ControllerConfigError(
                f"{option} expects KEY=VALUE (e.g. gains.kp=0.2), got {item!r}"
            )
        if key in out:
            raise ControllerConfigError(f"{option}: {key} given twice; each key once")
        try:
            out[key] = json.loads(text)
        except RecursionError:  # lists in lists in lists ...: json.loads runs out of stack
            raise ControllerConfigError(
                f"{option}: {key}: lists nested too deep to read (a value is at most a matrix, "
                "[[a, b], [c, d]])"
            ) from None
        except ValueError:
            out[key] = text
    return out


_TOML_ESCAPES = {
    **{chr(c): f"\\u{c:04x}" for c in [*range(0x20), 0x7F]},
    "\b": "\\b",
    "\t": "\\t",
    "\n": "\\n",
    "\f": "\\f",
    "\r": "\\r",
    '"': '\\"',
    "\\": "\\\\",
}
"""How each character a TOML basic string cannot hold raw is written (a path read from
``"C:\\new"`` holds a newline)."""


def toml_value(value: Any) -> str:
    """One TOML value (bool, str, number or list of those)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):  # a basic string: TOML allows no control character raw
        return '"' + "".join(_TOML_ESCAPES.get(c, c) for c in value) + '"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return repr(value)


def config_toml(cfg: RigConfig, header: str | None = None) -> str:
    """The configuration as TOML that :func:`hal.config.load_config` reads back unchanged."""
    lines = [] if header is None else [f"# {header}"]
    for section, body in cfg.to_dict().items():
        lines.append(f"\n[{section}]" if lines else f"[{section}]")
        lines += [f"{key} = {toml_value(value)}" for key, value in body.items()]
    return "\n".join(lines) + "\n"
