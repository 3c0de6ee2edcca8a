"""Options shared by several subcommands and the config they build."""

from __future__ import annotations

import argparse
import sys

from hal.config import LAW_NAMES, PROFILES, RigConfig, load_config
from rt_controller.config_rules import apply_overrides, parse_sets
from rt_controller.errors import ControllerConfigError


def add_config_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="rig configuration (TOML); default: embedded")


def add_set_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        dest="sets",
        help="override one config key, e.g. camera.model=analytic or gains.kp=0.2 "
        "(repeatable; VALUE is JSON, else a string; the rules of the named options apply)",
    )


def add_law_options(p: argparse.ArgumentParser, default_law: str | None = None) -> None:
    p.add_argument(
        "--law",
        choices=LAW_NAMES,
        default=default_law,
        help="control law for u: passivity-based (eq. 15), inverse-optimal (eq. 27) or "
        "receding-horizon (eq. 30); default: controller.law of the config",
    )
    d = RigConfig()  # each option's key; the file's value, else the embedded default, applies

    def key(name: str) -> str:
        section, _, field = name.partition(".")
        return f"{name}; default: the config's, embedded {getattr(getattr(d, section), field):g}"

    p.add_argument(
        "--rate", type=float, metavar="HZ", help=f"control rate ({key('rates.control_hz')})"
    )
    p.add_argument(
        "--horizon", type=float, metavar="T", help=f"RHC horizon T in s ({key('rhc.horizon')})"
    )
    p.add_argument(
        "--steps", type=int, metavar="N", help=f"RHC horizon steps N ({key('rhc.steps')})"
    )
    p.add_argument("--kmax", type=int, help=f"GMRES iterations per update ({key('rhc.kmax')})")
    p.add_argument(
        "--zeta", type=float, help=f"C/GMRES continuation gain in 1/s ({key('rhc.zeta')})"
    )


def add_scenario_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--no-disturbance", action="store_true", help="keep the target still (no jump at 3 s)"
    )
    p.add_argument("--seed", type=int, help="camera noise seed (camera.seed)")


def add_profile_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--profile",
        choices=PROFILES,
        help="hardware profile (hardware.profile): dsp, our DSP with SecOC (the default), or "
        "cia402, CANopen CiA 402 drives in cyclic synchronous torque (not authenticated)",
    )


RHC_ONLY_OPTIONS = ("horizon", "steps", "kmax", "zeta")
"""Options of :func:`add_law_options` that only the receding-horizon law reads."""


def config_from_args(args: argparse.Namespace) -> RigConfig:
    """The config file (or defaults) with the command-line overrides (the named options and
    each ``--set``) applied and validated (the rules:
    :func:`rt_controller.config_rules.apply_overrides`)."""
    return apply_overrides(
        load_config(getattr(args, "config", None)),
        law=getattr(args, "law", None),
        rate=getattr(args, "rate", None),
        horizon=getattr(args, "horizon", None),
        steps=getattr(args, "steps", None),
        kmax=getattr(args, "kmax", None),
        zeta=getattr(args, "zeta", None),
        seed=getattr(args, "seed", None),
        disturbance=False if getattr(args, "no_disturbance", False) else None,
        profile=getattr(args, "profile", None),
        sets=parse_sets(getattr(args, "sets", [])),
        from_command_line=True,
    )


def rhc_options_off_law(args: argparse.Namespace, cfg: RigConfig) -> list[str]:
    """The RHC-only options (``--horizon`` ...) the command line gives while the law in force
    in ``cfg`` (``--law``, else ``controller.law``) is not rhc: none when it is rhc."""
    if cfg.controller.law == "rhc":
        return []
    return [f"--{n}" for n in RHC_ONLY_OPTIONS if getattr(args, n, None) is not None]


def refuse_rhc_options_off_law(args: argparse.Namespace, cfg: RigConfig) -> None:
    """For a run whose law cannot change: an RHC-only option under another law would change
    nothing, so it is refused."""
    given = rhc_options_off_law(args, cfg)
    if given:
        law = cfg.controller.law
        raise ControllerConfigError(f"{given[0]}: only for the rhc law (the law in force is {law})")


def rhc_options_note(args: argparse.Namespace, cfg: RigConfig, prog: str) -> None:
    """For a run whose law can be switched while it runs (``hil param set controller.law``):
    an RHC-only option under another law is kept for that switch, and said on stderr."""
    given = rhc_options_off_law(args, cfg)
    if given:
        print(
            f"{prog}: note: {', '.join(given)} only take{'s' if len(given) == 1 else ''} effect "
            "once the law is switched to rhc "
            f"(the law in force is {cfg.controller.law}; hil param set controller.law=rhc)",
            file=sys.stderr,
        )
