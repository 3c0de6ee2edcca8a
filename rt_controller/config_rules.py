"""Configuration rules shared by the CLI, the experiment runner and the benchmarks.

One place for how command-line style overrides (``--law``, ``--rate``, ``--horizon`` ...) change
a :class:`~hal.config.RigConfig`, and for writing a config back as TOML for a child process.
Pure functions: no argparse, no I/O beyond returning text.
"""

from __future__ import annotations

import math
from typing import Any

from hal.config import RigConfig
from rt_controller.errors import ControllerConfigError

MAX_PREDICTION_STEP_S = 0.05
"""Largest T/N chosen automatically when only the horizon is given."""


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
) -> RigConfig:
    """``cfg`` with the given settings changed (None = keep), validated.

    Only the horizon given: N = max(rhc.steps, ceil(T / 0.05)) keeps the prediction step small
    enough for the arm's fast modes. A new rate moves the physics rate by
    :func:`physics_for_rate`.
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
    overrides: dict[str, Any] = {k: v for k, v in pairs.items() if v is not None}
    if horizon is not None and steps is None and math.isfinite(horizon) and horizon > 0:
        # (a NaN, infinite or non-positive horizon gets the range error of with_overrides)
        overrides["rhc.steps"] = max(cfg.rhc.steps, math.ceil(horizon / MAX_PREDICTION_STEP_S))
    if rate is not None:
        if not rate > 0:
            raise ControllerConfigError(f"--rate must be positive, got {rate}")
        physics = physics_for_rate(cfg, rate)
        if physics != cfg.rates.physics_hz:
            overrides["rates.physics_hz"] = physics
    return cfg.with_overrides(overrides) if overrides else cfg


def toml_value(value: Any) -> str:
    """One TOML value (bool, str, number or list of those)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
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
