"""Options shared by several subcommands and the config they build."""

from __future__ import annotations

import argparse
import math
from typing import Any

from hal.config import RigConfig, load_config
from rt_controller.errors import ControllerConfigError

MAX_PREDICTION_STEP_S = 0.05
"""Largest T/N chosen automatically when only --horizon is given."""


def add_config_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="rig configuration (TOML); default: embedded")


def add_law_options(p: argparse.ArgumentParser, default_law: str | None = None) -> None:
    p.add_argument(
        "--law",
        choices=("pbc", "ioc", "rhc"),
        default=default_law,
        help="control law for u: passivity-based (eq. 15), inverse-optimal (eq. 27) or "
        "receding-horizon (eq. 30); default: controller.law of the config",
    )
    p.add_argument("--rate", type=float, metavar="HZ", help="control rate (default 50)")
    p.add_argument("--horizon", type=float, metavar="T", help="RHC horizon T in s (default 0.1)")
    p.add_argument("--steps", type=int, metavar="N", help="RHC horizon steps N (default 10)")
    p.add_argument("--kmax", type=int, help="GMRES iterations per update (default 5)")
    p.add_argument("--zeta", type=float, help="C/GMRES continuation gain in 1/s (default 50)")


def add_scenario_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--no-disturbance", action="store_true", help="keep the target still (no jump at 3 s)"
    )
    p.add_argument("--seed", type=int, help="camera noise seed (camera.seed)")


def config_from_args(args: argparse.Namespace) -> RigConfig:
    """The config file (or defaults) with the command-line overrides applied and validated."""
    cfg = load_config(getattr(args, "config", None))
    overrides: dict[str, Any] = {}
    pairs = {
        "law": "controller.law",
        "rate": "rates.control_hz",
        "horizon": "rhc.horizon",
        "steps": "rhc.steps",
        "kmax": "rhc.kmax",
        "zeta": "rhc.zeta",
        "seed": "camera.seed",
    }
    for attr, key in pairs.items():
        value = getattr(args, attr, None)
        if value is not None:
            overrides[key] = value
    horizon = overrides.get("rhc.horizon")
    if horizon is not None and "rhc.steps" not in overrides:
        # Keep the prediction step T/N small enough for the arm's fast modes (Euler stability).
        overrides["rhc.steps"] = max(cfg.rhc.steps, math.ceil(horizon / MAX_PREDICTION_STEP_S))
    if getattr(args, "no_disturbance", False):
        overrides["scenario.disturbance"] = False
    rate = overrides.get("rates.control_hz")
    if rate is not None:
        if not rate > 0:
            raise ControllerConfigError(f"--rate must be positive, got {rate}")
        # Keep physics an integer multiple of the control rate and no slower than configured.
        physics = cfg.rates.physics_hz
        if abs(physics / rate - round(physics / rate)) > 1e-9 or physics < rate:
            overrides["rates.physics_hz"] = rate * math.ceil(physics / rate)
    return cfg.with_overrides(overrides) if overrides else cfg
